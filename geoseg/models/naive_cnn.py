"""The 2015 "naive" patch classifier of thesis fig. 4.5, with sparse connection tables.

Three 7x7 convolutions (Torch7 ``SpatialConvolutionMap``: each output map connected to a
subset of the inputs, random tables seeded by ``table_seed`` and saved as buffers) with two
poolings, then two linear layers, classify the ``46 x 46`` patch (:data:`PATCH_SIZE`) around a
pixel into the 8 classes; outside the image the border is replicated
(:func:`extract_patches`). :meth:`NaiveCNN.dense` applies exactly the patch classifier at every
pixel, fully convolutionally (the dilation trick). The layer table, where the sizes come from and
the connection tables: ``docs/networks.md`` ("The naive patch CNN").
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
