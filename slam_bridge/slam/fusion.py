"""Barrier fusion of the k-BA's optimum with a list of constraint providers (thesis eq. 2.3).

After the k-BA, ``X* = argmin zeta`` (:mod:`slam_bridge.slam.windows`), the newest keyframe's
window is fused with the constraints ``C_i`` the providers give for it:
``argmin gamma / (t - zeta(X)) + sum C_i(X)``, ``t = t_ratio zeta(X*)``, from ``X*``
(:func:`slam_bridge.ba.solvers.barrier.solve_barrier`; the barrier's rank-one term is handled by
Sherman-Morrison, so a provider must add no dense term, appendix B). A provider is anything
with a ``name`` and ``factors(slam_map, problem, k) -> list[Factor]``: the GPS fix of the
keyframe (:class:`GpsConstraints`, chapter 3) today; terrain elevation, odometry and building
constraints plug in the same way (:class:`DemConstraints`: terrain elevation;
:class:`OdometryConstraints`: the distance driven between the newest keyframes;
:class:`VerticalConstraints`: the vertical seen in the keyframe's image). A keyframe for which no
provider has a constraint keeps
``X*`` (a GPS dropout, for instance).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from geoseg.errors import check_finite, check_positive, check_shape
from slam_bridge.ba.factor import Factor
from slam_bridge.ba.robust import HuberKernel
from slam_bridge.ba.solvers.barrier import BarrierConfig, solve_barrier
from slam_bridge.errors import SlamError
from slam_bridge.factors.dem import DEMFactor
from slam_bridge.factors.gps import GPSFactor
from slam_bridge.factors.vertical import VerticalFactor
from slam_bridge.frontend.vertical_lines import (
    VerticalEstimate,
    VerticalLinesConfig,
    detect_segments,
    vertical_direction,
)
from slam_bridge.slam.map import Map

logger = logging.getLogger(__name__)

__all__ = [
    "ConstraintProvider",
    "GpsBiasSource",
    "GpsConstraints",
    "DemConstraints",
    "OdometryConstraints",
    "VerticalConstraints",
    "FusionConfig",
    "FusionOutcome",
    "fuse",
]


class ConstraintProvider(Protocol):
    """A source of constraint families for the fusion of keyframe ``k`` (module docstring).

    Attributes:
        name: label of its families in the records.
        world_frame: its constraints hold in the world frame (GPS, DEM): the loop applies them
            only once the map is georeferenced.
    """

    name: str
    world_frame: bool

    def factors(self, slam_map: Map, problem, k: int) -> list[Factor]:
        """The constraint families on ``problem``'s state (a
        :class:`slam_bridge.slam.hybrid_problem.HybridProblem` at ``X*``) for keyframe ``k``."""
        ...


class GpsBiasSource(Protocol):
    """An estimate of a GPS receiver's bias at keyframe ``k`` (e.g.
    :class:`slam_bridge.bridge.gps_bias.BuildingGpsBias`, from the building model).

    Attributes:
        inflate: the fix's weight is lowered by the estimate's uncertainty.
    """

    inflate: bool

    def estimate(self, slam_map: Map, problem, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(b (2,), cov (2, 2))``: the bias of keyframe ``k``'s fix (``fix = true + b``),
        metres, and its covariance."""
        ...

    def at(self, timestamps):
        """The best estimate so far of the bias of fixes at ``timestamps`` (a float: ``(2,)``;
        ``(N,)``: ``(N, 2)``); 0 where nothing is known."""
        ...


class GpsConstraints:
    """GPS fixes on the horizontal position of the newest camera (eq. 3.1, eq. B.7).

    Keyframe ``k`` is fused with the fix whose timestamp is within ``tolerance_s`` of its own,
    else (with ``interpolate_gap_s``) with the linear interpolation of the two valid fixes around
    it when they are at most that far apart (a 1 Hz receiver and keyframes every few tenths of a
    second); otherwise it is a dropout: no GPS constraint for that keyframe. A fix
    measures the antenna, ``antenna_c`` from the optical centre in the camera frame: the camera
    is constrained to ``fix - (R_wc antenna_c)_xy`` with ``R_wc`` the camera's rotation at
    ``X*`` (held during the fusion, which turns the camera by milliradians: millimetres for a
    lever arm of a metre).

    Args:
        timestamps: ``(F,)`` fix times, seconds, increasing.
        xy: ``(F, 2)`` fixes in the world frame, metres (NaN rows: dropouts).
        weight: weight of the GPS term.
        tolerance_s: how far from a keyframe's time a fix may be.
        interpolate_gap_s: the longest interval between two fixes interpolated (None: none).
        antenna_c: ``(3,)`` the antenna in the camera frame, metres (None: at the camera).
        bias: an estimate of the receiver's slowly varying bias (:class:`GpsBiasSource`;
            None: fixes taken as they are): each fix is corrected by it, and its weight lowered
            by the estimate's uncertainty when ``bias.inflate`` holds.
    """

    name = "gps"
    world_frame = True

    def __init__(
        self,
        timestamps: np.ndarray,
        xy: np.ndarray,
        *,
        weight: float = 1.0,
        tolerance_s: float = 1e-3,
        interpolate_gap_s: float | None = None,
        antenna_c: np.ndarray | None = None,
        bias: GpsBiasSource | None = None,
    ) -> None:
        self.bias = bias
        self.timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        self.xy = np.asarray(xy, dtype=np.float64)
        check_shape("xy", self.xy, (self.timestamps.size, 2))
        check_finite("timestamps", self.timestamps)
        if np.any(np.isinf(self.xy)):
            raise SlamError("xy: GPS fixes must be finite or NaN (dropout)")
        if np.any(np.diff(self.timestamps) <= 0):
            raise SlamError("timestamps: GPS fix times must increase")
        check_positive("weight", weight)
        check_positive("tolerance_s", tolerance_s)
        self.weight = float(weight)
        self.tolerance_s = float(tolerance_s)
        if interpolate_gap_s is not None:
            check_positive("interpolate_gap_s", interpolate_gap_s)
        self.interpolate_gap_s = interpolate_gap_s
        self.antenna_c = None
        if antenna_c is not None:
            self.antenna_c = np.asarray(antenna_c, dtype=np.float64)
            check_shape("antenna_c", self.antenna_c, (3,))
            check_finite("antenna_c", self.antenna_c)

    def fix_at(self, timestamp: float) -> np.ndarray | None:
        """The ``(2,)`` fix for ``timestamp``, or None (dropout, none near)."""
        rows = self.rows_at(timestamp)
        if rows is None:
            return None
        if len(rows) == 1:
            return self.xy[rows[0]].copy()
        a, b = rows
        w = (timestamp - self.timestamps[a]) / (self.timestamps[b] - self.timestamps[a])
        return (1 - w) * self.xy[a] + w * self.xy[b]

    def rows_at(self, timestamp: float) -> tuple[int, ...] | None:
        """The fixes :meth:`fix_at` uses for ``timestamp``: ``(i,)`` within ``tolerance_s``,
        ``(a, b)`` interpolated, or None."""
        t, n = self.timestamps, self.timestamps.size
        if n == 0:
            return None
        hi = int(np.searchsorted(t, timestamp))  # t[hi - 1] < timestamp <= t[hi]
        near = [i for i in (hi - 1, hi) if 0 <= i < n]
        i = min(near, key=lambda j: abs(t[j] - timestamp))
        if abs(t[i] - timestamp) <= self.tolerance_s:
            return (i,) if np.all(np.isfinite(self.xy[i])) else None
        if self.interpolate_gap_s is None or not 0 < hi < n:
            return None
        a, b = hi - 1, hi
        if t[b] - t[a] > self.interpolate_gap_s or not np.all(np.isfinite(self.xy[[a, b]])):
            return None
        return (a, b)

    def fix_weights(self) -> np.ndarray:
        """``(F,)`` each fix's weight: all :attr:`weight` (a provider whose fixes differ in
        accuracy gives its own)."""
        return np.full(self.timestamps.size, self.weight)

    def weight_at(self, timestamp: float) -> float:
        """The weight of the fix :meth:`fix_at` gives for ``timestamp`` (the lower of the two
        it interpolates; 0 when it gives none)."""
        rows = self.rows_at(timestamp)
        return 0.0 if rows is None else float(self.fix_weights()[list(rows)].min())

    def corrected_fix_at(self, timestamp: float) -> np.ndarray | None:
        """:meth:`fix_at` less the bias estimated for ``timestamp`` (``bias.at``; the fix
        itself without a bias source): what the start-up georeferences the map on."""
        fix = self.fix_at(timestamp)
        if fix is None or self.bias is None:
            return fix
        return fix - self.bias.at(timestamp)

    def corrected_xy(self) -> np.ndarray:
        """``(F, 2)`` every fix less the bias estimated for its time (:attr:`xy` without a
        bias source)."""
        if self.bias is None:
            return self.xy
        return self.xy - self.bias.at(self.timestamps)

    def camera_fix_at(self, timestamp: float, R_wc: np.ndarray) -> np.ndarray | None:
        """The ``(2,)`` fix of the optical centre of a camera of rotation ``R_wc`` ``(3, 3)``
        (the antenna's lever arm removed), or None."""
        fix = self.fix_at(timestamp)
        if fix is None or self.antenna_c is None:
            return fix
        return fix - (R_wc @ self.antenna_c)[:2]

    def factors(self, slam_map: Map, problem, k: int) -> list[Factor]:
        """One :class:`GPSFactor` on the newest free camera, or none (dropout)."""
        st = problem.state
        fix = self.camera_fix_at(float(slam_map.timestamps[k]), st.R_wc[st.free_cameras[-1]])
        if fix is None:
            return []
        weight = self.weight
        if self.bias is not None:
            b, cov = self.bias.estimate(slam_map, problem, k)
            fix = fix - b
            if self.bias.inflate:  # an uncertain bias is noise on the fix: sigma^2 + var(b)
                weight = 1.0 / (1.0 / weight + 0.5 * float(np.trace(cov)))
        return [GPSFactor.most_recent(problem.state, fix, weight=weight)]


class DemConstraints:
    """Terrain elevation of the newest camera: its altitude is the road's under it plus the
    camera height (appendix B.3.2, :class:`slam_bridge.factors.dem.DEMFactor`).

    A camera farther than ``max_distance_m`` from every DEM segment (off the modelled roads) is
    not constrained (logged): the nearest segment's altitude would be a guess.

    Args:
        terrain: the road DEM (:class:`slam_bridge.factors.dem.DemSegments`).
        camera_height_m: camera height above the road.
        weight: weight of the elevation term (1 / sigma^2, metres).
        max_distance_m: farthest horizontal distance to a segment.
    """

    name = "dem"
    world_frame = True

    def __init__(
        self, terrain, camera_height_m: float, *, weight: float = 1.0, max_distance_m: float = 15.0
    ) -> None:
        check_positive("camera_height_m", camera_height_m)
        check_positive("weight", weight)
        check_positive("max_distance_m", max_distance_m)
        self.terrain = terrain
        self.camera_height_m = float(camera_height_m)
        self.weight = float(weight)
        self.max_distance_m = float(max_distance_m)

    def factors(self, slam_map: Map, problem, k: int) -> list[Factor]:
        """One :class:`DEMFactor` on the newest free camera, or none off the DEM's roads."""
        st = problem.state
        cam = st.free_cameras[-1]
        distance = float(self.terrain.distance_at(st.t_wc[cam, :2])[0])
        if distance > self.max_distance_m:
            logger.debug("keyframe %d: %.0f m from the DEM's roads, no elevation term", k, distance)
            return []
        return [
            DEMFactor(np.array([cam]), self.terrain, self.camera_height_m, np.array([self.weight]))
        ]


class OdometryConstraints:
    """Wheel odometry between successive keyframes (appendix B.3.2): in the k-BA and the fusion.

    For each pair of successive keyframes: the length of their baseline,
    ``r = (||T_j - T_i|| - d) / sigma`` with ``d`` the distance driven between their times and
    ``sigma = max(sigma_rel d, sigma_min_m)``
    (:class:`slam_bridge.factors.baseline_length.BaselineLengthFactor`), and, when the log has
    yaw rates, the heading turned, ``sigma = sigma_yaw_rad + sigma_yaw_rel |dpsi|``
    (:class:`slam_bridge.factors.yaw_change.YawChangeFactor`): together the displacement
    between keyframes from speed and heading, the parts of it that do not depend on how the
    camera is mounted.

    Two places. In the k-BA's cost ``zeta`` (:meth:`window_factors`, every pair of the window)
    with a dead zone of ``band`` sigmas (:class:`slam_bridge.ba.robust.DeadZoneKernel`):
    a wheel odometry's scale error of a percent or two costs nothing there and the vision keeps
    its own scale, but a monocular scale drift of 20 % after a turn on few points (a 10-sigma
    miss) costs far more than the vision rows gain, and cannot survive. In the barrier fusion
    (:meth:`factors`, the newest pair) without a dead zone, as a gentle pull within the
    barrier's slack (``t_ratio``), which alone could never undo such a drift.

    Args:
        distance: an :class:`slam_bridge.slam.initialization.OdometryDistance` (or any
            ``distance(t0, t1) -> metres``; ``yaw_change(t0, t1)`` when it has one).
        sigma_rel: relative standard deviation of the odometry's distance.
        sigma_min_m: its floor, metres.
        sigma_yaw_rad: standard deviation of a heading change, radians.
        sigma_yaw_rel: its part proportional to the turn.
        band: the k-BA rows' dead zone, in sigmas (None: no k-BA rows, the fusion only).
    """

    name = "odometry"
    world_frame = False

    def __init__(
        self,
        distance,
        *,
        sigma_rel: float = 0.02,
        sigma_min_m: float = 0.02,
        sigma_yaw_rad: float = 0.005,
        sigma_yaw_rel: float = 0.05,
        band: float | None = 2.0,
    ) -> None:
        for name, v in (
            ("sigma_rel", sigma_rel), ("sigma_min_m", sigma_min_m),
            ("sigma_yaw_rad", sigma_yaw_rad), ("sigma_yaw_rel", sigma_yaw_rel),
        ):  # fmt: skip
            check_positive(name, v)
        if band is not None:
            check_positive("band", band)
        self.distance = distance
        self.sigma_rel, self.sigma_min_m = float(sigma_rel), float(sigma_min_m)
        self.sigma_yaw_rad, self.sigma_yaw_rel = float(sigma_yaw_rad), float(sigma_yaw_rel)
        self.band = band

    def factors(self, slam_map: Map, problem, k: int) -> list[Factor]:
        """The newest pair's rows for the fusion (when both keyframes are in the window)."""
        ids = list(problem.camera_ids)
        if k - 1 not in ids or k not in ids or slam_map.segment[k - 1] != slam_map.segment[k]:
            return []
        return self._rows(slam_map, [(ids.index(k - 1), ids.index(k))], ids, kernel=None)

    def window_factors(self, slam_map: Map, problem) -> list[Factor]:
        """Rows between the successive keyframes of the window of ``problem`` that are not both
        fixed, with the dead zone (none without ``band``)."""
        if self.band is None:
            return []
        from slam_bridge.ba.robust import DeadZoneKernel

        ids = np.asarray(problem.camera_ids)
        fixed = problem.state.camera_fixed
        order = np.argsort(ids)
        pairs = [
            (int(a), int(b))
            for a, b in zip(order[:-1], order[1:])
            if ids[b] == ids[a] + 1
            and not (fixed[a] and fixed[b])
            and slam_map.segment[ids[a]] == slam_map.segment[ids[b]]
        ]
        return self._rows(slam_map, pairs, list(ids), kernel=DeadZoneKernel(self.band))

    def _rows(self, slam_map: Map, pairs, ids, kernel) -> list[Factor]:
        """Baseline-length (and heading-change) families over state camera ``pairs``."""
        from slam_bridge.factors.baseline_length import BaselineLengthFactor
        from slam_bridge.factors.yaw_change import YawChangeFactor

        yaw_of = getattr(self.distance, "yaw_change", None)
        kept, lengths, yaws = [], [], []
        for a, b in pairs:
            t0, t1 = float(slam_map.timestamps[ids[a]]), float(slam_map.timestamps[ids[b]])
            d = float(self.distance(t0, t1))
            if not d > 0:
                continue
            kept.append((a, b))
            lengths.append(d)
            yaws.append(None if yaw_of is None else yaw_of(t0, t1))
        if not kept:
            return []
        pairs_a, lengths_a = np.array(kept), np.array(lengths)
        sigma = np.maximum(self.sigma_rel * lengths_a, self.sigma_min_m)
        out: list[Factor] = [BaselineLengthFactor(pairs_a, lengths_a, sigma, kernel=kernel)]
        has = np.array([y is not None for y in yaws])
        if has.any():
            dpsi = np.array([y for y in yaws if y is not None])
            sigma_yaw = self.sigma_yaw_rad + self.sigma_yaw_rel * np.abs(dpsi)
            out.append(YawChangeFactor(pairs_a[has], dpsi, sigma_yaw, kernel=kernel))
        return out


class VerticalConstraints:
    """World down as each keyframe's vertical line segments show it
    (:mod:`slam_bridge.frontend.vertical_lines`): a constraint on the tilt of every camera of
    the window that has one (:class:`slam_bridge.factors.vertical.VerticalFactor`).

    GPS and DEM hold positions only, so they leave the roll about a straight stretch of road
    free, and a DEM whose error slopes tilts the map to follow it. The newest keyframe's
    segments are gated around the vertical the k-BA predicts for it, so the measurement refines
    the SLAM's tilt rather than replacing it; it is kept on the map (``Map.down_c``, which the
    georeferencing's refits lean on) and constrains the keyframe while it is in the window. A
    keyframe without enough vertical segments (night, open country) has no row.

    Args:
        image_at: ``timestamp -> (H, W, 3) uint8`` image of a keyframe, or None.
        K: ``(3, 3)`` intrinsics of those images.
        config: the segment thresholds.
        huber_delta: Huber threshold of the whitened residual (a fit to the wrong segments is
            an outlier).
    """

    name = "vertical"
    world_frame = True

    def __init__(
        self,
        image_at,
        K: np.ndarray,
        config: VerticalLinesConfig | None = None,
        *,
        huber_delta: float = 2.0,
    ) -> None:
        self.K = np.asarray(K, dtype=np.float64)
        check_shape("K", self.K, (3, 3))
        self.image_at = image_at
        self.config = config or VerticalLinesConfig()
        self.kernel = HuberKernel(huber_delta)
        self._measured: dict[int, VerticalEstimate] = {}  # keyframe id -> its vertical

    def factors(self, slam_map: Map, problem, k: int) -> list[Factor]:
        """Keyframe ``k``'s vertical is measured; one :class:`VerticalFactor` over the free
        cameras of the window that have one."""
        st = problem.state
        image = self.image_at(float(slam_map.timestamps[k]))
        if image is not None and k not in self._measured:
            cam = int(st.free_cameras[-1])
            predicted = st.R_wc[cam].T @ np.array([0.0, 0.0, -1.0])
            est = vertical_direction(detect_segments(image), self.K, predicted, self.config)
            if est is not None:
                self._measured[k] = est
                slam_map.down_c[k] = est.down_c
        free = st.free_cameras
        ids = np.asarray(problem.camera_ids)[free]
        has = np.array([int(i) in self._measured for i in ids], dtype=bool)
        if not has.any():
            return []
        ests = [self._measured[int(i)] for i in ids[has]]
        return [
            VerticalFactor(
                free[has],
                np.stack([e.basis for e in ests]),
                np.stack([e.covariance for e in ests]),
                kernel=self.kernel,
            )
        ]


@dataclass
class FusionConfig:
    """Barrier fusion settings (:class:`slam_bridge.ba.solvers.barrier.BarrierConfig`).

    Attributes:
        iterations: barrier iterations.
        backtracks: halvings of a step that crosses the barrier before its damping is raised
            (0 = the thesis's Levenberg-Marquardt alone).
        gamma_rel: relative barrier weight.
        t_ratio: ``t = t_ratio zeta(X*)``.
    """

    iterations: int = 10
    backtracks: int = 3
    gamma_rel: float = 0.01
    t_ratio: float = 1.05

    def barrier(self) -> BarrierConfig:
        """The solver's config."""
        return BarrierConfig(
            t_ratio=self.t_ratio,
            gamma_rel=self.gamma_rel,
            max_iterations=self.iterations,
            max_backtracks=self.backtracks,
        )

    def __post_init__(self) -> None:
        self.barrier()  # bad values: SlamError now, not at the first fusion


@dataclass
class FusionOutcome:
    """One keyframe's fusion.

    Attributes:
        state: the fused state (``X*`` when nothing was fused).
        constraints: names of the providers whose constraints were fused.
        seconds: wall time of the barrier solve.
        iterations: barrier iterations.
        seconds_per_iteration: mean time of an iteration (assembly + solves).
        zeta_star: ``zeta(X*)``.
        zeta: ``zeta`` after the fusion.
    """

    state: object
    constraints: list[str] = field(default_factory=list)
    seconds: float = 0.0
    iterations: int = 0
    seconds_per_iteration: float = 0.0
    zeta_star: float = 0.0
    zeta: float = 0.0


def fuse(
    slam_map: Map, problem, k: int, providers: list[ConstraintProvider], cfg: FusionConfig
) -> FusionOutcome:
    """Fuse ``problem`` (at ``X*``) with the providers' constraints for keyframe ``k``.

    Returns:
        A :class:`FusionOutcome`; ``X*`` itself when no provider has a constraint.
    """
    factors, names = [], []
    for p in providers:
        got = p.factors(slam_map, problem, k)
        if got:
            factors += got
            names.append(p.name)
    if not factors:
        logger.debug("keyframe %d: no constraint to fuse", k)
        return FusionOutcome(problem.state)
    t0 = time.perf_counter()
    fused = solve_barrier(problem.vision, factors, problem.state, cfg.barrier())
    return FusionOutcome(
        state=fused.state,
        constraints=names,
        seconds=time.perf_counter() - t0,
        iterations=int(fused.iterations),
        seconds_per_iteration=float(fused.seconds_per_iteration),
        zeta_star=float(fused.zeta_star),
        zeta=float(fused.zeta),
    )
