"""One bundle adjustment over a whole run, constrained to the building model and the DEM: a
pseudo ground truth (thesis §3.7; ``geoseg slam refine``).

Where a sequence has no ground truth (the thesis's real drives), the run's map is adjusted once
more, all keyframes together, after the drive: every observation the run kept, every GPS fix,
the road DEM under every camera, the wheel odometry between successive keyframes and every map
point associated with a facade of the building model. The online SLAM could only see a window
of keyframes and the constraints up to the newest one; the global problem sees all of them, so
a keyframe benefits from the facades and fixes that come after it as well.

The problem (:func:`refine_map`), over the keyframes of the run that are in the world frame and
the points seen at least ``min_views`` times by them:

* reprojection rows (:class:`slam_bridge.factors.reprojection.ReprojectionFactor`,
  ``pixel_sigma``, Huber beyond ``pixel_huber`` pixels: outliers the run missed cost linearly);
* a GPS row per keyframe with a fix (:class:`slam_bridge.slam.fusion.GpsConstraints`' rule:
  the fix at its time, or the two around it interpolated; the antenna's lever arm removed),
  less the receiver's bias as the run estimated it from the building model when it did, its
  weight lowered by the estimate's variance as the run's fusion lowers it (``gps_bias``;
  :mod:`slam_bridge.bridge.gps_bias`);
* a base row per keyframe with a fix from an image base (the camera's own position, each fix
  with its own weight: :class:`slam_bridge.system.base_fixes.BaseConstraints`), Huber beyond
  ``base_huber`` sigmas: a fix on a repeated facade is an outlier;
* a DEM row per keyframe on the DEM's roads (:class:`slam_bridge.factors.dem.DEMFactor`);
* a vertical row per keyframe whose image gave world down (the run's vertical line segments,
  :class:`slam_bridge.factors.vertical.VerticalFactor`, ``vertical_sigma_deg`` per axis, Huber):
  GPS and DEM hold positions only, and would leave the map free to roll about a straight
  road or to pitch along the DEM's errors;
* odometry rows between successive keyframes of one segment, with the run's dead zone
  (:class:`slam_bridge.slam.fusion.OdometryConstraints.window_factors`);
* a point-plane row per associated point (:class:`slam_bridge.factors.building.
  BuildingFactor`, Geman-McClure of scale ``building_sigma_m``). The association is the run's
  own when its map file has one and the facade table is the run's (``association: auto`` or
  ``saved``): the run chose building points with a network, which tells a facade point from a
  tree in front of it, and a point-to-nearest-facade rule cannot. Otherwise (``nearest``) each
  point is given its nearest facade within ``radius_m``, the robust kernel absorbing the
  wrong ones. Together the building rows weigh at most ``building_share`` of the GPS rows'
  total weight (the run's ``bridge.window_weight`` rule: a GIS model off by a metre must not
  outvote a 0.75 m GPS); without a GPS they are the horizontal reference and are not capped.

Two ways to solve it (``method``): ``joint`` minimises the weighted sum of all the rows by
Levenberg-Marquardt (:func:`slam_bridge.ba.solvers.lm.levenberg_marquardt`); ``barrier`` is
the thesis's constrained form at the scale of the sequence, ``X* = argmin zeta`` (reprojection
and odometry) then ``argmin gamma / (t - zeta) + sum C_i`` with ``t = t_ratio zeta(X*)``
(:func:`slam_bridge.ba.solvers.barrier.solve_barrier`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from geoseg.errors import check_positive
from slam_bridge.ba.factor import Factor
from slam_bridge.ba.robust import HuberKernel
from slam_bridge.ba.solvers.barrier import BarrierConfig, solve_barrier
from slam_bridge.ba.solvers.lm import BAObjective, LMConfig, levenberg_marquardt
from slam_bridge.ba.state import BAState
from slam_bridge.bridge.association import nearest_facades
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError
from slam_bridge.factors.building import BuildingFactor
from slam_bridge.factors.dem import DEMFactor
from slam_bridge.factors.gps import GPSFactor
from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.factors.vertical import VerticalFactor
from slam_bridge.slam.fusion import GpsConstraints, OdometryConstraints
from slam_bridge.system.map_file import SavedMap

logger = logging.getLogger(__name__)

__all__ = [
    "METHODS",
    "ASSOCIATIONS",
    "RefineConfig",
    "RefineResult",
    "refine_map",
    "refine_run",
]

METHODS = ("joint", "barrier")
ASSOCIATIONS = ("auto", "saved", "nearest")


@dataclass
class RefineConfig:
    """Settings of the global bundle adjustment (module docstring).

    Attributes:
        method: ``joint`` (one weighted least squares) or ``barrier`` (eq. 2.3 over the
            sequence).
        pixel_sigma: pixel sigma of a reprojection row.
        pixel_huber: Huber threshold of a reprojection row, pixels (None: least squares).
        gps_weight: weight of a GPS row (per square metre; the run's ``gps_weight``).
        gps_bias: the fixes less the bias the run estimated, when its map has one.
        gps_tolerance_s: a fix within this time of a keyframe is its fix.
        gps_interpolate_gap_s: otherwise the fixes around it are interpolated when at most this
            far apart (None: not).
        dem_weight: weight of a DEM row (per square metre).
        dem_max_distance_m: a camera farther than this from every DEM segment has no DEM row.
        vertical_sigma_deg: standard deviation of a measured vertical, per axis, degrees
            (None: no vertical row).
        base_huber: Huber threshold of a base row, in sigmas of its fix (None: least squares).
        odometry_band: dead zone of the odometry rows, in sigmas of the odometry's distance.
        association: ``auto`` (the run's when it has one, else ``nearest``), ``saved`` (the
            run's, required) or ``nearest``.
        radius_m: ``nearest``: farthest facade of a point.
        building_sigma_m: Geman-McClure scale of a building row, metres.
        building_share: the building rows weigh together at most this share of the GPS rows'
            total weight (None: no cap).
        min_views: a point is kept when at least this many keyframes observe it.
        iterations: Levenberg-Marquardt iterations (``joint``; ``barrier``: of ``X*``).
        barrier_iterations: ``barrier``: iterations of the barrier solve.
        t_ratio: ``barrier``: ``t = t_ratio zeta(X*)``.
    """

    method: str = "joint"
    pixel_sigma: float = 1.0
    pixel_huber: float | None = 3.0
    gps_weight: float = 1.0
    gps_bias: bool = True
    gps_tolerance_s: float = 0.02
    gps_interpolate_gap_s: float | None = 1.5
    # chosen on bench/refine.py's tuning drives (bench/splits.py REFINE_TUNING_SEEDS): the
    # DEM's error is smooth and up to ~2 m, and at 1.0 (the run's) the whole trajectory
    # follows it (3D error 0.48 / 0.32 m, 0.31 / 0.23 deg; at 0.1: 0.45 / 0.24 m, 0.17 /
    # 0.11 deg; horizontal errors unchanged)
    dem_weight: float = 0.1
    dem_max_distance_m: float = 15.0
    vertical_sigma_deg: float | None = 0.5
    base_huber: float | None = 3.0
    odometry_band: float = 2.0
    association: str = "auto"
    radius_m: float = 1.0
    building_sigma_m: float = 0.5
    building_share: float | None = 0.4
    min_views: int = 2
    iterations: int = 50
    barrier_iterations: int = 30
    t_ratio: float = 1.05

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise SlamError(f"method: expected one of {METHODS}, got {self.method!r}")
        if self.association not in ASSOCIATIONS:
            raise SlamError(
                f"association: expected one of {ASSOCIATIONS}, got {self.association!r}"
            )
        for name in (
            "pixel_sigma", "gps_weight", "gps_tolerance_s", "dem_weight", "dem_max_distance_m",
            "odometry_band", "radius_m", "building_sigma_m",
        ):  # fmt: skip
            check_positive(name, getattr(self, name))
        for name in (
            "pixel_huber",
            "base_huber",
            "gps_interpolate_gap_s",
            "building_share",
            "vertical_sigma_deg",
        ):
            if getattr(self, name) is not None:
                check_positive(name, getattr(self, name))
        if self.min_views < 2:
            raise SlamError(f"min_views: expected >= 2, got {self.min_views}")
        if self.iterations < 1 or self.barrier_iterations < 1:
            raise SlamError("iterations, barrier_iterations: expected >= 1")
        if not self.t_ratio > 1:
            raise SlamError(f"t_ratio: expected > 1, got {self.t_ratio}")


@dataclass
class RefineResult:
    """The refined map.

    Attributes:
        map: the run's :class:`SavedMap` with the refined poses and points (keyframes outside
            the world frame, and points outside the problem, as the run left them).
        refined: ``(C,)`` bool, the keyframes the adjustment moved.
        figures: what the adjustment did (rows per family, cost before and after, the
            keyframes' mean displacement, iterations, seconds, ...).
    """

    map: SavedMap
    refined: np.ndarray
    figures: dict


def refine_map(
    saved: SavedMap,
    config: RefineConfig | None = None,
    *,
    facades: Facades | None = None,
    dem=None,
    gps: GpsConstraints | None = None,
    base=None,
    odometry=None,
) -> RefineResult:
    """The global constrained bundle adjustment of a run's map (module docstring).

    Args:
        saved: the run's map (:func:`slam_bridge.system.map_file.load_map`).
        config: its settings.
        facades: the building model (the run's ``--buildings`` table for its association).
        dem: the road DEM (:class:`slam_bridge.factors.dem.DemSegments`).
        gps: the GPS fixes (weight and lever arm of ``config`` and ``saved`` apply, not its
            own).
        base: fixes of the camera from an image base, each with its weight
            (:class:`slam_bridge.system.base_fixes.BaseConstraints`; its tolerance and
            interpolation apply).
        odometry: the wheel odometry (:class:`slam_bridge.slam.initialization.
            OdometryDistance`).

    Returns:
        A :class:`RefineResult`.

    Raises:
        SlamError: fewer than two keyframes in the world frame, no observation left, nothing
            that holds the map in the world (no GPS, base or building row), ``association:
            saved`` on a map without one, an association that refers to facades the table
            lacks.
    """
    cfg = config or RefineConfig()
    t0 = time.perf_counter()
    kf = np.flatnonzero(saved.in_world & saved.placed)
    if kf.size < 2:
        raise SlamError(
            f"refine: {kf.size} keyframe(s) in the world frame, expected at least 2 (a run "
            "that was never georeferenced has no world frame to refine in)"
        )
    state, rep, point_ids = _vision(saved, kf, cfg)
    problem = SimpleNamespace(camera_ids=kf, state=state)
    vision: list[Factor] = [rep]
    figures: dict = {
        "keyframes": int(kf.size),
        "points": int(point_ids.size),
        "observations": int(rep.cameras.size),
    }
    if odometry is not None:
        odo = OdometryConstraints(odometry, band=cfg.odometry_band)
        rows = odo.window_factors(saved, problem)
        vision += rows
        figures["odometry_rows"] = int(sum(f.pairs.shape[0] for f in rows[:1]))
    constraints: list[Factor] = []
    if cfg.vertical_sigma_deg is not None:
        v = _vertical_factor(saved, kf, cfg.vertical_sigma_deg)
        if v is not None:
            constraints.append(v)
        figures["vertical_rows"] = 0 if v is None else int(v.cameras.size)
    gps_total = 0.0
    if gps is not None:
        g = _gps_factor(saved, kf, state, gps, cfg)
        if g is not None:
            constraints.append(g)
            gps_total = float(np.sum(g.sqrt_weights**2))
        figures["gps_rows"] = 0 if g is None else int(g.cameras.size)
        figures["gps_bias_removed"] = bool(cfg.gps_bias and saved.gps_bias_xy is not None)
    if base is not None:
        b = _base_factor(saved, kf, base, cfg)
        if b is not None:
            constraints.append(b)
        figures["base_rows"] = 0 if b is None else int(b.cameras.size)
    if dem is not None:
        d = _dem_factor(saved, state, dem, cfg)
        if d is not None:
            constraints.append(d)
        figures["dem_rows"] = 0 if d is None else int(d.cameras.size)
    if facades is not None:
        b, method = _building_factor(saved, state, point_ids, facades, cfg, gps_total)
        if b is not None:
            constraints.append(b)
        figures["building_rows"] = 0 if b is None else int(b.points.size)
        figures["association"] = method
    if not any(isinstance(f, (GPSFactor, BuildingFactor)) for f in constraints):
        raise SlamError(
            "refine: nothing holds the map horizontally in the world frame: give a GPS log, "
            "an image base's fixes or a building model whose facades the map points lie near"
        )
    rms0 = _rms_px(rep, state)
    if cfg.method == "joint":
        res = levenberg_marquardt(
            BAObjective(vision + constraints), state, LMConfig(max_iterations=cfg.iterations)
        )
        final = res.state
        figures.update(
            iterations=int(res.iterations), initial_cost=float(res.initial_cost),
            cost=float(res.cost), termination=res.termination,
        )  # fmt: skip
    else:
        star = levenberg_marquardt(
            BAObjective(vision), state, LMConfig(max_iterations=cfg.iterations)
        )
        fused = solve_barrier(
            vision, constraints, star.state,
            BarrierConfig(t_ratio=cfg.t_ratio, max_iterations=cfg.barrier_iterations),
        )  # fmt: skip
        final = fused.state
        figures.update(
            iterations=int(star.iterations) + int(fused.iterations),
            zeta_star=float(fused.zeta_star), zeta=float(fused.zeta),
        )  # fmt: skip
    for f in constraints:
        figures[f"{f.name}_cost"] = float(f.cost(final))
    moved = np.linalg.norm(final.t_wc - state.t_wc, axis=1)
    figures.update(
        reprojection_rms_px_before=rms0,
        reprojection_rms_px=_rms_px(rep, final),
        keyframe_shift_m_mean=float(moved.mean()),
        keyframe_shift_m_max=float(moved.max()),
        seconds=time.perf_counter() - t0,
    )
    R, T, X = saved.R_wc.copy(), saved.t_wc.copy(), saved.X_w.copy()
    R[kf], T[kf], X[point_ids] = final.R_wc, final.t_wc, final.X_w
    refined = np.zeros(saved.num_keyframes, dtype=bool)
    refined[kf] = True
    out = dataclasses.replace(saved, R_wc=R, t_wc=T, X_w=X)
    return RefineResult(out, refined, figures)


# --------------------------------------------------------------------------------- internals
def _vision(saved: SavedMap, kf: np.ndarray, cfg: RefineConfig):
    """The state (the run's poses and points) and the reprojection rows of the problem.

    Returns:
        ``(state, reprojection factor, point ids (P,) of the state's points)``.
    """
    cam_of = np.full(saved.num_keyframes, -1, np.int64)
    cam_of[kf] = np.arange(kf.size)
    X = saved.X_w
    ok_point = saved.triangulated & np.isfinite(X).all(axis=1)
    use = saved.obs_active & (cam_of[saved.obs_keyframe] >= 0) & ok_point[saved.obs_point]
    views = np.bincount(saved.obs_point[use], minlength=X.shape[0])
    use &= views[saved.obs_point] >= cfg.min_views
    if not use.any():
        raise SlamError(
            f"refine: no point is seen by {cfg.min_views} keyframes of the world frame: "
            "nothing to adjust"
        )
    point_ids = np.unique(saved.obs_point[use])
    pt_of = np.full(X.shape[0], -1, np.int64)
    pt_of[point_ids] = np.arange(point_ids.size)
    state = BAState(saved.R_wc[kf], saved.t_wc[kf], X[point_ids])
    kernel = None if cfg.pixel_huber is None else "huber"
    scale = None if cfg.pixel_huber is None else cfg.pixel_huber / cfg.pixel_sigma
    rep = ReprojectionFactor(
        saved.K, cam_of[saved.obs_keyframe[use]], pt_of[saved.obs_point[use]],
        saved.obs_uv[use], sigma=cfg.pixel_sigma, kernel=kernel, kernel_scale=scale,
    )  # fmt: skip
    return state, rep, point_ids


def _gps_factor(saved, kf, state, gps: GpsConstraints, cfg: RefineConfig) -> GPSFactor | None:
    """A row per keyframe with a fix (the fix less the antenna's lever arm at the run's
    rotation)."""
    xy, var = gps.xy, np.zeros(gps.timestamps.size)
    if cfg.gps_bias and saved.gps_bias_xy is not None:
        t_b, b = saved.gps_bias_timestamps, saved.gps_bias_xy
        xy = xy - np.column_stack([np.interp(gps.timestamps, t_b, b[:, i]) for i in range(2)])
        var = np.interp(gps.timestamps, t_b, saved.gps_bias_var)
    rule = GpsConstraints(
        gps.timestamps, xy, tolerance_s=cfg.gps_tolerance_s,
        interpolate_gap_s=cfg.gps_interpolate_gap_s, antenna_c=saved.antenna_c,
    )  # fmt: skip
    cams, fixes, weights = [], [], []
    for i, k in enumerate(kf):
        t = float(saved.timestamps[k])
        fix = rule.camera_fix_at(t, state.R_wc[i])
        if fix is not None:
            cams.append(i)
            fixes.append(fix)
            # an uncertain bias is noise on the fix: sigma^2 + var(b) (the run's rule)
            weights.append(1.0 / (1.0 / cfg.gps_weight + np.interp(t, gps.timestamps, var)))
    if not cams:
        logger.warning("refine: no GPS fix at any keyframe's time (no GPS row)")
        return None
    return GPSFactor(np.array(cams), np.array(fixes), np.array(weights), name="gps")


def _base_factor(saved, kf, base, cfg: RefineConfig) -> GPSFactor | None:
    """A row per keyframe with a fix from the image base, weighted as the run weighed it."""
    cams, fixes, weights = [], [], []
    for i, k in enumerate(kf):
        t = float(saved.timestamps[k])
        fix = base.fix_at(t)
        if fix is not None:
            cams.append(i)
            fixes.append(fix)
            weights.append(base.weight_at(t))
    if not cams:
        logger.warning("refine: no base fix at any keyframe's time (no base row)")
        return None
    kernel = None if cfg.base_huber is None else HuberKernel(cfg.base_huber)
    return GPSFactor(np.array(cams), np.array(fixes), np.array(weights), kernel=kernel, name="base")


def _vertical_factor(saved, kf, sigma_deg: float) -> VerticalFactor | None:
    """A row per keyframe with a measured vertical (an isotropic covariance of
    ``sigma_deg``: the run keeps the directions, not their covariances)."""
    down = saved.down_c[kf]
    has = np.flatnonzero(np.isfinite(down).all(axis=1))
    if has.size == 0:
        return None
    d = down[has] / np.linalg.norm(down[has], axis=1, keepdims=True)
    # any orthonormal pair orthogonal to d: d x a (a an axis far from d), then d x that
    axis = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    b0 = np.cross(d, axis)
    b0 /= np.linalg.norm(b0, axis=1, keepdims=True)
    basis = np.stack([b0, np.cross(d, b0)], axis=1)
    cov = np.broadcast_to(np.eye(2) * np.radians(sigma_deg) ** 2, (has.size, 2, 2))
    return VerticalFactor(has, basis, cov)


def _dem_factor(saved, state, dem, cfg: RefineConfig) -> DEMFactor | None:
    """A row per camera on the DEM's roads."""
    near = np.flatnonzero(dem.distance_at(state.t_wc[:, :2]) <= cfg.dem_max_distance_m)
    if near.size == 0:
        logger.warning(
            "refine: no keyframe within %.0f m of the DEM's roads", cfg.dem_max_distance_m
        )
        return None
    return DEMFactor(near, dem, saved.camera_height_m, np.full(near.size, cfg.dem_weight))


def _building_factor(saved, state, point_ids, facades: Facades, cfg: RefineConfig, gps_total):
    """Point-plane rows of the associated points (module docstring).

    Returns:
        ``(factor or None, the association used: "saved" or "nearest")``.
    """
    method = cfg.association
    if method == "auto":
        method = "saved" if saved.facade is not None else "nearest"
    if method == "saved":
        if saved.facade is None:
            raise SlamError(
                "association saved: the run has no building association (it ran without "
                "--buildings); use association nearest"
            )
        facade, weight = saved.facade[point_ids], saved.facade_weight[point_ids]
        if facade.size and facade.max() >= len(facades):
            raise SlamError(
                f"association saved: the run's association refers to facade {int(facade.max())} "
                f"but the building model has {len(facades)}: give the table the run used "
                "(--buildings), or association nearest"
            )
    else:
        facade, _ = nearest_facades(facades, state.X_w, cfg.radius_m)
        weight = (facade >= 0).astype(np.float64)
    rows = np.flatnonzero((facade >= 0) & (weight > 0))
    if rows.size == 0:
        logger.warning("refine: no map point associated with a facade (no building row)")
        return None, method
    w = weight[rows].astype(np.float64)
    if (
        cfg.building_share is not None
        and gps_total > 0
        and w.sum() > cfg.building_share * gps_total
    ):
        w *= cfg.building_share * gps_total / w.sum()
    f = facade[rows]
    factor = BuildingFactor(
        rows, facades.normal[f], facades.d[f], w, sigma=cfg.building_sigma_m, name="building"
    )
    return factor, method


def _rms_px(rep: ReprojectionFactor, state: BAState) -> float:
    """Root mean square of the reprojection errors, pixels (valid rows)."""
    r, ok = rep.residuals(state)
    e = np.linalg.norm(r[ok], axis=1) * rep.sigma
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


# ------------------------------------------------------------------------------------ the stage
PRODUCER = "slam refine"
OUTPUTS = [
    "trajectory.csv",
    "frame_poses.csv",
    "trajectory_tum.txt",
    "trajectory_kitti.txt",
    "map_points.ply",
    "summary.json",
]


def refine_run(
    run_dir: str | Path,
    out_dir: str | Path,
    config: RefineConfig | None = None,
    *,
    buildings: str | Path | None = None,
    dem: str | Path | None = None,
    gps: str | Path | None = None,
    odometry: str | Path | None = None,
    truth: str | Path | None = None,
    overwrite: bool = False,
) -> Path:
    """Refine the run in ``run_dir`` (its ``map.npz``) and write the refined trajectory.

    Outputs in ``out_dir`` (a stage; ``summary.json`` last), in the formats of a run
    (:mod:`slam_bridge.system.outputs`): ``trajectory.csv`` (the keyframes; the ones the run
    had outside the world frame as it left them), ``frame_poses.csv``, ``trajectory_tum.txt``,
    ``trajectory_kitti.txt``, ``map_points.ply`` and ``summary.json`` (the adjustment's
    figures, :attr:`RefineResult.figures`, and with ``truth`` the errors of the refined and of
    the run's keyframes against it: ``translation_error_m``, ``run_translation_error_m``, ...).
    The folder is a reference for ``geoseg slam-eval run --reference``. A run with an image
    base saved its fixes in its map: they join the adjustment as base rows.

    Args:
        run_dir: a ``geoseg slam run`` output folder.
        out_dir: the output folder.
        config: the adjustment's settings.
        buildings: facade table CSV (the run's ``--buildings``).
        dem: road DEM CSV.
        gps: GPS log CSV.
        odometry: wheel-odometry CSV.
        truth: true poses (``poses.csv``), for evaluation only.
        overwrite: write into a folder of other files.

    Returns:
        ``out_dir``.

    Raises:
        SlamError: no map file in ``run_dir``, unreadable inputs, an ill-posed problem
            (:func:`refine_map`).
        GeosegError: ``out_dir`` holds other files (without ``overwrite``).
    """
    from geoseg.output_dir import prepare_output_dir, record_outputs, remove_outputs
    from slam_bridge.system.map_file import load_map
    from slam_bridge.system.reference import Trajectory, compare_trajectories, read_trajectory
    from slam_bridge.system.sensor_logs import read_dem_csv, read_odometry_csv

    cfg = config or RefineConfig()
    saved = load_map(run_dir)  # before anything is written: a bad run folder leaves no output
    facades = None if buildings is None else Facades.read_csv(buildings)
    terrain = None if dem is None else read_dem_csv(dem)
    fixes = None if gps is None else _read_gps(gps, saved)
    distance = None
    if odometry is not None:
        from slam_bridge.slam.initialization import OdometryDistance

        distance = OdometryDistance(*read_odometry_csv(odometry))
    reference = None if truth is None else read_trajectory(truth)
    out = prepare_output_dir(out_dir, producer=PRODUCER, overwrite=overwrite)
    remove_outputs(out, ["summary.json"])
    record_outputs(out, OUTPUTS)
    base = None
    if saved.base_xy is not None:  # a run with an image base: its fixes, as it weighed them
        base = _SavedBaseFixes(saved, cfg.gps_interpolate_gap_s)
    result = refine_map(
        saved, cfg, facades=facades, dem=terrain, gps=fixes, base=base, odometry=distance
    )
    summary = {"method": cfg.method, "run": str(Path(run_dir).resolve()), **result.figures}
    if reference is not None:
        world = result.refined
        for prefix, m in (("", result.map), ("run_", saved)):
            est = Trajectory(m.timestamps[world], m.R_wc[world], m.t_wc[world], "keyframes")
            figures = compare_trajectories(est, reference)
            summary.update({f"{prefix}{k}": v for k, v in figures.items() if k != "unmatched"})
    _write_outputs(out, result, summary)
    return out


class _SavedBaseFixes(GpsConstraints):
    """The image base's fixes a run saved (the camera's position, each with its weight): what
    :func:`_base_factor` reads of :class:`slam_bridge.system.base_fixes.BaseConstraints`."""

    def __init__(self, saved: SavedMap, interpolate_gap_s: float | None) -> None:
        super().__init__(
            saved.base_timestamps, saved.base_xy, tolerance_s=0.02,
            interpolate_gap_s=interpolate_gap_s,
        )  # fmt: skip
        self.weights = np.asarray(saved.base_weight, dtype=np.float64)

    def fix_weights(self) -> np.ndarray:
        """``(B,)`` the weights the run gave its fixes."""
        return self.weights


def _read_gps(path, saved: SavedMap) -> GpsConstraints:
    """The GPS log in the world frame (a WGS84 log through the run's georeference)."""
    from slam_bridge.system.sensor_logs import read_gps_csv

    log = read_gps_csv(path)
    xy = log.xy
    if xy is None:
        if saved.georef is None:
            raise SlamError(
                f"{path}: a WGS84 GPS log, but the run has no georeference to put it in the "
                "world frame: give a log in world x, y"
            )
        from geoseg.synth.georef import Georeference

        g = Georeference(*(float(v) for v in saved.georef))
        xy = np.full((log.timestamps.size, 2), np.nan)
        ok = np.isfinite(log.lat_lon[:, 0])
        lat, lon = log.lat_lon[ok, 0], log.lat_lon[ok, 1]
        xy[ok] = g.wgs84_to_world(lat, lon, np.full(lat.size, g.origin_alt_m))[:, :2]
    return GpsConstraints(log.timestamps, xy)


def _write_outputs(out: Path, result: RefineResult, summary: dict) -> None:
    """The refined trajectory in a run's formats, then the summary."""
    from slam_bridge.slam.frame_poses import frame_poses
    from slam_bridge.system import outputs as so

    m = result.map
    in_world = m.in_world & m.placed
    view = SimpleNamespace(
        map=m,
        placed=m.placed,
        in_world=in_world,
        records=[SimpleNamespace(keyframe=k, tracking=str(s)) for k, s in enumerate(m.tracking)],
    )
    georef = None
    if m.georef is not None:
        from geoseg.synth.georef import Georeference

        georef = Georeference(*(float(v) for v in m.georef))
    so.write_trajectory_csv(out / "trajectory.csv", view, m.frame, georef)
    poses = frame_poses(view, m.frame_timestamps)
    so.write_frame_poses(out, poses)
    so.write_map_points(out / "map_points.ply", m)
    summary["frames_with_pose"] = {
        s: int(np.sum(poses.source == s))
        for s in ("keyframe", "interpolated", "extrapolated", "none")
    }
    so.write_summary(out / "summary.json", summary)
