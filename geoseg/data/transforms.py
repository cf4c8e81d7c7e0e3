"""Augmentations applied consistently to an image, its labels and its surface normals.

Built on torchvision transforms v2: in a sample the image is wrapped as ``tv_tensors.Image``, the
labels as ``tv_tensors.Mask`` (so resizing uses nearest-neighbour and labels stay integers) and
the normals as :class:`Normals`, a custom tv_tensor with its own kernels:

* horizontal flip mirrors the map **and negates the x component** (camera frame: x right, y down,
  z forward); vertical flip negates y;
* resize interpolates bilinearly (antialiased like the image), then renormalises to unit length;
  pixels whose nearest source pixel is invalid (a zero vector, e.g. sky) stay zero, and valid
  pixels next to invalid ones take the direction of their valid neighbours;
* crop / centre crop / constant padding move pixels only; new pixels are zero (invalid);
* rotation, affine, perspective and elastic warps are refused with :class:`GeosegError` (they
  would need the camera intrinsics to rotate the vectors correctly);
* colour transforms leave normals (and labels) untouched.

Uniform scaling and cropping do not change camera-frame normals (they only change the
intrinsics); an anisotropic resize would, slightly, and is not compensated.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torchvision import tv_tensors
from torchvision.transforms import v2
from torchvision.transforms.v2 import functional as F

from geoseg.classes import IGNORE_INDEX
from geoseg.data.camera_effects import CameraEffectsConfig
from geoseg.errors import ConfigError, GeosegError
from geoseg.vectors import vector_length

logger = logging.getLogger(__name__)

_REGISTERED = False


class Normals(tv_tensors.TVTensor):
    """Surface normals, unit vectors in the camera frame, shape ``(..., 3, H, W)``.

    Invalid pixels (no surface, e.g. sky) hold the zero vector.
    """

    def __new__(
        cls,
        data: Any,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | int | None = None,
        requires_grad: bool | None = None,
    ) -> Normals:
        register_normals_kernels()
        tensor = cls._to_tensor(data, dtype=dtype, device=device, requires_grad=requires_grad)
        if tensor.ndim < 3 or tensor.shape[-3] != 3:
            raise GeosegError(f"normals: expected shape (..., 3, H, W), got {tuple(tensor.shape)}")
        if not tensor.is_floating_point():
            raise GeosegError(f"normals: expected a floating-point tensor, got {tensor.dtype}")
        return tensor.as_subclass(cls)


def _plain(t: torch.Tensor) -> torch.Tensor:
    return t.as_subclass(torch.Tensor)


def _valid(n: torch.Tensor) -> torch.Tensor:
    """``(..., 1, H, W)`` uint8 mask of non-zero normals."""
    return (vector_length(n, -3, keepdim=True) > 0.5).to(torch.uint8)


def _renormalise(n: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    norm = vector_length(n, -3, keepdim=True)
    ok = (valid > 0) & (norm > 1e-6)
    return torch.where(ok, n / norm.clamp_min(1e-6), torch.zeros_like(n))


def _hflip(inpt: Normals) -> Normals:
    out = _plain(inpt).flip(-1).clone()
    out[..., 0, :, :] = -out[..., 0, :, :]
    return tv_tensors.wrap(out, like=inpt)


def _vflip(inpt: Normals) -> Normals:
    out = _plain(inpt).flip(-2).clone()
    out[..., 1, :, :] = -out[..., 1, :, :]
    return tv_tensors.wrap(out, like=inpt)


def _resize(
    inpt: Normals,
    size: list[int] | None,
    interpolation: Any = v2.InterpolationMode.BILINEAR,
    max_size: int | None = None,
    antialias: bool | None = True,
) -> Normals:
    n = _plain(inpt)
    values = F.resize_image(
        n, size, interpolation=v2.InterpolationMode.BILINEAR, max_size=max_size, antialias=antialias
    )
    valid = F.resize_mask(_valid(n), size, max_size=max_size)
    return tv_tensors.wrap(_renormalise(values, valid), like=inpt)


def _crop(inpt: Normals, top: int, left: int, height: int, width: int) -> Normals:
    return tv_tensors.wrap(F.crop_image(_plain(inpt), top, left, height, width), like=inpt)


def _center_crop(inpt: Normals, output_size: list[int]) -> Normals:
    return tv_tensors.wrap(F.center_crop_image(_plain(inpt), output_size), like=inpt)


def _resized_crop(
    inpt: Normals,
    top: int,
    left: int,
    height: int,
    width: int,
    size: list[int],
    interpolation: Any = v2.InterpolationMode.BILINEAR,
    antialias: bool | None = True,
) -> Normals:
    return _resize(_crop(inpt, top, left, height, width), size, antialias=antialias)


def _pad(
    inpt: Normals, padding: list[int], fill: Any = None, padding_mode: str = "constant"
) -> Normals:
    if padding_mode != "constant":
        raise GeosegError(
            f"normals: padding mode {padding_mode!r} is not supported (reflected normals would "
            "need their components flipped); use constant padding"
        )
    return tv_tensors.wrap(F.pad_image(_plain(inpt), padding, fill=0.0), like=inpt)


def _refuse(name: str) -> Callable[..., Any]:
    def kernel(inpt: Normals, *args: Any, **kwargs: Any) -> Normals:
        raise GeosegError(
            f"normals: the {name} transform is not supported (it would have to rotate the "
            "vectors with the camera intrinsics); use flips, resizes and crops"
        )

    return kernel


def register_normals_kernels() -> None:
    """Register :class:`Normals` kernels with torchvision's v2 functionals (idempotent)."""
    global _REGISTERED
    if _REGISTERED:
        return
    F.register_kernel(F.horizontal_flip, Normals)(_hflip)
    F.register_kernel(F.vertical_flip, Normals)(_vflip)
    F.register_kernel(F.resize, Normals)(_resize)
    F.register_kernel(F.crop, Normals)(_crop)
    F.register_kernel(F.center_crop, Normals)(_center_crop)
    F.register_kernel(F.resized_crop, Normals)(_resized_crop)
    F.register_kernel(F.pad, Normals)(_pad)
    for functional in (F.rotate, F.affine, F.perspective, F.elastic):
        F.register_kernel(functional, Normals)(_refuse(functional.__name__))
    _REGISTERED = True


@dataclass
class AugmentConfig:
    """Training augmentations (all off but the flip by default).

    Attributes:
        hflip: probability of a horizontal flip.
        scale: range of a random rescale factor applied to the network input size before
            cropping back to it (``(1.0, 1.0)`` = none).
        brightness, contrast, saturation, hue: ``ColorJitter`` strengths (image only).
        camera: camera effects on the image only (noise, blur, vignetting, exposure, white
            balance, JPEG; :mod:`geoseg.data.camera_effects`), all off by default; applied to
            training frames after the other augmentations (:func:`training.frame_data.build_frame_dataset`).
    """

    hflip: float = 0.5
    scale: tuple[float, float] = (1.0, 1.0)
    brightness: float = 0.0
    contrast: float = 0.0
    saturation: float = 0.0
    hue: float = 0.0
    camera: CameraEffectsConfig = field(default_factory=CameraEffectsConfig)

    def __post_init__(self) -> None:
        if not 0.0 <= self.hflip <= 1.0:
            raise ConfigError(f"augment.hflip: expected a probability, got {self.hflip}")
        if not 0 < self.scale[0] <= self.scale[1]:
            raise ConfigError(f"augment.scale: expected 0 < lo <= hi, got {self.scale}")
        if not 0.0 <= self.hue <= 0.5:
            raise ConfigError(f"augment.hue: expected 0 <= hue <= 0.5, got {self.hue}")
        for key in ("brightness", "contrast", "saturation"):
            if getattr(self, key) < 0:
                raise ConfigError(f"augment.{key}: expected >= 0, got {getattr(self, key)}")


class SampleTransform:
    """Apply a v2 transform to a sample dict, keeping image, labels and normals aligned.

    Args:
        transform: a torchvision v2 transform (e.g. ``v2.Compose``).
        image_key: key of the ``(3, H, W)`` float image.
        mask_keys: keys of ``(H, W)`` integer maps (labels, instance ids): nearest resampling,
            padded with :data:`~geoseg.classes.IGNORE_INDEX` by the builders here.
        normal_keys: keys of ``(3, H, W)`` camera-frame normals.

    Other entries pass through unchanged; a tensor entry with the image's spatial size that is
    not declared raises GeosegError (it would silently fall out of alignment).
    """

    def __init__(
        self,
        transform: Callable[[Any], Any],
        *,
        image_key: str = "image",
        mask_keys: tuple[str, ...] = ("labels",),
        normal_keys: tuple[str, ...] = ("normals",),
    ) -> None:
        register_normals_kernels()
        self.transform = transform
        self.image_key = image_key
        self.mask_keys = tuple(mask_keys)
        self.normal_keys = tuple(normal_keys)

    def __call__(self, sample: Mapping[str, Any]) -> dict[str, Any]:
        """Transform ``sample``; returns a new dict of plain tensors."""
        if self.image_key not in sample:
            raise GeosegError(f"sample: missing {self.image_key!r} (keys: {sorted(sample)})")
        image = sample[self.image_key]
        hw = tuple(image.shape[-2:])
        wrapped: dict[str, Any] = {}
        for key, value in sample.items():
            if key == self.image_key:
                wrapped[key] = tv_tensors.Image(value)
            elif key in self.mask_keys:
                wrapped[key] = tv_tensors.Mask(value)
            elif key in self.normal_keys:
                wrapped[key] = Normals(value)
            elif (
                isinstance(value, torch.Tensor)
                and value.ndim >= 2
                and tuple(value.shape[-2:]) == hw
            ):
                raise GeosegError(
                    f"sample[{key!r}]: a {tuple(value.shape)} map not declared as mask or normals; "
                    "pass it in mask_keys/normal_keys or drop it before transforming"
                )
            else:
                wrapped[key] = value
        out = self.transform(wrapped)
        return {
            k: (v.as_subclass(torch.Tensor) if isinstance(v, torch.Tensor) else v)
            for k, v in out.items()
        }

    def __repr__(self) -> str:
        return f"SampleTransform({self.transform!r})"


def build_transforms(
    cfg: AugmentConfig | None = None,
    *,
    size: tuple[int, int] | None = None,
    train: bool = True,
) -> SampleTransform:
    """The standard pipeline: resize to ``size``, then (train only) scale jitter + crop back to
    ``size``, horizontal flip and colour jitter.

    Args:
        cfg: augmentation settings (defaults when None).
        size: ``(H, W)`` of the output; None keeps the input size (no resize, no scale jitter).
        train: False gives the deterministic evaluation pipeline (resize only).
    """
    cfg = cfg or AugmentConfig()
    fill = {tv_tensors.Image: 0.0, tv_tensors.Mask: IGNORE_INDEX, Normals: 0.0}
    steps: list[Any] = []
    if size is not None:
        steps.append(v2.Resize(list(size), antialias=True))
    if train:
        if size is not None and cfg.scale != (1.0, 1.0):
            # ScaleJitter's target size is (W, H)
            target = (size[1], size[0])
            steps.append(v2.ScaleJitter(target, scale_range=tuple(cfg.scale), antialias=True))
            steps.append(v2.RandomCrop(list(size), pad_if_needed=True, fill=fill))
        if cfg.hflip > 0:
            steps.append(v2.RandomHorizontalFlip(p=cfg.hflip))
        if any((cfg.brightness, cfg.contrast, cfg.saturation, cfg.hue)):
            steps.append(
                v2.ColorJitter(
                    brightness=cfg.brightness or None,
                    contrast=cfg.contrast or None,
                    saturation=cfg.saturation or None,
                    hue=cfg.hue or None,
                )
            )
    return SampleTransform(v2.Compose(steps) if steps else v2.Identity())
