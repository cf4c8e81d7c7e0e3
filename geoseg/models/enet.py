"""ENet (Paszke et al. 2016): bottleneck blocks, the encoder trunk, the decoder head, the network.

For ``num_classes=8`` the network has 359,199 parameters (the paper reports ~0.37 M). It is split
into :class:`ENetTrunk` (layers 1-21, up to bottleneck 3.6: the "layer-21" feature map the joint
network and the relocalisation heads use) and :class:`ENetHead` (layers 22-29), so that
:mod:`geoseg.models.joint` can share the trunk and duplicate the head. Sides that are not
multiples of 8 are padded (replicate, bottom and right) and the logits cropped back to
``(H, W)``; ``features`` is the padded input's layer-21 map, ``(B, 128, ceil(H / 8),
ceil(W / 8))``. The layer table and the CPU training-speed profile that kept the layers in their
plain torch form: ``docs/networks.md`` ("ENet").
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from geoseg.classes import NUM_CLASSES
from geoseg.errors import ConfigError, check_positive
from geoseg.models.checks import check_image_tensor

logger = logging.getLogger(__name__)

FEATURE_CHANNELS = 128  # channels of the layer-21 map
STRIDE = 8  # total downsampling of the encoder


def _act(channels: int, relu: bool) -> nn.Module:
    return nn.ReLU(inplace=True) if relu else nn.PReLU(channels)


class InitialBlock(nn.Module):
    """ENet's initial block: 3x3 stride-2 conv with 13 filters ∥ 2x2 max pooling, concatenated.

    Input `(B, 3, H, W)` (H, W even) → output `(B, 16, H/2, W/2)`.
    """

    def __init__(self, in_channels: int = 3, out_channels: int = 16) -> None:
        super().__init__()
        self.conv = nn.Conv2d(
            in_channels, out_channels - in_channels, 3, stride=2, padding=1, bias=False
        )
        self.pool = nn.MaxPool2d(2, stride=2)
        self.bn = nn.BatchNorm2d(out_channels)
        self.act = nn.PReLU(out_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(torch.cat([self.conv(x), self.pool(x)], dim=1)))


class RegularBottleneck(nn.Module):
    """Regular, dilated or asymmetric bottleneck, `(B, C, H, W)` → `(B, C, H, W)`.

    Args:
        channels: input and output channels C.
        kind: ``"regular"`` (3x3), ``"dilated"`` (3x3 with ``dilation``) or ``"asymmetric"``
            (``kernel`` x 1 followed by 1 x ``kernel``).
        dilation: dilation of the dilated 3x3 convolution.
        kernel: size of the asymmetric convolutions.
        dropout: spatial dropout probability.
        relu: ReLU (decoder) instead of PReLU (encoder).
    """

    def __init__(
        self,
        channels: int,
        *,
        kind: str = "regular",
        dilation: int = 1,
        kernel: int = 5,
        dropout: float = 0.1,
        relu: bool = False,
    ) -> None:
        super().__init__()
        inner = channels // 4
        if kind == "asymmetric":
            middle: nn.Module = nn.Sequential(
                nn.Conv2d(inner, inner, (kernel, 1), padding=(kernel // 2, 0), bias=False),
                nn.Conv2d(inner, inner, (1, kernel), padding=(0, kernel // 2), bias=False),
            )
        elif kind in ("regular", "dilated"):
            d = dilation if kind == "dilated" else 1
            middle = nn.Conv2d(inner, inner, 3, padding=d, dilation=d, bias=False)
        else:
            raise ValueError(f"kind: expected regular, dilated or asymmetric, got {kind!r}")
        self.ext = nn.Sequential(
            nn.Conv2d(channels, inner, 1, bias=False),
            nn.BatchNorm2d(inner),
            _act(inner, relu),
            middle,
            nn.BatchNorm2d(inner),
            _act(inner, relu),
            nn.Conv2d(inner, channels, 1, bias=False),
            nn.BatchNorm2d(channels),
            nn.Dropout2d(dropout),
        )
        self.out_act = _act(channels, relu)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out_act(x + self.ext(x))


class DownsamplingBottleneck(nn.Module):
    """Downsampling bottleneck, `(B, Cin, H, W)` → `(B, Cout, H/2, W/2)` and pooling indices.

    The main branch max-pools (keeping the indices for the decoder) and zero-pads the channels;
    the extension branch starts with a 2x2 stride-2 convolution.
    """

    def __init__(self, in_channels: int, out_channels: int, *, dropout: float = 0.1) -> None:
        super().__init__()
        inner = in_channels // 4
        self.extra_channels = out_channels - in_channels
        self.pool = nn.MaxPool2d(2, stride=2, return_indices=True)
        self.ext = nn.Sequential(
            nn.Conv2d(in_channels, inner, 2, stride=2, bias=False),
            nn.BatchNorm2d(inner),
            nn.PReLU(inner),
            nn.Conv2d(inner, inner, 3, padding=1, bias=False),
            nn.BatchNorm2d(inner),
            nn.PReLU(inner),
            nn.Conv2d(inner, out_channels, 1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.Dropout2d(dropout),
        )
        self.out_act = nn.PReLU(out_channels)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        main, indices = self.pool(x)
        main = F.pad(main, (0, 0, 0, 0, 0, self.extra_channels))
        return self.out_act(main + self.ext(x)), indices


class UpsamplingBottleneck(nn.Module):
    """Upsampling bottleneck, `(B, Cin, h, w)` + indices → `(B, Cout, 2h, 2w)`.

    The main branch is a 1x1 convolution followed by max-unpooling with the indices of the matching
    encoder downsampling block; the extension branch uses a 3x3 stride-2 transposed convolution.
    """

    def __init__(self, in_channels: int, out_channels: int, *, dropout: float = 0.1) -> None:
        super().__init__()
        inner = in_channels // 4
        self.main_conv = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, 1, bias=False), nn.BatchNorm2d(out_channels)
        )
        self.unpool = nn.MaxUnpool2d(2, stride=2)
        self.ext = nn.Sequential(
            nn.Conv2d(in_channels, inner, 1, bias=False),
            nn.BatchNorm2d(inner),
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(inner, inner, 3, stride=2, padding=1, output_padding=1, bias=False),
            nn.BatchNorm2d(inner),
            nn.ReLU(inplace=True),
            nn.Conv2d(inner, out_channels, 1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.Dropout2d(dropout),
        )
        self.out_act = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
        main = self.unpool(self.main_conv(x), indices)
        return self.out_act(main + self.ext(x))


def _stage_2_3(prefix: str, dropout: float) -> list[tuple[str, nn.Module]]:
    """Bottlenecks x.1-x.8 of stages 2 and 3 (128 channels), named ``{prefix}_1`` .. ``_8``."""
    specs = [
        ("regular", 1),
        ("dilated", 2),
        ("asymmetric", 1),
        ("dilated", 4),
        ("regular", 1),
        ("dilated", 8),
        ("asymmetric", 1),
        ("dilated", 16),
    ]
    return [
        (
            f"{prefix}_{i + 1}",
            RegularBottleneck(FEATURE_CHANNELS, kind=kind, dilation=d, kernel=5, dropout=dropout),
        )
        for i, (kind, d) in enumerate(specs)
    ]


class ENetTrunk(nn.Module):
    """ENet layers 1-21 (initial block to bottleneck 3.6), shared by ENet and the joint network.

    Layer counting (one layer per block): initial = 1, 1.0 = 2, 1.1-1.4 = 3-6, 2.0 = 7,
    2.1-2.8 = 8-15, 3.1-3.8 = 16-23, so layer 21 is bottleneck 3.6.

    Args:
        in_channels: image channels.
    """

    def __init__(self, in_channels: int = 3) -> None:
        super().__init__()
        self.initial = InitialBlock(in_channels, 16)
        self.down1 = DownsamplingBottleneck(16, 64, dropout=0.01)
        self.stage1 = nn.Sequential(*[RegularBottleneck(64, dropout=0.01) for _ in range(4)])
        self.down2 = DownsamplingBottleneck(64, FEATURE_CHANNELS, dropout=0.1)
        stage2 = _stage_2_3("b2", 0.1)
        stage3 = _stage_2_3("b3", 0.1)[:6]  # 3.1-3.6; 3.7 and 3.8 belong to the head
        self.stage2_3 = nn.Sequential(OrderedDict(stage2 + stage3))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Run layers 1-21.

        Args:
            x: `(B, 3, H, W)` normalised image, H and W multiples of 8.

        Returns:
            ``(features, indices1, indices2)``: the layer-21 map `(B, 128, H/8, W/8)` and the
            max-pooling indices of bottlenecks 1.0 `(B, 16, H/4, W/4)` and 2.0
            `(B, 64, H/8, W/8)`.
        """
        x = self.initial(x)
        x, indices1 = self.down1(x)
        x = self.stage1(x)
        x, indices2 = self.down2(x)
        return self.stage2_3(x), indices1, indices2


class ENetHead(nn.Module):
    """ENet layers 22-29 (3.7, 3.8, stage 4, stage 5, fullconv) producing ``out_channels`` maps.

    Args:
        out_channels: channels of the full-resolution output (classes, or 3 for normals).
    """

    def __init__(self, out_channels: int) -> None:
        super().__init__()
        self.stage3_end = nn.Sequential(OrderedDict(_stage_2_3("b3", 0.1)[6:]))
        self.up4 = UpsamplingBottleneck(FEATURE_CHANNELS, 64, dropout=0.1)
        self.stage4 = nn.Sequential(*[RegularBottleneck(64, relu=True) for _ in range(2)])
        self.up5 = UpsamplingBottleneck(64, 16, dropout=0.1)
        self.stage5 = RegularBottleneck(16, relu=True)
        self.fullconv = nn.ConvTranspose2d(16, out_channels, 2, stride=2)

    def forward(
        self, features: torch.Tensor, indices1: torch.Tensor, indices2: torch.Tensor
    ) -> torch.Tensor:
        """Decode the layer-21 map.

        Args:
            features: `(B, 128, h, w)` layer-21 map.
            indices1: `(B, 16, 2h, 2w)` pooling indices of bottleneck 1.0.
            indices2: `(B, 64, h, w)` pooling indices of bottleneck 2.0.

        Returns:
            `(B, out_channels, 8h, 8w)` output maps.
        """
        x = self.stage3_end(features)
        x = self.stage4(self.up4(x, indices2))
        x = self.stage5(self.up5(x, indices1))
        return self.fullconv(x)


def pad_to_multiple(x: torch.Tensor, multiple: int = STRIDE) -> torch.Tensor:
    """Replicate-pad `(B, C, H, W)` on the bottom and right so that H and W are multiples."""
    h, w = x.shape[-2], x.shape[-1]
    pad_h = (h + multiple - 1) // multiple * multiple - h  # ceil-div form: export-friendly
    pad_w = (w + multiple - 1) // multiple * multiple - w
    return F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")


def crop_to(x: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """The top-left `(B, C, h, w)` of `(B, C, H, W)`, H >= h, W >= w (undoes
    :func:`pad_to_multiple`). A negative pad: one node in an ONNX graph, where ``x[..., :h, :w]``
    is a ``Slice`` per axis, each a full copy in onnxruntime."""
    return F.pad(x, (0, w - x.shape[-1], 0, h - x.shape[-2]))


class ENet(nn.Module):
    """ENet semantic segmentation network.

    Args:
        num_classes: output classes C.
        in_channels: image channels.

    Forward:
        x: `(B, 3, H, W)` float normalised image, any H, W >= 1 (padded to multiples of 8).

        Returns ``{"logits": (B, C, H, W), "features": (B, 128, ceil(H/8), ceil(W/8))}``.
    """

    def __init__(self, *, num_classes: int = NUM_CLASSES, in_channels: int = 3) -> None:
        super().__init__()
        check_positive("num_classes", num_classes)
        self.num_classes = num_classes
        self.in_channels = in_channels
        self.trunk = ENetTrunk(in_channels)
        self.head = ENetHead(num_classes)
        self._frozen: tuple[str, ...] = ()

    def freeze(self, names: Sequence[str] = ("trunk",)) -> ENet:
        """Freeze the named submodules (``trunk``, ``trunk.stage1``, ``head.up4``...) and
        unfreeze the others, to fine-tune the rest alone.

        Freezing the ``trunk`` (layers 1-21) keeps its layer-21 features, which the normals and
        relocalisation heads read, so every head trained on them stays valid. Frozen parameters
        get ``requires_grad=False`` and the frozen modules stay in eval mode (batch-norm
        statistics and dropout fixed) even when ``train()`` is called.

        Raises:
            ConfigError: a name that is not a submodule (the error lists the trunk's and head's).

        Returns:
            ``self``.
        """
        modules = dict(self.named_modules())
        unknown = [n for n in names if not n or n not in modules]
        if unknown:
            known = [n for n in modules if n.count(".") <= 1 and n]
            raise ConfigError(f"freeze: no submodule {unknown} in ENet; e.g. {known}")
        self._frozen = tuple(names)
        for p in self.parameters():
            p.requires_grad_(True)
        for name in self._frozen:
            for p in modules[name].parameters():
                p.requires_grad_(False)
        return self.train(self.training)

    def train(self, mode: bool = True) -> ENet:
        super().train(mode)
        modules = dict(self.named_modules())
        for name in self._frozen:
            modules[name].eval()
        return self

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        check_image_tensor("x", x, channels=self.in_channels)
        h, w = x.shape[-2], x.shape[-1]
        features, indices1, indices2 = self.trunk(pad_to_multiple(x))
        logits = crop_to(self.head(features, indices1, indices2), h, w)
        return {"logits": logits, "features": features}


def enet(*, num_classes: int = NUM_CLASSES, in_channels: int = 3) -> ENet:
    """Build an ENet (randomly initialised); see :class:`ENet`."""
    return ENet(num_classes=num_classes, in_channels=in_channels)


def count_parameters(module: nn.Module, *, trainable_only: bool = False) -> int:
    """Number of parameters of ``module`` (all, or only those with ``requires_grad``)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)
