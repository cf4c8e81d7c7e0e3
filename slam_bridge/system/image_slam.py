"""The SLAM on a folder of images, as a user runs it (``geoseg slam run``).

Inputs (:func:`load_inputs`): a folder of images with its ``camera.json`` (K, image size; the
layout ``geoseg render`` writes is one such folder, see :mod:`slam_bridge.frontend.frames`),
and optionally a GPS log, a wheel-odometry log and a road DEM
(:mod:`slam_bridge.system.sensor_logs`).
``camera.json`` may also give the rig: ``camera_height_m`` and ``gps_antenna_c`` (the GPS
antenna in the camera frame, metres; :class:`slam_bridge.slam.initialization.VehicleRig`).

The run (:func:`run_image_slam`): the visual front end
(:class:`slam_bridge.frontend.image_tracks.ImageTracks`) turns the images into keyframe tracks,
the start-up (:class:`slam_bridge.slam.initialization.TwoViewStart`) initialises and
georeferences the map without ground truth, and the loop (:func:`slam_bridge.slam.loop.
run_slam`) fuses the GPS at every keyframe (and the DEM, the odometry and, given a building
model, building constraints chosen by a network: :mod:`slam_bridge.bridge`). Outputs in ``out_dir`` (a stage: the folder is
refused if it holds other files, and ``summary.json`` is written last, so a folder without it
is an unfinished run):

* ``trajectory.csv``: per keyframe its frame, timestamp, world pose (``tx, ty, tz``, the
  quaternion ``qw, qx, qy, qz`` and ``R_wc`` row-major), WGS84 position when a georeference is
  known, tracking state and segment;
* ``map_points.ply``: the triangulated map points (trimesh point cloud);
* ``map.npz``: the map a global bundle adjustment needs (keyframes, points, observations,
  intrinsics, the building association): :mod:`slam_bridge.system.map_file`;
* ``keyframes.csv``: the per-keyframe log (tracking state, inliers, observations, new points,
  window sizes, k-BA and fusion times, constraints fused);
* ``trajectory.png``: a top-down plot of the trajectory over the GPS fixes (and the ground
  truth when the folder has a ``poses.csv``);
* ``frame_poses.csv``, ``trajectory_tum.txt``, ``trajectory_kitti.txt``: a pose for every
  frame (:mod:`slam_bridge.slam.frame_poses`: keyframe, interpolated or extrapolated);
* ``summary.json``: the figures (keyframes, tracking failures, frames per second, the run's
  ``status`` with its reasons from :mod:`slam_bridge.slam.health`, the last estimate of the
  GPS's bias when it was estimated from the building model, ``gps_bias_m``,
  ``gps_bias_facades``, ``gps_biased_probability``: :mod:`slam_bridge.bridge.gps_bias`, what
  an image base gave when one was (``base_fixes``, ``base_fused_keyframes``:
  :mod:`slam_bridge.system.base_fixes`), the colour reference the network's keyframes were
  mapped onto when one was (``colour_transfer``: :mod:`slam_bridge.bridge.builder`), and the
  errors against the ground truth when there is one: evaluation only, never used by the run).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from geoseg.errors import check_finite
from slam_bridge.bridge.builder import BridgeConfig, check_covers_window
from slam_bridge.bridge.gps_bias import BuildingGpsBias, GpsBiasConfig
from slam_bridge.csv_columns import read_columns
from slam_bridge.errors import SlamError
from slam_bridge.frontend.base import KeyframeObservations
from slam_bridge.frontend.frames import ImageFolder
from slam_bridge.frontend.image_tracks import ImageTracks, ImageTracksConfig
from slam_bridge.frontend.vertical_lines import VerticalLinesConfig
from slam_bridge.slam.config import SlamConfig
from slam_bridge.slam.frame_poses import POSE_SOURCES, frame_poses
from slam_bridge.slam.fusion import (
    DemConstraints,
    GpsConstraints,
    OdometryConstraints,
    VerticalConstraints,
)
from slam_bridge.slam.health import HealthConfig, assess_run
from slam_bridge.slam.initialization import InitConfig, OdometryDistance, TwoViewStart, VehicleRig
from slam_bridge.slam.loop import SlamResult, run_slam
from slam_bridge.slam.windows import METHODS
from slam_bridge.system.base_fixes import (
    BaseConstraints,
    BaseFixConfig,
    BaseFixes,
    adjust_on_fixes,
    base_constraints,
    localise_frames,
)
from slam_bridge.system.map_file import save_map
from slam_bridge.system.sensor_logs import read_dem_csv, read_gps_csv, read_odometry_csv

logger = logging.getLogger(__name__)

__all__ = [
    "ImageSlamConfig",
    "SlamInputs",
    "load_inputs",
    "run_on_images",
    "run_image_slam",
    "evaluate_run",
    "gps_fix_errors",
    "read_truth_csv",
]

PRODUCER = "slam run"
#: farthest a truth's positions may be from the GPS fixes (median) to be in their frame, metres
TRUTH_GPS_MAX_M = 50.0
OUTPUTS = [
    "trajectory.csv",
    "frame_poses.csv",
    "trajectory_tum.txt",
    "trajectory_kitti.txt",
    "keyframes.csv",
    "map_points.ply",
    "map.npz",
    "trajectory.png",
    "summary.json",
]


@dataclass
class ImageSlamConfig:
    """Settings of an image-SLAM run (``configs/slam_images.yaml``).

    Attributes:
        method: ``ba`` (plain k-BA window), ``dpc`` or ``mpc`` (hybrid windows, chapter 3).
        slam: the keyframe loop.
        init: the start-up.
        frontend: the visual front end.
        gps_tolerance_s: a fix within this time of a keyframe is its fix.
        gps_interpolate_gap_s: otherwise the two fixes around it are interpolated when at most
            this far apart (None: not).
        gps_weight: weight of a GPS fix in the fusion (per square metre).
        dem_weight: weight of the terrain-elevation term (per square metre).
        odometry_band: the odometry rows' dead zone in the k-BA, in sigmas of its 2 % distance
            (:class:`slam_bridge.slam.fusion.OdometryConstraints`): a wheel scale error of a few
            percent passes, a monocular scale drift of 20 % cannot survive; None: the odometry
            in the fusion only.
        vertical: the tilt from each keyframe's vertical line segments joins the fusion
            (:class:`slam_bridge.slam.fusion.VerticalConstraints`).
        vertical_lines: how those segments are found and fitted.
        bridge: the network bridge, when a building model is given (``--buildings``).
        base: how frames localised against an image base become fixes (``--base``).
        gps_bias: the GPS's bias estimated from the building model and removed from the fixes
            (:mod:`slam_bridge.bridge.gps_bias`; only with a building model and a GPS).
        health: the gates of the run's consistency checks (its ``status``).
    """

    method: str = "ba"
    slam: SlamConfig = field(default_factory=SlamConfig)
    init: InitConfig = field(default_factory=InitConfig)
    frontend: ImageTracksConfig = field(default_factory=ImageTracksConfig)
    gps_tolerance_s: float = 0.02
    gps_interpolate_gap_s: float | None = 1.5
    gps_weight: float = 1.0
    dem_weight: float = 1.0
    odometry_band: float | None = 2.0
    vertical: bool = True
    vertical_lines: VerticalLinesConfig = field(default_factory=VerticalLinesConfig)
    bridge: BridgeConfig = field(default_factory=BridgeConfig)
    base: BaseFixConfig = field(default_factory=BaseFixConfig)
    gps_bias: GpsBiasConfig = field(default_factory=GpsBiasConfig)
    health: HealthConfig = field(default_factory=HealthConfig)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise SlamError(f"method: expected one of {sorted(METHODS)}, got {self.method!r}")
        check_covers_window(self.bridge, self.slam.window)


@dataclass
class SlamInputs:
    """What a run reads (:func:`load_inputs`).

    Attributes:
        frames: the images.
        rig: camera height and GPS antenna offset.
        gps_timestamps: ``(F,)`` GPS fix times, or None.
        gps_xy: ``(F, 2)`` fixes in the world frame (NaN: dropout), or None.
        odometry: distance driven between two times, or None.
        dem: the road DEM, or None.
        georef: the world frame's WGS84 origin, or None (no WGS84 output).
        truth: ``(timestamps (T,), R_wc (T, 3, 3), t_wc (T, 3))`` from ``poses.csv`` when the
            folder has one (evaluation only), or None.
        base: an image base folder whose localised frames give fixes (``--base``), or None.
        base_fixes: those fixes once localised (:func:`base_fixes_of`).
    """

    frames: ImageFolder
    rig: VehicleRig
    gps_timestamps: np.ndarray | None = None
    gps_xy: np.ndarray | None = None
    odometry: OdometryDistance | None = None
    dem: object = None
    georef: object = None
    truth: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    base: Path | None = None
    base_fixes: BaseFixes | None = None


def load_inputs(
    frames_dir: str | Path,
    *,
    camera: str | Path | None = None,
    timestamps: str | Path | None = None,
    gps: str | Path | None = None,
    odometry: str | Path | None = None,
    dem: str | Path | None = None,
    georeference: str | Path | None = None,
    truth: str | Path | None = None,
    base: str | Path | None = None,
) -> SlamInputs:
    """Read and check everything a run needs, before any work.

    Args:
        frames_dir: the image folder, or a KITTI odometry sequence folder
            (:class:`slam_bridge.frontend.kitti.KittiSequence`: ``calib.txt``, ``image_0/`` or
            ``image_2/``, ``times.txt``; its ``poses.txt`` is not read: it is in the first
            camera's frame, see ``geoseg slam simulate-logs``).
        camera: its ``camera.json`` (default: in the folder).
        timestamps: a timestamps CSV (default: see :class:`ImageFolder`).
        gps: GPS log CSV.
        odometry: wheel-odometry CSV.
        dem: road DEM CSV.
        georeference: JSON with the world origin's WGS84 position (``origin_lat_deg``,
            ``origin_lon_deg``, ``origin_alt_m``; default: ``frames_dir/gis/georeference.json``
            when present; a GPS log in WGS84 without it puts the origin at its first fix).
        truth: true poses in the GPS's world frame (:func:`read_truth_csv`), for evaluation
            only (default: the folder's ``poses.csv``, as a render writes it). A truth whose
            positions are far from the GPS fixes is refused (given) or ignored (the folder's).
        base: an image base (``geoseg base build``) in the GPS's world frame: frames localised
            against it give fixes (:mod:`slam_bridge.system.base_fixes`).

    Raises:
        SlamError: any unreadable or inconsistent input, naming the file and the problem
            (logs that do not overlap the images' time span included; images of another size
            than the first).
    """
    from geoseg.synth.georef import Georeference
    from slam_bridge.frontend.kitti import KITTI_CAMERA_HEIGHT_M, KittiSequence, is_kitti_sequence

    kitti = camera is None and is_kitti_sequence(frames_dir)
    if kitti:
        frames = KittiSequence(frames_dir, timestamps=timestamps)
    else:
        frames = ImageFolder(frames_dir, camera=camera, timestamps=timestamps)
    frames.check_sizes()
    cam_path = Path(camera) if camera is not None else Path(frames_dir) / "camera.json"
    rig = _read_rig(cam_path)
    if kitti and not cam_path.is_file():
        rig = VehicleRig(camera_height_m=KITTI_CAMERA_HEIGHT_M)
    span = (float(frames.timestamps[0]), float(frames.timestamps[-1]))
    geo_path = (
        Path(georeference) if georeference else Path(frames_dir) / "gis" / "georeference.json"
    )
    georef = _read_georef(geo_path) if (georeference or geo_path.is_file()) else None
    inputs = SlamInputs(frames, rig, georef=georef)
    if gps is not None:
        log = read_gps_csv(gps)
        _check_overlap(log.path, log.timestamps, span)
        xy = log.xy
        if xy is None:  # WGS84: into the world frame of the georeference (or one at the fix)
            valid = np.isfinite(log.lat_lon[:, 0])
            if georef is None:
                first = log.lat_lon[valid][0]
                georef = inputs.georef = Georeference(float(first[0]), float(first[1]), 0.0)
            xy = np.full((log.timestamps.size, 2), np.nan)
            lat, lon = log.lat_lon[valid, 0], log.lat_lon[valid, 1]
            xyz = georef.wgs84_to_world(lat, lon, np.full(lat.size, georef.origin_alt_m))
            xy[valid] = xyz[:, :2]
        inputs.gps_timestamps, inputs.gps_xy = log.timestamps, xy
    if odometry is not None:
        t, v, yaw_rate = read_odometry_csv(odometry)
        _check_overlap(Path(odometry), t, span)
        inputs.odometry = OdometryDistance(t, v, yaw_rate)
    if dem is not None:
        inputs.dem = read_dem_csv(dem)
    if base is not None:
        if not (Path(base) / "poses.csv").is_file():
            raise SlamError(f"--base {base}: not an image base (no poses.csv): geoseg base build")
        inputs.base = Path(base)
    poses = Path(truth) if truth is not None else Path(frames_dir) / "poses.csv"
    if truth is not None or poses.is_file():
        inputs.truth = _checked_truth(poses, inputs, given=truth is not None)
    return inputs


def run_image_slam(
    inputs: SlamInputs,
    out_dir: str | Path,
    config: ImageSlamConfig | None = None,
    *,
    overwrite: bool = False,
    progress: bool = True,
    bridge=None,
) -> Path:
    """Run the SLAM over ``inputs`` and write its outputs (module docstring).

    Args:
        bridge: a :class:`slam_bridge.bridge.worker.BridgeWorker` (building constraints chosen
            by a network, :func:`slam_bridge.bridge.builder.build_bridge`), or None.

    Returns:
        ``out_dir``.

    Raises:
        SlamError: the SLAM could not start (too few frames or tracks), a non-finite estimate.
        GeosegError: ``out_dir`` holds other files (without ``overwrite``) or is not writable.
    """
    from geoseg.output_dir import prepare_output_dir, record_outputs, remove_outputs

    cfg = config or ImageSlamConfig()
    out = prepare_output_dir(out_dir, producer=PRODUCER, overwrite=overwrite)
    remove_outputs(out, ["summary.json"])  # unfinished until written again (only our own)
    record_outputs(out, OUTPUTS)
    t0 = time.perf_counter()
    gps = _gps_constraints(inputs, cfg)
    result, tracks = run_on_images(inputs, cfg, progress, bridge=bridge, gps=gps)
    seconds = time.perf_counter() - t0
    frame_of = np.searchsorted(inputs.frames.timestamps, result.map.timestamps)
    summary = {
        "method": cfg.method,
        "frames": len(inputs.frames),
        # every frame read by the front end; the ones after the last keyframe have
        # extrapolated poses (frames_with_pose)
        "frames_processed": int(tracks.timings.get("frames", frame_of[-1] + 1)),
        "keyframes": result.map.num_keyframes,
        "segments": int(result.map.segment.max()) + 1,
        "tracking_failures": result.tracking_failures,
        "bridged_keyframes": result.bridged,
        "georeferenced": bool(result.georeferenced),
        "map_points": int(result.map.triangulated.sum()),
        "gps_fused_keyframes": sum(r.gps_used for r in result.records),
        "seconds": seconds,
        "frames_per_second": int(tracks.timings.get("frames", frame_of[-1] + 1)) / seconds,
        "frontend_seconds": float(tracks.timings.get("total", 0.0)),
    }
    if bridge is not None:
        a = bridge.constraints.association
        summary.update(
            association=cfg.bridge.association,
            bridge_mode=_bridge_mode(cfg.bridge),
            building_keyframes=sum("building" in r.constraints for r in result.records),
            associated_points=0 if a is None else int(a.associated.sum()),
        )
        if cfg.bridge.colour_transfer is not None and cfg.bridge.association != "raycast":
            summary["colour_transfer"] = cfg.bridge.colour_transfer  # the network's reference
        if summary["associated_points"] == 0:  # documented fallback: no building constraint
            logger.warning(
                "no map point was associated with a facade: is the building model in the "
                "images' world frame, and does it cover the route? (no building constraint)"
            )
    if inputs.base is not None:
        summary.update(base_fixes_of(inputs, cfg).summary())
        summary["base_fused_keyframes"] = sum("base" in r.constraints for r in result.records)
        if result.adjustment is not None:
            summary["base_adjustment"] = result.adjustment
    if gps is not None and gps.bias is not None and gps.bias.history:
        _, _, b, _, facades, p_biased = gps.bias.history[-1]
        summary.update(  # the last estimate of the GPS's bias (the fixes less it were fused)
            gps_bias_m=[float(b[0]), float(b[1])],
            gps_bias_facades=int(facades),
            gps_biased_probability=float(p_biased),
        )
    health = assess_run(  # against the fixes the run fused (less their estimated bias)
        result,
        gps=gps or _base_constraints(inputs, cfg),
        odometry=inputs.odometry,
        antenna_c=np.asarray(inputs.rig.antenna_c, dtype=np.float64),
        config=cfg.health,
    )
    summary.update(status=health.status, status_reasons=health.reasons, checks=health.figures)
    poses = frame_poses(result, inputs.frames.timestamps)
    summary["frames_with_pose"] = {s: int(np.sum(poses.source == s)) for s in POSE_SOURCES}
    if inputs.truth is not None:
        summary.update(evaluate_run(result, inputs))
    from slam_bridge.system import outputs as so

    so.write_trajectory_csv(out / "trajectory.csv", result, frame_of, inputs.georef)
    so.write_frame_poses(out, poses)
    so.write_keyframe_log(out / "keyframes.csv", result, frame_of)
    so.write_map_points(out / "map_points.ply", result.map)
    base = _base_constraints(inputs, cfg)
    save_map(out / "map.npz", result, inputs, bridge, gps, base)  # for `geoseg slam refine`
    so.plot_run(out / "trajectory.png", result, inputs, title=f"{cfg.method}: {out.name}")
    so.write_summary(out / "summary.json", summary)
    return out


def evaluate_run(result: SlamResult, inputs: SlamInputs) -> dict:
    """Errors of the keyframes against the ground truth (``poses.csv``) and of the GPS fixes.

    Returns:
        ``translation_error_m`` (mean horizontal error, no alignment), ``translation_error_3d_m``,
        ``rotation_error_deg`` (mean), ``gps_error_m`` (mean horizontal error of the valid
        fixes over the keyframes' time span, each against the true antenna position at the
        fix's own time: :func:`gps_fix_errors`) and their ratio ``translation_error_over_gps``;
        over the keyframes placed in the world frame only (``keyframes_in_world``). After an
        adjustment of the whole run (``result.adjustment``), ``loop_translation_error_m`` is
        the error of the positions the loop left and ``online_translation_error_m`` of those
        it gave each keyframe when it was made.
    """
    from slam_bridge.evaluation.metrics import rotation_errors

    t_true, R_true, T_true = inputs.truth
    m = result.map
    idx = np.clip(np.searchsorted(t_true, m.timestamps), 0, t_true.size - 1)
    if np.any(np.abs(t_true[idx] - m.timestamps) > 1e-6):
        raise SlamError("poses.csv: its timestamps do not match the images'")
    out: dict[str, float] = {}
    keep = result.in_world
    if not keep.any():  # a map in its first camera's frame: nothing to compare
        return out
    out["keyframes_in_world"] = int(keep.sum())
    e_h = np.linalg.norm(m.t_wc[keep, :2] - T_true[idx][keep, :2], axis=1)
    e_3 = np.linalg.norm(m.t_wc[keep] - T_true[idx][keep], axis=1)
    e_r = np.degrees(rotation_errors(m.R_wc[keep], R_true[idx][keep]))
    out.update(
        translation_error_m=float(e_h.mean()),
        translation_error_3d_m=float(e_3.mean()),
        rotation_error_deg=float(e_r.mean()),
    )
    if result.adjustment is not None:
        for name, t_wc in (("loop", result.loop_t_wc), ("online", m.t_wc_online)):
            if t_wc is not None:
                e = np.linalg.norm(t_wc[keep, :2] - T_true[idx][keep, :2], axis=1)
                out[f"{name}_translation_error_m"] = float(np.nanmean(e))
    if inputs.gps_xy is not None:
        t0, t1 = float(m.timestamps[keep][0]), float(m.timestamps[keep][-1])
        errors = gps_fix_errors(inputs, (t0, t1))
        if errors.size:
            out["gps_error_m"] = float(errors.mean())
            out["gps_fixes_evaluated"] = int(errors.size)
            out["translation_error_over_gps"] = out["translation_error_m"] / out["gps_error_m"]
    return out


def gps_fix_errors(inputs: SlamInputs, span: tuple[float, float] | None = None) -> np.ndarray:
    """Horizontal errors of the valid GPS fixes against the truth at each fix's own time.

    The true antenna position is the true pose interpolated at the fix's time (positions
    linearly, the lever arm with the nearest pose's rotation): a fix compared with the truth at
    another time (a keyframe's) would count the vehicle's motion in between as GPS error.

    Args:
        inputs: with ``gps_xy`` and ``truth``.
        span: ``(t0, t1)``: only the fixes in this time span (default: the truth's).

    Returns:
        ``(F,)`` metres, one per valid fix inside the span and the truth's time span.
    """
    t_true, R_true, T_true = inputs.truth
    t, xy = inputs.gps_timestamps, inputs.gps_xy
    lo, hi = (t_true[0], t_true[-1]) if span is None else span
    lo, hi = max(lo, t_true[0]), min(hi, t_true[-1])
    use = np.isfinite(xy).all(axis=1) & (t >= lo - 1e-9) & (t <= hi + 1e-9)
    if not use.any():
        return np.zeros(0)
    tf = t[use]
    pos = np.column_stack([np.interp(tf, t_true, T_true[:, i]) for i in range(3)])
    nearest = np.clip(np.searchsorted(t_true, tf), 0, t_true.size - 1)
    earlier = np.clip(nearest - 1, 0, t_true.size - 1)
    nearest = np.where(
        np.abs(t_true[earlier] - tf) < np.abs(t_true[nearest] - tf), earlier, nearest
    )
    antenna = np.asarray(inputs.rig.antenna_c, dtype=np.float64)
    true_antenna = pos + R_true[nearest] @ antenna
    return np.linalg.norm(xy[use] - true_antenna[:, :2], axis=1)


def run_on_images(
    inputs: SlamInputs,
    cfg: ImageSlamConfig | None = None,
    progress: bool = True,
    bridge=None,
    start=None,
    gps: GpsConstraints | None = None,
) -> tuple[SlamResult, ImageTracks]:
    """The run itself, for programs and benchmarks (no file written).

    Args:
        inputs: what the run reads.
        cfg: its settings.
        progress: show a progress bar.
        bridge: a :class:`slam_bridge.bridge.worker.BridgeWorker`: its building constraints join
            the fusion and it sees every keyframe (given the images of the start-up's keyframes
            when it has no ``image_at``); finished (every job applied) at the end.
        start: the start-up (default: :class:`TwoViewStart`, georeferenced by the GPS); an
            experiment with a known first pose gives a
            :class:`slam_bridge.slam.loop.KnownStartPoses`.
        gps: the GPS provider (default: from ``inputs`` and ``cfg``); given, it carries the
            run's bias estimate afterwards (``gps.bias``, with a building model).

    Returns:
        ``(the SLAM's result, the front end with its timings and counters)``.
    """
    cfg = cfg or ImageSlamConfig()
    gps = gps if gps is not None else _gps_constraints(inputs, cfg)
    base = _base_constraints(inputs, cfg)
    tracks = ImageTracks(inputs.frames, cfg.frontend, distance=inputs.odometry)
    init = cfg.init
    if gps is None and base is not None:  # the base's fixes alone: centimetres, not metres
        init = replace(init, refit_distance_m=cfg.base.refit_distance_m)
    start = start or TwoViewStart(
        init,
        inputs.rig,
        mapping=cfg.slam.mapping,
        outlier_gate_px=cfg.slam.tracking.outlier_gate_px,
        gps=gps or base,  # without a GPS, the base's fixes georeference the start
        odometry=inputs.odometry,
        dem=inputs.dem,
    )
    providers = [p for p in (gps, base) if p is not None]
    if inputs.dem is not None:
        providers.append(
            DemConstraints(inputs.dem, inputs.rig.camera_height_m, weight=cfg.dem_weight)
        )
    if inputs.odometry is not None:
        providers.append(OdometryConstraints(inputs.odometry, band=cfg.odometry_band))
    source = _Progress(tracks, progress)
    if cfg.vertical:
        providers.append(VerticalConstraints(source.image_at, tracks.K, cfg.vertical_lines))
    if bridge is not None:
        providers.append(bridge.constraints)
        if gps is not None and cfg.gps_bias.enabled:
            gps.bias = BuildingGpsBias(bridge.constraints, gps.camera_fix_at, cfg.gps_bias)
            # the GPS after the buildings: its estimate reads the association the building
            # rows of the same fusion used (a replayed run, experiments/replay.py, sets it then)
            providers.remove(gps)
            providers.append(gps)
        if bridge.image_at is None:
            frames = inputs.frames
            bridge.image_at = lambda t: frames[int(np.searchsorted(frames.timestamps, t))][1]
    try:
        result = run_slam(
            source, cfg.method, start, providers, cfg.slam, distance=inputs.odometry,
            on_keyframe=bridge,
        )  # fmt: skip
        if bridge is not None:
            bridge.finish(result.map)
    finally:
        source.bar.close()
        if bridge is not None:
            bridge.close()
    if base is not None and cfg.base.adjust and result.in_world.any():
        result.adjustment = adjust_on_fixes(result, inputs, base, gps)
    return result, tracks


# --------------------------------------------------------------------------------- internals
def _bridge_mode(cfg: BridgeConfig) -> str:
    """How the bridge's results joined the run, for ``summary.json``."""
    if not cfg.asynchronous:
        return "inline"
    if cfg.lag_keyframes is not None:
        return (
            f"repeatable: each keyframe's results applied {cfg.lag_keyframes} keyframes later, "
            "waited for when late"
        )
    return "as ready: results applied when done, never waited for (runs may differ)"


def _gps_constraints(inputs: SlamInputs, cfg: ImageSlamConfig) -> GpsConstraints | None:
    if inputs.gps_xy is None:
        return None
    return GpsConstraints(
        inputs.gps_timestamps,
        inputs.gps_xy,
        tolerance_s=cfg.gps_tolerance_s,
        interpolate_gap_s=cfg.gps_interpolate_gap_s,
        weight=cfg.gps_weight,
        antenna_c=np.asarray(inputs.rig.antenna_c, dtype=np.float64),
    )


def base_fixes_of(inputs: SlamInputs, cfg: ImageSlamConfig) -> BaseFixes | None:
    """The fixes of ``inputs.base`` (localised once, then kept on ``inputs``)."""
    if inputs.base is None:
        return None
    if inputs.base_fixes is None:
        inputs.base_fixes = localise_frames(inputs.frames, inputs.base, cfg.base)
    return inputs.base_fixes


def _base_constraints(inputs: SlamInputs, cfg: ImageSlamConfig) -> BaseConstraints | None:
    fixes = base_fixes_of(inputs, cfg)
    if fixes is None:
        return None
    return base_constraints(fixes, cfg.base, cfg.gps_interpolate_gap_s)


class _Progress:
    """The front end seen by the loop, with a progress bar over the frames."""

    def __init__(self, tracks: ImageTracks, enabled: bool) -> None:
        from tqdm import tqdm

        self.tracks = tracks
        self.K, self.image_size = tracks.K, tracks.image_size
        self.bar = tqdm(total=len(tracks.frames), unit="frame", desc="slam", disable=not enabled)
        self.last: KeyframeObservations | None = None

    def image_at(self, timestamp: float) -> np.ndarray | None:
        """The image of the keyframe given last, when it is the one at ``timestamp``."""
        last = self.last
        return last.image if last is not None and last.timestamp == timestamp else None

    def next_keyframe(self, slam_map) -> KeyframeObservations | None:
        obs = self.last = self.tracks.next_keyframe(slam_map)
        self.bar.n = len(self.tracks.frames) if obs is None else obs.frame_index + 1
        self.bar.refresh()
        return obs


def _read_rig(path: Path) -> VehicleRig:
    try:
        camera = json.loads(path.read_text())
    except (OSError, ValueError):
        return VehicleRig()  # the frame reader has already reported a bad camera.json
    kw = {}
    if "camera_height_m" in camera:
        kw["camera_height_m"] = float(camera["camera_height_m"])
    if "gps_antenna_c" in camera:
        kw["antenna_c"] = tuple(float(v) for v in camera["gps_antenna_c"])
    try:
        return VehicleRig(**kw)
    except (ValueError, TypeError) as err:
        raise SlamError(f"{path}: camera_height_m / gps_antenna_c: {err}") from None


def _read_georef(path: Path):
    from geoseg.synth.georef import Georeference

    try:
        data = json.loads(path.read_text())
        return Georeference(
            float(data["origin_lat_deg"]),
            float(data["origin_lon_deg"]),
            float(data.get("origin_alt_m", 0.0)),
        )
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise SlamError(
            f"{path}: not a georeference (origin_lat_deg, origin_lon_deg): {err}"
        ) from None


def _check_overlap(path: Path, t: np.ndarray, span: tuple[float, float]) -> None:
    if t[-1] < span[0] or t[0] > span[1]:
        raise SlamError(
            f"{path}: its times {t[0]:.3f}-{t[-1]:.3f} s do not overlap the images' "
            f"{span[0]:.3f}-{span[1]:.3f} s (same clock expected)"
        )


def _checked_truth(path: Path, inputs: SlamInputs, given: bool):
    """The truth of ``path`` when it can be in the GPS's frame (module docstring)."""
    truth = read_truth_csv(path)
    if inputs.gps_xy is None:
        return truth
    saved, inputs.truth = inputs.truth, truth
    errors = gps_fix_errors(inputs)
    inputs.truth = saved
    if errors.size and np.median(errors) <= TRUTH_GPS_MAX_M:
        return truth
    why = (
        "its times do not overlap the GPS log's"
        if not errors.size
        else f"its positions are {np.median(errors):.0f} m from the GPS fixes (median)"
    )
    message = (
        f"{path}: not a truth in the GPS's world frame: {why}; give true poses in that frame "
        "(geoseg slam simulate-logs writes truth.csv beside its logs)"
    )
    if given:
        raise SlamError(message)
    logger.warning("%s; no evaluation", message)
    return None


def read_truth_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True poses of a ``poses.csv`` (columns ``timestamp, tx, ty, tz, r00 ... r22``).

    Returns:
        ``(timestamps (T,), R_wc (T, 3, 3), t_wc (T, 3))``.

    Raises:
        SlamError: missing columns, non-finite values, times that do not increase.
    """
    path = Path(path)
    names = ["timestamp", "tx", "ty", "tz"] + [f"r{i}{j}" for i in range(3) for j in range(3)]
    cols = read_columns(path, names)
    for n in names:
        check_finite(f"{path}: {n}", cols[n])
    R = np.stack([cols[f"r{i}{j}"] for i in range(3) for j in range(3)], axis=1).reshape(-1, 3, 3)
    t = np.column_stack([cols["tx"], cols["ty"], cols["tz"]])
    if np.any(np.diff(cols["timestamp"]) <= 0):
        raise SlamError(f"{path}: timestamps must increase")
    return cols["timestamp"], R, t
