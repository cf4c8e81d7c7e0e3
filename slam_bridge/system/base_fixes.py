"""Position fixes from a georeferenced image base: relocalisation as a visual GPS.

Chapter 5's relocalisation feeds chapter 3's fusion: frames of the drive, one every
``every_s`` seconds, are localised against an image base (``geoseg base build``) by
:class:`geoseg.reloc.localizer.Localizer` (retrieval, then the relative-pose heads' ranged
rays). A frame whose matches' rays agree (the localiser's confidence gate,
``min_agreeing_rays``) gives a fix at their point; one where they disagree gives its best
match's camera position (within half the base's spacing of the truth when retrieval is right),
unless ``best_match`` is off; one that finds nothing gives none. The fixes join the fusion through the GPS term under
the name ``base`` with their own weight, and, without a GPS, they georeference the start-up
and a segment started after a tracking loss, in the same world frame: the SLAM starts and
recovers from the base.

The frames are localised before the loop starts (a recorded drive); a live system would
localise keyframes as they come, with the same fixes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam_bridge.errors import SlamError
from slam_bridge.slam.fusion import GpsConstraints

__all__ = ["BaseFixConfig", "BaseFixes", "BaseConstraints", "localise_frames"]

logger = logging.getLogger(__name__)

#: the localiser's position methods from agreeing rays (its gated fallback: "best match")
TRUSTED_METHODS = ("ranged rays", "rays")


@dataclass
class BaseFixConfig:
    """How frames become fixes (``geoseg slam run --base``).

    Attributes:
        every_s: seconds between two localised frames.
        weight: weight of a fix in the fusion, per square metre (a GPS fix's is
            ``ImageSlamConfig.gps_weight``).
        max_residual_m: a fix whose agreeing rays miss their point by more than this (rms) is
            dropped.
        best_match: where the rays disagree, the best match's position is a fix (else none).
        batch: frames localised together (memory against speed).
    """

    every_s: float = 0.5
    weight: float = 1.0
    max_residual_m: float = 2.0
    best_match: bool = True
    batch: int = 16

    def __post_init__(self) -> None:
        for name in ("every_s", "weight", "max_residual_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0):
                raise SlamError(f"base.{name}: expected a positive number, got {value!r}")
        if int(self.batch) != self.batch or self.batch < 1:
            raise SlamError(f"base.batch: expected an int >= 1, got {self.batch!r}")


@dataclass
class BaseFixes:
    """The localised frames and the fixes they gave.

    Attributes:
        timestamps: ``(L,)`` times of the localised frames, seconds.
        xy: ``(L, 2)`` fixes in the base's world frame (NaN: no trusted position).
        methods: ``L`` localiser position methods (``ranged rays``, ``best match``, ...).
        base: the image base's folder.
    """

    timestamps: np.ndarray
    xy: np.ndarray
    methods: list[str] = field(default_factory=list)
    base: Path | None = None

    def _valid(self) -> np.ndarray:
        return np.isfinite(self.xy[:, 0])

    @property
    def accepted(self) -> int:
        """Frames that gave a fix."""
        return int(self._valid().sum())

    def summary(self) -> dict[str, Any]:
        """Counts for ``summary.json``."""
        return {
            "base": str(self.base) if self.base is not None else None,
            "base_frames_localised": int(self.timestamps.size),
            "base_fixes": self.accepted,
            "base_fixes_from_rays": int(
                sum(m in TRUSTED_METHODS and ok for m, ok in zip(self.methods, self._valid()))
            ),
        }


class BaseConstraints(GpsConstraints):
    """The base's fixes in the fusion: the GPS term, named ``base`` (the camera's own
    position: no antenna offset)."""

    name = "base"


def _rgb(image: np.ndarray) -> np.ndarray:
    """A frame as the localiser's networks take it: uint8 ``(H, W, 3)``."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return image


def localise_frames(
    frames: Any, base: str | Path, config: BaseFixConfig | None = None, *, localizer: Any = None
) -> BaseFixes:
    """Localise one frame every ``config.every_s`` seconds against ``base``.

    Args:
        frames: the drive's :class:`~slam_bridge.frontend.frames.FrameSequence`.
        base: an image base folder (``geoseg base build``).
        config: :class:`BaseFixConfig`.
        localizer: a ready :class:`~geoseg.reloc.localizer.Localizer` (default: the shipped
            networks over ``base``, :meth:`~geoseg.reloc.localizer.Localizer.from_base`).

    Returns:
        :class:`BaseFixes`, one row per localised frame.

    Raises:
        SlamError: the base cannot be read, or its camera does not fit the frames.
    """
    from geoseg.errors import GeosegError

    cfg = config or BaseFixConfig()
    if localizer is None:
        from geoseg.reloc.localizer import Localizer

        try:
            localizer = Localizer.from_base(base)
        except GeosegError as err:
            raise SlamError(f"--base {base}: {err}") from None
    t = np.asarray(frames.timestamps, dtype=np.float64)
    picks, last = [], -np.inf
    for i, ti in enumerate(t):
        if ti - last >= cfg.every_s - 1e-9:
            picks.append(i)
            last = ti
    xy = np.full((len(picks), 2), np.nan)
    methods: list[str] = []
    for start in range(0, len(picks), cfg.batch):
        chunk = picks[start : start + cfg.batch]
        images = [_rgb(frames[i][1]) for i in chunk]
        try:
            results = localizer.localize(images, names=[f"frame {i}" for i in chunk], sequence=None)
        except GeosegError as err:
            raise SlamError(f"--base {base}: {err}") from None
        for j, result in enumerate(results):
            position = result.position
            methods.append(str(position.get("method", "")))
            residuals = np.asarray(position.get("residuals_m", []), dtype=np.float64)
            rms = float(np.sqrt(np.mean(residuals**2))) if residuals.size else 0.0
            if result.xyz is None:
                continue
            if position.get("method") in TRUSTED_METHODS:
                if rms <= cfg.max_residual_m:
                    xy[start + j] = result.xyz[:2]
            elif cfg.best_match:
                xy[start + j] = result.xyz[:2]
    fixes = BaseFixes(t[picks], xy, methods, Path(base))
    logger.info(
        "image base %s: %d of %d localised frames gave a fix (one every %.2f s)",
        base, fixes.accepted, len(picks), cfg.every_s,
    )  # fmt: skip
    return fixes


def base_constraints(fixes: BaseFixes, config: BaseFixConfig, interpolate_gap_s: float | None):
    """The fusion's provider of ``fixes`` (None when no frame gave one)."""
    if fixes.accepted == 0:
        logger.warning("image base %s: no frame was localised with confidence", fixes.base)
        return None
    return BaseConstraints(
        fixes.timestamps,
        fixes.xy,
        weight=config.weight,
        tolerance_s=0.02,
        interpolate_gap_s=interpolate_gap_s,
    )
