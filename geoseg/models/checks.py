"""Input validation for the image tensors fed to the networks, shared by every model.

The checks raise :class:`geoseg.errors.GeosegError` (a ``ValueError``) with a message naming the
argument. They are skipped while the model is being traced, compiled or exported
(``torch.compiler.is_compiling()``, ``torch.jit.is_tracing()``, ``torch.onnx.is_in_onnx_export()``)
so that no data-dependent branch enters the exported graph.
"""

from __future__ import annotations

import logging

import torch

from geoseg.errors import GeosegError, check_finite

logger = logging.getLogger(__name__)


def is_exporting() -> bool:
    """True while torch is tracing, compiling or exporting the model (checks must stay out)."""
    if torch.compiler.is_compiling() or torch.jit.is_tracing():
        return True
    exporting = getattr(torch.compiler, "is_exporting", None)
    if exporting is not None and exporting():
        return True
    try:
        return bool(torch.onnx.is_in_onnx_export())
    except Exception:  # pragma: no cover - older torch without the helper
        return False


def check_image_tensor(name: str, x: object, *, channels: int = 3, min_size: int = 1) -> None:
    """Raise unless ``x`` is a finite floating-point tensor of shape ``(B, channels, H, W)``.

    Args:
        name: the argument's name, used in the message.
        x: the candidate tensor, expected `(B, channels, H, W)` float.
        channels: the expected channel count.
        min_size: the smallest accepted height and width.

    Raises:
        GeosegError: not a tensor, not 4-D, wrong channel count, integer dtype, too small,
            or NaN/infinite values.
    """
    if is_exporting():
        return
    if not isinstance(x, torch.Tensor):
        raise GeosegError(
            f"{name}: expected a torch.Tensor (B, {channels}, H, W), got {type(x).__name__}"
        )
    if x.dim() != 4:
        raise GeosegError(
            f"{name}: expected a 4-D tensor (B, {channels}, H, W), got {x.dim()}-D shape {tuple(x.shape)}"
        )
    if not x.is_floating_point():
        raise GeosegError(
            f"{name}: expected a floating-point tensor (normalised image), got dtype {x.dtype}; "
            "convert uint8 images with geoseg.infer.Segmenter or x.float()"
        )
    if x.shape[1] != channels:
        raise GeosegError(
            f"{name}: expected {channels} channels (B, {channels}, H, W), got shape {tuple(x.shape)}"
        )
    if x.shape[0] < 1 or x.shape[2] < min_size or x.shape[3] < min_size:
        raise GeosegError(
            f"{name}: expected a non-empty batch and sides >= {min_size}, got shape {tuple(x.shape)}"
        )
    if x.is_cuda and torch.cuda.is_current_stream_capturing():
        return  # reading values back would break CUDA graph capture
    check_finite(name, x)
