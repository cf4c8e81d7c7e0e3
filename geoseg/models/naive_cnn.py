"""The 2015 "naive" patch classifier of thesis fig. 4.5, with sparse connection tables.

Architecture (Torch7 names from the figure; sizes from Farabet et al. 2013, the network the thesis
takes its single-scale branch from, since the thesis gives none):

======  ======================================  =======================  ===========
step    layer                                   connection table         output
======  ======================================  =======================  ===========
1       SpatialConvolutionMap 7x7, 3 → 16       full (every input)       16 x 40 x 40
2-3     ReLU, SpatialMaxPooling 2x2/2                                    16 x 20 x 20
4       SpatialConvolutionMap 7x7, 16 → 64      random, fan-in 8         64 x 14 x 14
5-6     ReLU, SpatialMaxPooling 2x2/2                                    64 x 7 x 7
7       SpatialConvolutionMap 7x7, 64 → 256     random, fan-in 32        256 x 1 x 1
8       Reshape(256)                                                     256
9-12    Linear(256, 512), ReLU, Linear(512, 8), LogSoftMax               8
======  ======================================  =======================  ===========

The input is a ``46 x 46`` patch (:data:`PATCH_SIZE`), the receptive field of the three 7x7
convolutions and two poolings, so the last convolution outputs a 256-vector. The patch of pixel
``(y, x)`` covers rows ``y - 23 .. y + 22`` and columns ``x - 23 .. x + 22``; outside the image the
border is replicated (:func:`extract_patches`).

Connection tables (Torch7 ``SpatialConvolutionMap``): each output map is connected to a subset of
the input maps. Table ``(out, fan_in)`` lists the input indices of each output: layer 1 is full
(``nn.tables.full``), layers 4 and 7 are random tables as Torch7's ``nn.tables.random(nin, nout,
fan_in)``: for each output, ``fan_in`` distinct inputs drawn without replacement, here from a
``numpy.random.Generator`` seeded by ``table_seed`` (default 0) so that the table is
reproducible; the tables are saved in the state dict as buffers. Only the connected weights exist
as parameters (``(out, fan_in, k, k)``); they are scattered into a dense kernel at run time.

Dense prediction (:meth:`NaiveCNN.dense`) is exactly the patch classifier applied at every pixel,
computed fully convolutionally with the "dilation trick" (equivalent to shift-and-stitch): every
pooling keeps stride 1 and the layers after the ``k``-th pooling are dilated by ``2**k``; the
Linear layers become 1x1 convolutions.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from geoseg.classes import NUM_CLASSES
from geoseg.errors import GeosegError, check_positive
from geoseg.models.checks import check_image_tensor

logger = logging.getLogger(__name__)

PATCH_SIZE = 46
KERNEL = 7


def full_table(n_in: int, n_out: int) -> np.ndarray:
    """Torch7 ``nn.tables.full``: `(n_out, n_in)` input indices, every output sees every input."""
    return np.tile(np.arange(n_in), (n_out, 1))


def random_table(n_in: int, n_out: int, fan_in: int, *, seed: int = 0) -> np.ndarray:
    """Torch7 ``nn.tables.random``: `(n_out, fan_in)` sorted distinct input indices per output."""
    if not 1 <= fan_in <= n_in:
        raise GeosegError(f"fan_in: expected 1 <= fan_in <= {n_in}, got {fan_in}")
    rng = np.random.default_rng(seed)
    return np.stack([np.sort(rng.choice(n_in, fan_in, replace=False)) for _ in range(n_out)])


class SpatialConvolutionMap(nn.Module):
    """Convolution with a sparse input/output connection table (Torch7 ``SpatialConvolutionMap``).

    Args:
        n_in: input maps.
        table: `(n_out, fan_in)` integer array, input indices feeding each output map.
        kernel: square kernel size.

    Forward:
        x: `(B, n_in, H, W)`; ``dilation`` keyword for the dense (dilated) form.
        Returns `(B, n_out, H - dilation * (kernel - 1), W - dilation * (kernel - 1))`.
    """

    def __init__(self, n_in: int, table: np.ndarray, kernel: int = KERNEL) -> None:
        super().__init__()
        table = np.asarray(table, dtype=np.int64)
        n_out, fan_in = table.shape
        self.n_in, self.n_out, self.kernel = n_in, n_out, kernel
        self.register_buffer("table", torch.from_numpy(table.copy()))
        bound = 1.0 / np.sqrt(fan_in * kernel * kernel)  # Torch7's reset()
        self.weight = nn.Parameter(
            torch.empty(n_out, fan_in, kernel, kernel).uniform_(-bound, bound)
        )
        self.bias = nn.Parameter(torch.empty(n_out).uniform_(-bound, bound))

    def dense_weight(self) -> torch.Tensor:
        """The `(n_out, n_in, k, k)` kernel with zeros where the table has no connection."""
        k = self.kernel
        index = self.table[:, :, None, None].expand(-1, -1, k, k)
        zeros = self.weight.new_zeros(self.n_out, self.n_in, k, k)
        return zeros.scatter(1, index, self.weight)

    def forward(self, x: torch.Tensor, *, dilation: int = 1) -> torch.Tensor:
        return F.conv2d(x, self.dense_weight(), self.bias, dilation=dilation)


class NaiveCNN(nn.Module):
    """Patch classifier of thesis fig. 4.5 (see the module docstring for sizes and tables).

    Args:
        num_classes: output classes (8 in the thesis).
        in_channels: image channels.
        table_seed: seed of the random connection tables of layers 4 and 7.

    Forward:
        patches: `(B, 3, 46, 46)` normalised image patches.
        Returns ``{"log_probs": (B, num_classes)}``.
    """

    patch_size = PATCH_SIZE

    def __init__(
        self, *, num_classes: int = NUM_CLASSES, in_channels: int = 3, table_seed: int = 0
    ) -> None:
        super().__init__()
        check_positive("num_classes", num_classes)
        self.num_classes = num_classes
        self.in_channels = in_channels
        self.conv1 = SpatialConvolutionMap(in_channels, full_table(in_channels, 16))
        self.conv2 = SpatialConvolutionMap(16, random_table(16, 64, 8, seed=table_seed))
        self.conv3 = SpatialConvolutionMap(64, random_table(64, 256, 32, seed=table_seed + 1))
        self.fc1 = nn.Linear(256, 512)
        self.fc2 = nn.Linear(512, num_classes)

    def forward(self, patches: torch.Tensor) -> dict[str, torch.Tensor]:
        check_image_tensor("patches", patches, channels=self.in_channels)
        if patches.shape[-2:] != (PATCH_SIZE, PATCH_SIZE):
            raise GeosegError(
                f"patches: expected (B, {self.in_channels}, {PATCH_SIZE}, {PATCH_SIZE}), "
                f"got {tuple(patches.shape)}; use dense() for whole images"
            )
        x = F.max_pool2d(F.relu(self.conv1(patches)), 2)
        x = F.max_pool2d(F.relu(self.conv2(x)), 2)
        x = self.conv3(x).flatten(1)  # Reshape(256)
        x = self.fc2(F.relu(self.fc1(x)))
        return {"log_probs": F.log_softmax(x, dim=1)}

    def _dense(self, padded: torch.Tensor) -> torch.Tensor:
        x = F.max_pool2d(F.relu(self.conv1(padded)), 2, stride=1)
        x = F.max_pool2d(F.relu(self.conv2(x, dilation=2)), 2, stride=1, dilation=2)
        x = self.conv3(x, dilation=4)
        x = F.conv2d(x, self.fc1.weight[:, :, None, None], self.fc1.bias)
        x = F.conv2d(F.relu(x), self.fc2.weight[:, :, None, None], self.fc2.bias)
        return F.log_softmax(x, dim=1)

    def dense(self, image: torch.Tensor, *, band_rows: int | None = None) -> torch.Tensor:
        """Per-pixel log-probabilities, equal to the patch classifier at every pixel.

        Args:
            image: `(B, 3, H, W)` normalised image.
            band_rows: process horizontal bands of this many output rows to bound memory
                (``None``: the whole image at once; the result is identical).

        Returns:
            `(B, num_classes, H, W)` log-probabilities.
        """
        check_image_tensor("image", image, channels=self.in_channels)
        lo, hi = PATCH_SIZE // 2, PATCH_SIZE - 1 - PATCH_SIZE // 2
        padded = F.pad(image, (lo, hi, lo, hi), mode="replicate")
        h = image.shape[-2]
        if band_rows is None or band_rows >= h:
            return self._dense(padded)
        check_positive("band_rows", band_rows)
        bands = [
            self._dense(padded[:, :, y : min(y + band_rows, h) + PATCH_SIZE - 1])
            for y in range(0, h, band_rows)
        ]
        return torch.cat(bands, dim=2)


class NaiveDense(nn.Module):
    """Dense (whole-image) form of a :class:`NaiveCNN`, the module exported to ONNX and served.

    Forward:
        x: `(B, 3, H, W)` normalised image.
        Returns ``{"log_probs": (B, num_classes, H, W)}``.
    """

    def __init__(self, net: NaiveCNN) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"log_probs": self.net.dense(x)}


def extract_patches(image: torch.Tensor, yx: torch.Tensor) -> torch.Tensor:
    """Cut the 46x46 patches centred on pixels, with replicated borders (as :meth:`NaiveCNN.dense`).

    Args:
        image: `(3, H, W)` normalised image.
        yx: `(N, 2)` integer pixel coordinates (row, column).

    Returns:
        `(N, 3, 46, 46)` patches; patch ``i`` covers rows ``y - 23 .. y + 22``.
    """
    lo, hi = PATCH_SIZE // 2, PATCH_SIZE - 1 - PATCH_SIZE // 2
    padded = F.pad(image[None], (lo, hi, lo, hi), mode="replicate")[0]
    return torch.stack([padded[:, y : y + PATCH_SIZE, x : x + PATCH_SIZE] for y, x in yx.tolist()])


def naive_cnn(
    *, num_classes: int = NUM_CLASSES, in_channels: int = 3, table_seed: int = 0
) -> NaiveCNN:
    """Build the naive patch classifier (randomly initialised); see :class:`NaiveCNN`."""
    return NaiveCNN(num_classes=num_classes, in_channels=in_channels, table_seed=table_seed)
