"""Export-time rewrites of the ENet blocks into the forms onnxruntime runs fast on the CPU.

onnxruntime's CPU provider runs convolutions, pooling, nearest upsampling, equal-shape
``Add``/``Mul`` and ``Relu`` in a blocked channel layout (NCHWc) and copies the tensor in and out
of it around every other node; the plain ENet graph does so around each PReLU, channel padding
and unpooling, and runs its transposed convolutions single-threaded. The rewrites keep the
computation and change its form: PReLU as depthwise 1x1 convolutions, the initial block and the
downsampling padding as convolutions, max-unpooling as ``nearest_upsample(main) * mask`` with a
*switch mask* instead of pooling indices, transposed convolutions as sub-pixel convolutions, pixel
shuffles as ``fold`` (ONNX ``Col2Im``), the normals' L2 normalisation as a sum of squares. Each
rewrite and what it bought: ``docs/onnx_operators.md``.

Outputs equal the original module's up to float rounding (batch norms folded), so a near-tie in a
max-pooling window can move a switch: compare by argmax agreement and mean errors, as for any
export. The rewritten modules fold the batch-norm running statistics: they are for inference only.
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from geoseg.models.enet import DownsamplingBottleneck, InitialBlock, UpsamplingBottleneck
from geoseg.models.joint import UnitNormals


def _folded_batch_norm(bn: nn.BatchNorm2d) -> tuple[torch.Tensor, torch.Tensor]:
    """``(scale, shift)`` `(C,)` with ``bn(x) = scale * x + shift`` in eval mode."""
    scale = bn.weight.detach() / torch.sqrt(bn.running_var + bn.eps)
    return scale, bn.bias.detach() - bn.running_mean * scale


def _per_output(weight: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Scale a conv weight `(Cout, ...)` row by row."""
    return weight * scale.reshape(-1, *([1] * (weight.ndim - 1)))


def _channel_placement(out_channels: int, in_channels: int, offset: int = 0) -> torch.Tensor:
    """1x1 conv weight `(Cout, Cin, 1, 1)` copying input channel i to output ``offset + i``."""
    weight = torch.zeros(out_channels, in_channels, 1, 1)
    index = torch.arange(in_channels)
    weight[offset + index, index, 0, 0] = 1.0
    return weight


def _depthwise(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Per-channel scaling `(B, C, H, W)` by ``weight`` `(C, 1, 1, 1)` as a depthwise 1x1 conv."""
    return F.conv2d(x, weight, groups=weight.shape[0])


def depth_to_space(x: torch.Tensor) -> torch.Tensor:
    """``pixel_shuffle(x, 2)``: `(B, 4 C, h, w)` → `(B, C, 2h, 2w)`, as ``fold`` (ONNX ``Col2Im``)
    with 2x2 blocks at stride 2: each output pixel is one input value, channel 4 c + k going to
    window position k of channel c.

    onnxruntime's ``DepthToSpace`` is a generic 6-D transpose, about ten times slower here.
    """
    b, c4, h, w = x.shape
    return F.fold(x.reshape(b, c4, h * w), (2 * h, 2 * w), 2, stride=2)


class DepthwisePReLU(nn.Module):
    """``PReLU`` as ``x + (1 - a) relu(-x)``; on 4-D inputs the scalings are depthwise 1x1 convs.

    Args:
        prelu: the module to replace (one slope per channel or one for all; copied).
    """

    def __init__(self, prelu: nn.PReLU) -> None:
        super().__init__()
        self.register_buffer("slope", prelu.weight.detach().clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, C, ...) -> (B, C, ...)``."""
        c = x.shape[1]
        keep = (1.0 - self.slope).expand(c)  # the negative part's (1 - a)
        if x.ndim != 4:
            return x + keep.reshape((-1,) + (1,) * (x.ndim - 2)) * torch.relu(-x)
        negate = -torch.ones(c, 1, 1, 1, dtype=x.dtype, device=x.device)
        return x + _depthwise(torch.relu(_depthwise(x, negate)), keep.reshape(c, 1, 1, 1))


class InitialBlockForExport(nn.Module):
    """:class:`~geoseg.models.enet.InitialBlock` as two convolutions summed (batch norm folded).

    `(B, Cin, H, W)` → `(B, 16, H/2, W/2)`.
    """

    def __init__(self, block: InitialBlock) -> None:
        super().__init__()
        conv = block.conv
        filters, in_channels = conv.weight.shape[:2]
        scale, shift = _folded_batch_norm(block.bn)
        weight = torch.zeros(filters + in_channels, in_channels, 3, 3)
        weight[:filters] = conv.weight.detach()
        self.register_buffer("conv_weight", _per_output(weight, scale))
        self.register_buffer("conv_bias", shift)
        place = _channel_placement(filters + in_channels, in_channels, offset=filters)
        self.register_buffer("pool_weight", _per_output(place, scale))
        self.act = block.act

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        conv = F.conv2d(x, self.conv_weight, self.conv_bias, stride=2, padding=1)
        return self.act(conv + F.conv2d(F.max_pool2d(x, 2, 2), self.pool_weight))


def window_priority(height: int, width: int, dtype: torch.dtype) -> torch.Tensor:
    """`(H, W)` rank of each pixel in its 2x2 window, 4 for the first in row-major order down to
    1 for the last: ``[[4, 3], [2, 1]]`` tiled (H, W even)."""
    tile = torch.tensor([[4.0, 3.0], [2.0, 1.0]], dtype=dtype)
    return tile.repeat(height // 2, width // 2)


def _upsample2(x: torch.Tensor) -> torch.Tensor:
    """Nearest-neighbour 2x upsampling `(B, C, h, w)` → `(B, C, 2h, 2w)`."""
    return F.interpolate(x, scale_factor=2.0, mode="nearest")


def switch_mask(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """2x2 stride-2 max pooling and its switch mask.

    Args:
        x: `(B, C, H, W)`, H and W even.

    Returns:
        ``(pooled, mask)``: `(B, C, H/2, W/2)` maxima and `(B, C, H, W)` float mask, 1 at the first
        maximum of each window in row-major order (where torch's max-pooling index points).

    All at full resolution, exact: the maxima of each window (``x`` equal to its upsampled
    pooling) get their :func:`window_priority`, and a second pooling of those priorities keeps
    the first of tied maxima. Pooling and nearest upsampling run in onnxruntime's blocked layout;
    the earlier form (windows unshuffled to channels by a grouped stride-2 convolution, a grouped
    1x1 convolution keeping the first of four) ran outside it, ~4 GMAC/s (docs/onnx_operators.md).
    """
    pooled = F.max_pool2d(x, 2, 2)
    priority = window_priority(x.shape[-2], x.shape[-1], x.dtype).to(x.device)
    ranked = (x == _upsample2(pooled)).to(x.dtype) * priority  # 0 where not a maximum
    first = ranked == _upsample2(F.max_pool2d(ranked, 2, 2))
    return pooled, first.to(x.dtype)


class PixelShuffleConvTranspose(nn.Module):
    """``ConvTranspose2d(C, C', 2, stride=2)`` (ENet's last layer) as a 1x1 convolution to
    ``4 C'`` channels and a pixel shuffle (:func:`depth_to_space`): `(B, C, h, w)` →
    `(B, C', 2h, 2w)`. Output pixel ``(2y + i, 2x + j)`` of channel c is kernel tap ``(i, j)``
    applied to input pixel ``(y, x)``: channel ``4 c + 2 i + j`` of the 1x1 convolution.

    onnxruntime runs the transposed convolution as a GEMM plus a single-threaded col2im, outside
    its blocked layout (~4.6 ms of the joint network's ~57 ms at 640x480, one thread).
    """

    def __init__(self, conv: nn.ConvTranspose2d) -> None:
        super().__init__()
        weight = conv.weight.detach()  # (Cin, Cout, 2, 2)
        in_channels, out_channels = weight.shape[:2]
        self.register_buffer(
            "weight", weight.permute(1, 2, 3, 0).reshape(4 * out_channels, in_channels, 1, 1)
        )
        bias = conv.bias.detach() if conv.bias is not None else torch.zeros(out_channels)
        self.register_buffer("bias", bias.repeat_interleave(4))

    @staticmethod
    def applies(conv: nn.ConvTranspose2d) -> bool:
        """Whether ``conv`` is a plain 2x2 stride-2 transposed convolution."""
        return (
            conv.kernel_size == (2, 2)
            and conv.stride == (2, 2)
            and conv.padding == (0, 0)
            and conv.output_padding == (0, 0)
            and conv.dilation == (1, 1)
            and conv.groups == 1
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return depth_to_space(F.conv2d(x, self.weight, self.bias))


class DownsamplingForExport(nn.Module):
    """:class:`~geoseg.models.enet.DownsamplingBottleneck` returning a switch mask for indices.

    `(B, Cin, H, W)` → ``(out (B, Cout, H/2, W/2), mask (B, Cin, H, W))``.
    """

    def __init__(self, block: DownsamplingBottleneck) -> None:
        super().__init__()
        in_channels = block.ext[0].in_channels
        self.register_buffer(
            "pad_weight", _channel_placement(in_channels + block.extra_channels, in_channels)
        )
        # an identity depthwise conv: onnxruntime then keeps the mask in its blocked layout
        self.register_buffer("identity", torch.ones(in_channels, 1, 1, 1))
        self.ext = block.ext
        self.out_act = block.out_act

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pooled, mask = switch_mask(x)
        main = F.conv2d(pooled, self.pad_weight)
        return self.out_act(main + self.ext(x)), _depthwise(mask, self.identity)


class SubPixelTransposedConv(nn.Module):
    """``ConvTranspose2d(C, C', 3, stride=2, padding=1, output_padding=1)`` (+ ``BatchNorm2d``)
    as a 2x2 convolution to ``4 C'`` channels and ``pixel_shuffle``: `(B, C, h, w)` →
    `(B, C', 2h, 2w)`. Output pixel ``(2y + i, 2x + j)`` takes kernel taps ``ky = 1`` (i = 0) or
    ``ky = 2, 0`` from input rows ``y, y + 1`` (i = 1), and the same for columns.

    Args:
        conv: the transposed convolution (bias allowed).
        bn: a batch norm applied to its output, folded in (optional).
        relu: apply ReLU before the shuffle (it commutes with it).
    """

    # (output parity, input offset) -> kernel tap
    _TAPS = {(0, 0): 1, (1, 0): 2, (1, 1): 0}

    def __init__(
        self, conv: nn.ConvTranspose2d, bn: nn.BatchNorm2d | None = None, *, relu: bool = False
    ) -> None:
        super().__init__()
        if (
            conv.kernel_size != (3, 3)
            or conv.stride != (2, 2)
            or conv.padding != (1, 1)
            or conv.output_padding != (1, 1)
            or conv.dilation != (1, 1)
            or conv.groups != 1
        ):
            raise ValueError(f"conv: expected a 3x3 stride-2 transposed conv, got {conv}")
        weight = conv.weight.detach()  # (Cin, Cout, 3, 3)
        in_channels, out_channels = weight.shape[:2]
        bias = conv.bias.detach() if conv.bias is not None else torch.zeros(out_channels)
        scale, shift = _folded_batch_norm(bn) if bn is not None else (1.0, 0.0)
        sub = torch.zeros(out_channels, 2, 2, in_channels, 2, 2)
        for (i, dy), ky in self._TAPS.items():
            for (j, dx), kx in self._TAPS.items():
                sub[:, i, j, :, dy, dx] = weight[:, :, ky, kx].T
        sub = sub.reshape(4 * out_channels, in_channels, 2, 2)  # pixel_shuffle's channel order
        scale4 = torch.as_tensor(scale).expand(out_channels).repeat_interleave(4)
        self.register_buffer("weight", _per_output(sub, scale4))
        self.register_buffer("bias", (bias * scale + shift).repeat_interleave(4))
        self.relu = relu

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.conv2d(F.pad(x, (0, 1, 0, 1)), self.weight, self.bias)
        return depth_to_space(torch.relu(y) if self.relu else y)


class UpsamplingForExport(nn.Module):
    """:class:`~geoseg.models.enet.UpsamplingBottleneck` unpooling with a switch mask.

    ``(x (B, Cin, h, w), mask (B, Cout, 2h, 2w))`` → `(B, Cout, 2h, 2w)`.
    """

    def __init__(self, block: UpsamplingBottleneck) -> None:
        super().__init__()
        layers = list(block.ext)
        at = next(i for i, m in enumerate(layers) if isinstance(m, nn.ConvTranspose2d))
        bn, relu = layers[at + 1], layers[at + 2]
        if not isinstance(bn, nn.BatchNorm2d) or not isinstance(relu, nn.ReLU):
            raise ValueError("block: expected ConvTranspose2d, BatchNorm2d, ReLU in its extension")
        self.main_conv = block.main_conv
        self.ext = nn.Sequential(
            *layers[:at], SubPixelTransposedConv(layers[at], bn, relu=True), *layers[at + 3 :]
        )
        self.out_act = block.out_act

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        main = _upsample2(self.main_conv(x)) * mask
        return self.out_act(main + self.ext(x))


class UnitNormalsForExport(nn.Module):
    """:class:`~geoseg.models.joint.UnitNormals` as ``x / max(sqrt(sum_c x^2), eps)``:
    `(B, 3, H, W)` → `(B, 3, H, W)`, the same arithmetic as ``F.normalize``. onnxruntime's
    ``ReduceL2`` over three channels runs ~1.5x slower than ``Mul``, ``ReduceSum``, ``Sqrt``
    (docs/onnx_operators.md)."""

    def __init__(self, unit: UnitNormals) -> None:
        super().__init__()
        self.eps = unit.eps

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return raw / torch.sqrt((raw * raw).sum(1, keepdim=True)).clamp_min(self.eps)


_REWRITES: dict[type, type] = {
    InitialBlock: InitialBlockForExport,
    DownsamplingBottleneck: DownsamplingForExport,
    UpsamplingBottleneck: UpsamplingForExport,
    nn.PReLU: DepthwisePReLU,
    nn.ConvTranspose2d: PixelShuffleConvTranspose,
    UnitNormals: UnitNormalsForExport,
}


def _rewrite_children(module: nn.Module) -> None:
    for name, child in module.named_children():
        rewrite = _REWRITES.get(type(child))
        if rewrite is PixelShuffleConvTranspose and not rewrite.applies(child):
            rewrite = None
        if rewrite is not None:
            child = rewrite(child)
            setattr(module, name, child)
        _rewrite_children(child)


def needs_rewrite(model: nn.Module) -> bool:
    """Whether ``model`` has modules that :func:`rewrite_for_onnxruntime` replaces."""
    return any(
        type(m) in _REWRITES
        and not (isinstance(m, nn.ConvTranspose2d) and not PixelShuffleConvTranspose.applies(m))
        for m in model.modules()
    )


def rewrite_for_onnxruntime(model: nn.Module) -> nn.Module:
    """A copy of ``model`` (eval mode) with its ENet blocks and PReLUs in their export forms.

    Downsampling and upsampling blocks are rewritten together (the masks replace the indices
    between them), so a model must hold both or neither, as ENet and the joint network do.

    Args:
        model: any module; returned as is when nothing needs rewriting.

    Returns:
        The rewritten copy (``model`` itself is left untouched).
    """
    if not needs_rewrite(model):
        return model
    kinds = {type(m) for m in model.modules()}
    if (DownsamplingBottleneck in kinds) != (UpsamplingBottleneck in kinds):
        raise ValueError(
            "model: has downsampling without upsampling blocks (or the reverse); the pooling "
            "indices they pass cannot be rewritten as switch masks"
        )
    model = copy.deepcopy(model).eval()
    _rewrite_children(model)
    return model
