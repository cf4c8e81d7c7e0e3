"""Camera effects for training images: what a real camera does to a picture that a clean
rendering lacks (a domain-randomisation step toward real photographs).

Each effect changes the image only: labels, normals and depth stay as rendered (none of these
moves a pixel). Lens distortion, which does move pixels, belongs in the renderer's camera model,
not here.

Effects, in the order applied (each drawn with its own probability, strengths uniform in their
ranges):

- exposure: gain ``2 ** stops`` on the linear-ish RGB;
- white balance: per-channel gains ``1 + u``, ``u`` in ``±white_balance`` (a colour cast);
- vignetting: brightness ``1 - strength * (r / r_corner) ** 2`` (darker corners);
- defocus blur: a disk kernel of the drawn radius (pixels);
- motion blur: a line kernel of the drawn length in a random direction;
- sensor noise: Gaussian, std drawn in ``noise_std`` (of the [0, 1] range), per pixel and channel;
- JPEG compression: encode and decode at a quality drawn in ``jpeg_quality``.

Random draws use torch's global generator, so that a seeded training loop (and its DataLoader
workers) reproduces them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from geoseg.config import check_range
from geoseg.errors import ConfigError, GeosegError


@dataclass
class CameraEffectsConfig:
    """Probabilities (``p_*``, 0 = off) and strength ranges of the camera effects.

    All effects are off by default (``p_* = 0``); :data:`REALISTIC` is a tested preset.

    Attributes:
        p_exposure, exposure_stops: probability, and range of the exposure change in stops.
        p_white_balance, white_balance: probability, and the largest per-channel gain offset.
        p_vignetting, vignetting: probability, and range of the corner darkening (0..1).
        p_defocus, defocus_radius: probability, and range of the disk radius in pixels.
        p_motion_blur, motion_blur_length: probability, and range of the streak in pixels.
        p_noise, noise_std: probability, and range of the Gaussian noise std (image in [0, 1]).
        p_jpeg, jpeg_quality: probability, and range of the JPEG quality (1..100).
    """

    p_exposure: float = 0.0
    exposure_stops: tuple[float, float] = (-1.0, 1.0)
    p_white_balance: float = 0.0
    white_balance: float = 0.1
    p_vignetting: float = 0.0
    vignetting: tuple[float, float] = (0.1, 0.5)
    p_defocus: float = 0.0
    defocus_radius: tuple[float, float] = (0.5, 2.0)
    p_motion_blur: float = 0.0
    motion_blur_length: tuple[float, float] = (2.0, 7.0)
    p_noise: float = 0.0
    noise_std: tuple[float, float] = (0.005, 0.03)
    p_jpeg: float = 0.0
    jpeg_quality: tuple[int, int] = (30, 95)

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if name.startswith("p_"):
                check_range(f"augment.camera.{name}", value, 0.0, 1.0)
        ranges = {
            "exposure_stops": (None, None),
            "vignetting": (0.0, 1.0),
            "defocus_radius": (0.0, None),
            "motion_blur_length": (0.0, None),
            "noise_std": (0.0, 1.0),
            "jpeg_quality": (1, 100),
        }
        for name, (low, high) in ranges.items():
            lo, hi = getattr(self, name)
            check_range(f"augment.camera.{name}[0]", lo, low, high)
            check_range(f"augment.camera.{name}[1]", hi, low, high)
            if lo > hi:
                raise ConfigError(f"augment.camera.{name}: expected low <= high, got {(lo, hi)}")
        check_range("augment.camera.white_balance", self.white_balance, 0.0, 1.0, high_open=True)

    @property
    def enabled(self) -> bool:
        """Whether any effect can fire."""
        return any(v > 0 for k, v in vars(self).items() if k.startswith("p_"))


REALISTIC = CameraEffectsConfig(
    p_exposure=0.5,
    p_white_balance=0.5,
    p_vignetting=0.3,
    p_defocus=0.2,
    p_motion_blur=0.2,
    p_noise=0.5,
    p_jpeg=0.5,
)
"""A preset with every effect on at moderate rates (configs: copy its values)."""


def _uniform(low: float, high: float) -> float:
    return float(low + (high - low) * torch.rand(()).item())


def _fires(p: float) -> bool:
    return p > 0 and torch.rand(()).item() < p


def _disk_kernel(radius: float) -> np.ndarray:
    size = 2 * int(np.ceil(radius)) + 1
    yy, xx = np.mgrid[:size, :size] - size // 2
    # anti-aliased edge: pixels within half a pixel of the rim get a partial weight, so that
    # radii below 1 still blur a little instead of being the identity
    kernel = np.clip(radius + 0.5 - np.hypot(xx, yy), 0.0, 1.0).astype(np.float32)
    return kernel / kernel.sum()


def _line_kernel(length: float, angle_rad: float) -> np.ndarray:
    size = 2 * int(np.ceil(length / 2)) + 1
    kernel = np.zeros((size, size), np.float32)
    c = size // 2
    dx, dy = np.cos(angle_rad) * length / 2, np.sin(angle_rad) * length / 2
    cv2.line(kernel, (round(c - dx), round(c - dy)), (round(c + dx), round(c + dy)), 1.0, 1)
    return kernel / kernel.sum()


def apply_camera_effects(image: np.ndarray, cfg: CameraEffectsConfig) -> np.ndarray:
    """Apply the effects ``cfg`` draws to one image.

    Args:
        image: `(H, W, 3)` float32 RGB in [0, 1].
        cfg: the effects' probabilities and ranges.

    Returns:
        `(H, W, 3)` float32 RGB in [0, 1] (a new array).
    """
    out = np.array(image, dtype=np.float32, copy=True)
    h, w = out.shape[:2]
    if _fires(cfg.p_exposure):
        out *= 2.0 ** _uniform(*cfg.exposure_stops)
    if _fires(cfg.p_white_balance):
        gains = [1.0 + _uniform(-cfg.white_balance, cfg.white_balance) for _ in range(3)]
        out *= np.asarray(gains, np.float32)
    if _fires(cfg.p_vignetting):
        yy, xx = np.mgrid[:h, :w].astype(np.float32)
        r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (
            ((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2
        )
        out *= (1.0 - _uniform(*cfg.vignetting) * r2)[..., None]
    if _fires(cfg.p_defocus):
        out = cv2.filter2D(
            out, -1, _disk_kernel(_uniform(*cfg.defocus_radius)), borderType=cv2.BORDER_REFLECT
        )
    if _fires(cfg.p_motion_blur):
        kernel = _line_kernel(_uniform(*cfg.motion_blur_length), _uniform(0.0, np.pi))
        out = cv2.filter2D(out, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if _fires(cfg.p_noise):
        std = _uniform(*cfg.noise_std)
        out += std * torch.randn(out.shape).numpy()
    out = np.clip(out, 0.0, 1.0)
    if _fires(cfg.p_jpeg):
        quality = round(_uniform(*cfg.jpeg_quality))
        bgr = cv2.cvtColor(np.round(out * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise GeosegError("camera effects: JPEG encoding failed")
        out = (
            cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(np.float32)
            / 255.0
        )
    return out


class CameraEffects:
    """Sample transform: :func:`apply_camera_effects` on ``sample["image"]`` only.

    The image is `(3, H, W)` float in [0, 1] (before normalisation); every other entry (labels,
    normals, depth) passes through untouched.
    """

    def __init__(self, cfg: CameraEffectsConfig) -> None:
        self.cfg = cfg

    def __call__(self, sample: Mapping[str, Any]) -> dict[str, Any]:
        out = dict(sample)
        image = out["image"]
        hwc = image.permute(1, 2, 0).numpy()
        out["image"] = (
            torch.from_numpy(apply_camera_effects(hwc, self.cfg)).permute(2, 0, 1).contiguous()
        )
        return out

    def __repr__(self) -> str:
        return f"CameraEffects({self.cfg})"
