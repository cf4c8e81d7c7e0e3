"""Position fixes from a georeferenced image base: relocalisation as a visual GPS.

Chapter 5's relocalisation feeds chapter 3's fusion: frames of the drive, one every
``every_s`` seconds, are localised against an image base (``geoseg base build``) by
:class:`geoseg.reloc.localizer.Localizer`: retrieval of the nearest base images, then the
query's pose on the points those images see (PnP on the base's triangulated points,
:mod:`geoseg.reloc.base_structure`), centimetres where enough points match. Where too few do,
the relative-pose heads' rays give a position when they agree, else the best match's camera
position (within about half the base's spacing when retrieval is right), unless
``best_match`` is off; a frame that finds nothing gives none. Each kind of fix has its own
weight. The fixes join the fusion through the GPS term under the name ``base``, and, without a
GPS, they georeference the start-up and a segment started after a tracking loss, in the same
world frame: the SLAM starts and recovers from the base.

The fusion moves only the newest keyframe, and within the barrier's slack (a few per cent of
the window's reprojection cost): fixes to a decimetre pull it far less than they could, and
the keyframes behind it never feel the fixes that come after them. Once the run is over, one
bundle adjustment of every keyframe together (:func:`adjust_on_fixes`, the global adjustment of
:mod:`slam_bridge.system.refine` with the base's rows) bends the map onto all of them.

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

__all__ = ["BaseFixConfig", "BaseFixes", "BaseConstraints", "localise_frames", "adjust_on_fixes"]

logger = logging.getLogger(__name__)

#: the localiser's position methods from agreeing rays (its gated fallback: "best match")
TRUSTED_METHODS = ("ranged rays", "rays")
#: the localiser's pose from the base's triangulated points
STRUCTURE_METHOD = "structure"


@dataclass
class BaseFixConfig:
    """How frames become fixes (``geoseg slam run --base``).

    Attributes:
        every_s: seconds between two localised frames.
        structure: localise on the base's triangulated points first (PnP).
        structure_weight: weight of a fix from the base's points, per square metre (a GPS
            fix's is ``ImageSlamConfig.gps_weight``, for a 0.75 m receiver). The weights, the
            tracking and ``refit_distance_m`` were chosen on the tuning drives
            ``RELOC_SLAM_TUNING_SEEDS`` (bench/splits.py; ``bench/reloc_slam.py --tuning``
            runs them), the fixes of each localised once: no GPS, mean error
            0.47 m with the defaults (the start-up's fit weighing each fix by its weight),
            0.81 with ``refit_distance_m`` 40 (one drive's start turned by a fit over too
            few fixes), 0.97 with 200 (docs/relocalisation.md).
        weight: weight of a fix from the rays or the best match, per square metre.
        max_residual_m: a fix whose agreeing rays miss their point by more than this (rms) is
            dropped.
        best_match: where the rays disagree, the best match's position is a fix (else none).
        track_every_s: with ``structure``, frames between the localised ones, one every this
            many seconds, are placed on the points of the base images nearest where the last
            fixes predict them (PnP only, no retrieval: cheap); None: the localised frames only.
        track_max_gap_s: a fix older than this predicts nothing (the last localised frame's
            matches alone are tried).
        track_images: base images nearest the predicted position whose points are tried.
        refit_distance_m: without a GPS, the start-up's similarity refits stop once the
            base's fixes spread over this distance (a GPS run's is ``init.refit_distance_m``,
            200 m): fixes to centimetres fix the heading within tens of metres, and beyond
            them a refit of the whole segment only spreads the map's own bends over it.
        batch: frames localised together (memory against speed).
        adjust: once the run is over, adjust all its keyframes together on the fixes
            (:func:`adjust_on_fixes`): on the tuning drives 41-46, no GPS, mean error 0.61 m
            without, 0.06 with (0.04-0.14 by drive); the base rows' Huber threshold (3 sigmas)
            0.06 against 0.08 without one.
    """

    every_s: float = 0.5
    structure: bool = True
    structure_weight: float = 100.0
    weight: float = 1.0
    max_residual_m: float = 2.0
    best_match: bool = True
    track_every_s: float | None = 0.1
    track_max_gap_s: float = 3.0
    track_images: int = 3
    refit_distance_m: float = 80.0
    batch: int = 16
    adjust: bool = True

    def __post_init__(self) -> None:
        for name in (
            "every_s", "structure_weight", "weight", "max_residual_m", "track_max_gap_s",
            "refit_distance_m",
        ):  # fmt: skip
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0):
                raise SlamError(f"base.{name}: expected a positive number, got {value!r}")
        if self.track_every_s is not None and not self.track_every_s > 0:
            raise SlamError(
                f"base.track_every_s: expected a positive number or null, got {self.track_every_s!r}"
            )
        for name in ("batch", "track_images"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise SlamError(f"base.{name}: expected an int >= 1, got {value!r}")


@dataclass
class BaseFixes:
    """The localised frames and the fixes they gave.

    Attributes:
        timestamps: ``(L,)`` times of the localised frames, seconds.
        xy: ``(L, 2)`` fixes in the base's world frame (NaN: no trusted position).
        methods: ``L`` localiser position methods (``ranged rays``, ``best match``,
            ``structure``, ...; ``tracking lost`` for a tracked frame the points did not place).
        base: the image base's folder.
        tracked: ``(L,)`` bool, the frames placed on the points without retrieval (None: none).
    """

    timestamps: np.ndarray
    xy: np.ndarray
    methods: list[str] = field(default_factory=list)
    base: Path | None = None
    tracked: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.tracked is None:
            self.tracked = np.zeros(self.timestamps.size, dtype=bool)

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
            "base_frames_localised": int((~self.tracked).sum()),
            "base_frames_tracked": int(self.tracked.sum()),
            "base_fixes": self.accepted,
            "base_fixes_from_rays": int(
                sum(m in TRUSTED_METHODS and ok for m, ok in zip(self.methods, self._valid()))
            ),
            "base_fixes_from_structure": int(
                sum(m == STRUCTURE_METHOD and ok for m, ok in zip(self.methods, self._valid()))
            ),
        }


class BaseConstraints(GpsConstraints):
    """The base's fixes in the fusion: the GPS term, named ``base`` (the camera's own
    position: no antenna offset), each fix with its own weight.

    Args:
        timestamps: ``(F,)`` fix times, seconds, increasing.
        xy: ``(F, 2)`` fixes (NaN rows: none).
        weights: ``(F,)`` each fix's weight, per square metre (an interpolated fix takes the
            lower of its two).
        **kwargs: ``tolerance_s``, ``interpolate_gap_s`` of :class:`GpsConstraints`.
    """

    name = "base"

    def __init__(self, timestamps, xy, weights, **kwargs) -> None:
        self.weights = np.asarray(weights, dtype=np.float64).reshape(-1)
        if self.weights.size != np.size(timestamps) or not (self.weights > 0).all():
            raise SlamError(
                f"weights: expected {np.size(timestamps)} positive weights, got "
                f"{self.weights.size} (min {self.weights.min(initial=np.inf):g})"
            )
        super().__init__(timestamps, xy, weight=float(self.weights.max()), **kwargs)

    def fix_weights(self) -> np.ndarray:
        """``(F,)`` each fix's weight (the start-up's fit weighs its fixes by them)."""
        return self.weights

    def factors(self, slam_map, problem, k: int) -> list:
        """One :class:`~slam_bridge.factors.gps.GPSFactor` on the newest free camera with the
        weight of its fix, or none."""
        from slam_bridge.factors.gps import GPSFactor

        st = problem.state
        timestamp = float(slam_map.timestamps[k])
        fix = self.camera_fix_at(timestamp, st.R_wc[st.free_cameras[-1]])
        if fix is None:
            return []
        return [GPSFactor.most_recent(st, fix, weight=self.weight_at(timestamp))]


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
            try:
                localizer = Localizer.from_base(base, structure=cfg.structure, query_K=frames.K)
            except GeosegError as err:
                if not cfg.structure:
                    raise
                # a base without intrinsics or too sparse to triangulate: the rays alone
                logger.warning("--base %s: no points to place frames on (%s)", base, err)
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
    candidates: list[list[int]] = []  # each localised frame's base matches
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
            candidates.append([int(m["index"]) for m in result.matches])
            residuals = np.asarray(position.get("residuals_m", []), dtype=np.float64)
            rms = float(np.sqrt(np.mean(residuals**2))) if residuals.size else 0.0
            if result.xyz is None:
                continue
            if position.get("method") == STRUCTURE_METHOD:
                xy[start + j] = result.xyz[:2]
            elif position.get("method") in TRUSTED_METHODS:
                if rms <= cfg.max_residual_m:
                    xy[start + j] = result.xyz[:2]
            elif cfg.best_match:
                xy[start + j] = result.xyz[:2]
    tracked = np.zeros(len(picks), dtype=bool)
    structure = getattr(localizer, "structure", None)
    if structure is not None and cfg.track_every_s is not None:
        localised = set(picks)
        picks, xy, methods = _track_on_points(
            frames, t, picks, xy, methods, candidates, structure, localizer.index.t_wc, cfg
        )
        tracked = np.array([i not in localised for i in picks])
    fixes = BaseFixes(t[picks], xy, methods, Path(base), tracked)
    logger.info(
        "image base %s: %d of %d frames gave a fix (localised every %.2f s, %d on the base's "
        "points)",
        base, fixes.accepted, len(picks), cfg.every_s,
        fixes.summary()["base_fixes_from_structure"],
    )  # fmt: skip
    return fixes


def _track_on_points(frames, t, picks, xy, methods, candidates, structure, base_t_wc, cfg):
    """Frames between the localised ones, placed on the base's points near where they should be.

    Retrieval (the trunk on every frame) is what makes localising costly; a frame shortly
    after a fix needs none: its base images are those nearest the position the last two fixes
    predict (constant velocity), with the last localised frame's matches (those alone without
    a recent fix). Only the points' PnP runs, and only its poses are kept. Returns the merged
    ``(frame indices, fixes, methods)`` in time order.
    """
    rows = {p: (xy[r], methods[r], candidates[r]) for r, p in enumerate(picks)}
    fixes: list[tuple[float, np.ndarray]] = []  # the last two (time, xy) placed on the points
    last_matches: list[int] = []
    next_track = -np.inf

    def placed(ti, fix):
        fixes.append((ti, fix))
        del fixes[:-2]

    for i, ti in enumerate(t):
        if i in rows:
            fix, method, last_matches = rows[i]
            if method == STRUCTURE_METHOD and np.isfinite(fix).all():
                placed(ti, fix)
            continue
        if ti < next_track - 1e-9:
            continue
        next_track = ti + cfg.track_every_s
        chosen = list(last_matches)
        if fixes and ti - fixes[-1][0] <= cfg.track_max_gap_s:
            (t0, p0), (t1, p1) = fixes[0], fixes[-1]
            velocity = (p1 - p0) / (t1 - t0) if t1 > t0 else np.zeros(2)
            predicted = p1 + velocity * (ti - t1)
            near = np.argsort(np.linalg.norm(base_t_wc[:, :2] - predicted, axis=1))
            chosen = [int(b) for b in near[: cfg.track_images]] + chosen
        if not chosen:
            continue
        chosen = list(dict.fromkeys(chosen))
        pose = structure.locate(_rgb(frames[i][1]), chosen)
        rows[i] = (pose.t_wc[:2] if pose.ok else np.full(2, np.nan),
                   STRUCTURE_METHOD if pose.ok else "tracking lost", chosen)  # fmt: skip
        if pose.ok:
            placed(ti, pose.t_wc[:2])
    order = sorted(rows)
    return (
        order,
        np.array([rows[i][0] for i in order]).reshape(-1, 2),
        [rows[i][1] for i in order],
    )


def base_constraints(fixes: BaseFixes, config: BaseFixConfig, interpolate_gap_s: float | None):
    """The fusion's provider of ``fixes`` (None when no frame gave one)."""
    if fixes.accepted == 0:
        logger.warning("image base %s: no frame was localised with confidence", fixes.base)
        return None
    weights = np.where(
        [m == STRUCTURE_METHOD for m in fixes.methods], config.structure_weight, config.weight
    )
    return BaseConstraints(
        fixes.timestamps,
        fixes.xy,
        weights,
        tolerance_s=0.02,
        interpolate_gap_s=interpolate_gap_s,
    )


def adjust_on_fixes(result, inputs, base: BaseConstraints, gps=None) -> dict[str, Any]:
    """One bundle adjustment of the whole run on the base's fixes, once it is over.

    The global adjustment of :func:`slam_bridge.system.refine.refine_map` (its default
    settings): every observation the run kept, a row per keyframe with a base fix (its
    weight, Huber), the GPS's rows when there is one, the DEM, the odometry and the verticals.
    The adjusted poses and points replace the run's in ``result.map`` (the loop's are kept in
    ``result.loop_t_wc``, and the online poses, ``Map.t_wc_online``, stay what the run knew
    then); a problem the adjustment cannot solve
    leaves the run as it was, with a warning.

    Args:
        result: the run's :class:`slam_bridge.slam.loop.SlamResult`, georeferenced.
        inputs: its :class:`slam_bridge.system.image_slam.SlamInputs` (DEM, odometry, rig).
        base: the run's base provider.
        gps: the run's :class:`slam_bridge.slam.fusion.GpsConstraints`, or None.

    Returns:
        The adjustment's figures (:attr:`slam_bridge.system.refine.RefineResult.figures`;
        ``error``: why nothing was adjusted).
    """
    from slam_bridge.system.map_file import saved_map
    from slam_bridge.system.refine import refine_map

    try:
        refined = refine_map(
            saved_map(result, inputs, gps=gps, base=base), dem=inputs.dem, gps=gps, base=base,
            odometry=inputs.odometry,
        )  # fmt: skip
    except SlamError as err:
        logger.warning("image base: the run's keyframes were not adjusted on its fixes (%s)", err)
        return {"error": str(err)}
    m, kf = result.map, refined.refined
    result.loop_t_wc = m.t_wc.copy()
    m.R_wc[kf] = refined.map.R_wc[kf]
    m.t_wc[kf] = refined.map.t_wc[kf]
    m.X_w[:] = refined.map.X_w
    f = refined.figures
    logger.info(
        "image base: %d keyframes adjusted on %d fixes (moved %.2f m on average, %.2f at most; "
        "%.1f s)",
        kf.sum(), f.get("base_rows", 0), f["keyframe_shift_m_mean"], f["keyframe_shift_m_max"],
        f["seconds"],
    )  # fmt: skip
    return f
