"""Start-up of the image SLAM without ground truth: two views, metric scale, georeferencing.

:class:`TwoViewStart` is the :class:`slam_bridge.slam.loop.StartUp` of a camera that knows only
its images, an optional wheel odometry, an optional GPS and an optional DEM:

1. **Two views.** The first keyframe ``a`` is the reference; each next keyframe ``b`` is tried
   in turn (the essential matrix of their common tracks and ``cv2.recoverPose``,
   :func:`slam_bridge.geometry.multiview.two_view_init`) until at least ``min_matches`` tracks
   are inliers and ``min_points`` of them triangulate with enough parallax. Rejected tracks lose
   those observations; keyframes between ``a`` and ``b`` take interpolated poses. After
   ``max_tries`` failures (or at once when the reference has too few tracks left) the newest
   keyframe becomes the reference; the keyframes given up keep no pose at the start of a run,
   and the motion model's prediction after a lost tracking.
2. **Metric scale**: the distance the wheel odometry drove between ``a`` and ``b``; without
   odometry the baseline is 1 and the GPS displacement over tens of metres gives the scale.
3. **Georeferencing** (:meth:`TwoViewStart.georeference`, after each keyframe until it holds):
   once the segment has GPS fixes at ``min_fixes`` keyframes spread over ``min_distance_m``,
   :func:`fit_similarity` maps the optical centres at the fixes' times onto the fixes (z from
   the DEM plus the camera height, the antenna offset ``antenna_c`` accounted for) and the
   cameras' up axis onto the world's ``+z`` (pinning the roll about a straight start, which
   positions alone leave free); with odometry the scale stays the odometry's. The whole map
   moves into the world frame, where the fusion's constraint providers keep it.

After a lost tracking (:meth:`TwoViewStart.restart`) a new segment starts at the lost keyframe,
placed where the previous segment's motion predicts it (*re-anchored*: no jump; the GPS fusion
then pulls it onto the fixes), with the scale of the odometry or of the previous segment's
speed, and is initialised by two views again.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from geoseg.errors import check_finite, check_positive, check_shape
from slam_bridge.errors import SlamError
from slam_bridge.frontend.base import ObservationSource
from slam_bridge.geometry.alignment import rotation_and_scale
from slam_bridge.geometry.lie import so3_exp, so3_log
from slam_bridge.geometry.multiview import two_view_init
from slam_bridge.slam.fusion import GpsConstraints
from slam_bridge.slam.loop import StartResult
from slam_bridge.slam.map import Map
from slam_bridge.slam.mapping import MappingConfig, triangulate_new

logger = logging.getLogger(__name__)

__all__ = [
    "VehicleRig",
    "InitConfig",
    "OdometryDistance",
    "TwoViewStart",
    "fit_similarity",
    "fit_level_similarity",
]


@dataclass
class VehicleRig:
    """Where the camera sits on the vehicle.

    Attributes:
        camera_height_m: height of the optical centre above the road.
        antenna_c: ``(3,)`` the GPS antenna (the point the fixes measure) in the camera frame
            (OpenCV: x right, y down, z forward), metres. A car camera 1.5 m above a road-level
            reference point 1 m behind it: ``(0, 1.5, -1)``.
    """

    camera_height_m: float = 1.5
    antenna_c: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        check_positive("camera_height_m", self.camera_height_m)
        a = np.asarray(self.antenna_c, dtype=np.float64)
        check_shape("antenna_c", a, (3,))
        check_finite("antenna_c", a)


@dataclass
class InitConfig:
    """Start-up settings (module docstring).

    Attributes:
        min_matches: essential-matrix inliers a two-view start needs.
        min_points: points it must triangulate.
        max_tries: second views tried against one reference keyframe.
        threshold_px: RANSAC threshold of the essential matrix.
        min_fixes: keyframes with a GPS fix needed to georeference.
        min_distance_m: spread of those fixes (largest distance from the first), metres.
        up_weight: weight of the up-axis pair against the positions in the similarity fit:
            small, so that it only pins what the positions leave free (the roll about a straight
            start); the cameras' -y axes lean with the road's slope.
        measured_up_weight: the same weight when at least ``min_fixes`` of the segment's
            keyframes have a measured vertical (``Map.down_c``): their mean up replaces the
            cameras' axes and, being a measurement, holds the tilt that a DEM with a sloping
            error would otherwise give the fit.
        refit_distance_m: the similarity is fitted again at every keyframe, to all the
            segment's fixes, until its fixes spread over this distance: the map keeps the
            orientation it is given (the fusion moves the newest camera only, within the
            barrier's slack), and a fit's heading error falls with the distance it spans (GPS
            noise / distance).
        warn_residual_m: a fit whose horizontal residual exceeds this (rms, metres) is
            logged as a warning: the map's shape does not follow the GPS track (a poor
            two-view start, a bent map), several times a consumer GPS's noise.
        recover_keyframes: once the fits have stopped (``refit_distance_m``), this many
            successive keyframes whose fix is more than ``warn_residual_m`` from the camera
            make the segment be georeferenced again, to all its fixes (a recovery, reported in
            :attr:`TwoViewStart.recoveries`); 0: never.
        scale_tolerance: with odometry the fit keeps the odometry's scale, unless the fixes
            call for a scale further than this from 1 over at least ``4 min_distance_m`` (a
            wheel calibration off, a map whose scale drifted): the fit then takes the GPS's
            scale, and says so.
    """

    min_matches: int = 40
    min_points: int = 25
    max_tries: int = 6
    threshold_px: float = 1.0
    min_fixes: int = 8
    min_distance_m: float = 25.0
    up_weight: float = 0.05
    measured_up_weight: float = 5.0
    refit_distance_m: float = 200.0
    warn_residual_m: float = 3.0
    recover_keyframes: int = 5
    scale_tolerance: float = 0.05

    def __post_init__(self) -> None:
        if self.min_matches < 8 or self.min_points < 8:
            raise SlamError("min_matches, min_points: expected >= 8")
        if self.max_tries < 1:
            raise SlamError(f"max_tries: expected >= 1, got {self.max_tries}")
        if self.min_fixes < 3:
            raise SlamError(f"min_fixes: expected >= 3, got {self.min_fixes}")
        check_positive("threshold_px", self.threshold_px)
        check_positive("min_distance_m", self.min_distance_m)
        check_positive("up_weight", self.up_weight, strict=False)
        check_positive("measured_up_weight", self.measured_up_weight, strict=False)
        check_positive("warn_residual_m", self.warn_residual_m)


class OdometryDistance:
    """Distance driven (and heading turned) between two times, integrated from wheel odometry.

    Args:
        timestamps: ``(N,)`` seconds, increasing.
        speed_mps: ``(N,)`` speeds (trapezoidal integration; constant beyond the ends).
        yaw_rate_radps: ``(N,)`` heading rates, counter-clockwise seen from above, or None
            (the log gives speeds only).
    """

    def __init__(
        self,
        timestamps: np.ndarray,
        speed_mps: np.ndarray,
        yaw_rate_radps: np.ndarray | None = None,
    ) -> None:
        t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        v = np.asarray(speed_mps, dtype=np.float64).reshape(-1)
        check_shape("speed_mps", v, (t.size,))
        check_finite("timestamps", t)
        check_finite("speed_mps", v)
        if t.size < 2 or np.any(np.diff(t) <= 0):
            raise SlamError("odometry: expected at least two samples with increasing times")
        self.t = t
        self.v = v
        self.s = self._integral(v)
        self.yaw_rate = None
        if yaw_rate_radps is not None:
            self.yaw_rate = np.asarray(yaw_rate_radps, dtype=np.float64).reshape(-1)
            check_shape("yaw_rate_radps", self.yaw_rate, (t.size,))
            check_finite("yaw_rate_radps", self.yaw_rate)
            self.psi = self._integral(self.yaw_rate)

    def _integral(self, rate: np.ndarray) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum(np.diff(self.t) * 0.5 * (rate[1:] + rate[:-1]))])

    def _at(self, time_s: float, rate: np.ndarray, total: np.ndarray) -> float:
        if time_s <= self.t[0]:
            return float(rate[0] * (time_s - self.t[0]))
        if time_s >= self.t[-1]:
            return float(total[-1] + rate[-1] * (time_s - self.t[-1]))
        return float(np.interp(time_s, self.t, total))

    def __call__(self, t0: float, t1: float) -> float:
        """Metres driven from ``t0`` to ``t1``."""
        return self._at(t1, self.v, self.s) - self._at(t0, self.v, self.s)

    def yaw_change(self, t0: float, t1: float) -> float | None:
        """Heading turned from ``t0`` to ``t1`` (radians, counter-clockwise), or None without
        yaw rates."""
        if self.yaw_rate is None:
            return None
        return self._at(t1, self.yaw_rate, self.psi) - self._at(t0, self.yaw_rate, self.psi)


def fit_level_similarity(
    src: np.ndarray,
    dst: np.ndarray,
    *,
    up_src: np.ndarray,
    fix_scale: bool = False,
    weights: np.ndarray | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``dst ~ s R src + T`` whose tilt maps ``up_src`` onto ``+z`` exactly, the rest
    (heading, horizontal position, scale) fitted to the horizontal coordinates only; ``T_z``
    puts the mean altitude at the mean of ``dst``'s.

    Args:
        src: ``(N, 3)`` points in the source frame.
        dst: ``(N, 3)`` targets (their ``z`` only sets the mean altitude).
        up_src: ``(3,)`` the source frame's up direction.
        fix_scale: keep ``s = 1``.
        weights: ``(N,)`` positive weight of each pair (None: all equal).

    Returns:
        ``(s, R (3, 3), T (3,))``.

    Raises:
        SlamError: fewer than 2 points, coincident points, a zero up direction.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    check_shape("src", src, (None, 3))
    check_shape("dst", dst, (src.shape[0], 3))
    if src.shape[0] < 2:
        raise SlamError("fit_level_similarity: needs at least 2 points")
    u = np.asarray(up_src, dtype=np.float64)
    if not np.linalg.norm(u) > 0:
        raise SlamError("fit_level_similarity: zero up direction")
    u = u / np.linalg.norm(u)
    axis = np.cross(u, [0.0, 0.0, 1.0])
    angle = np.arctan2(np.linalg.norm(axis), u[2])
    R_level = so3_exp(axis / max(np.linalg.norm(axis), 1e-12) * angle)
    w = _pair_weights(weights, src.shape[0], "fit_level_similarity")
    level = src @ R_level.T
    _, a = _centred(level[:, :2], w)
    _, b = _centred(dst[:, :2], w)
    s, R2 = rotation_and_scale(a, b, b.T @ a, fix_scale=fix_scale, name="fit_level_similarity")
    R_yaw = np.eye(3)
    R_yaw[:2, :2] = R2
    R = R_yaw @ R_level
    moved = s * src @ R.T

    def mean(x: np.ndarray) -> np.ndarray:
        return x.mean(axis=0) if w is None else w @ x

    T = np.append(mean(dst[:, :2]) - mean(moved[:, :2]), 0.0)
    T[2] = mean(dst[:, 2]) - mean(moved[:, 2])
    return s, R, T


def _pair_weights(weights: np.ndarray | None, n: int, name: str) -> np.ndarray | None:
    """``(n,)`` weights summing to 1, or None when they are all equal (the unweighted fit,
    computed as such: a GPS's fits stay the same to the last bit)."""
    if weights is None:
        return None
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.size != n or not np.all(np.isfinite(w)) or not np.all(w > 0):
        raise SlamError(f"{name}: expected {n} positive finite weights, got {w.size}")
    return None if np.all(w == w[0]) else w / w.sum()


def _centred(x: np.ndarray, w: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(mean (D,), rows centred on it and scaled by sqrt(w) (N, D))``: weighted least squares
    as unweighted least squares on the scaled rows (plain means and rows when ``w`` is None)."""
    if w is None:
        mu = x.mean(axis=0)
        return mu, x - mu
    mu = w @ x
    return mu, np.sqrt(w)[:, None] * (x - mu)


def fit_similarity(
    src: np.ndarray,
    dst: np.ndarray,
    *,
    up_src: np.ndarray | None = None,
    up_weight: float = 1.0,
    fix_scale: bool = False,
    weights: np.ndarray | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s R src + T`` (Umeyama), optionally with a direction.

    Args:
        src: ``(N, 3)`` points in the source frame.
        dst: ``(N, 3)`` the same points in the target frame.
        up_src: ``(3,)`` a direction in the source frame that must map onto the target's
            ``+z`` (weighted into the rotation's cross-covariance).
        up_weight: its weight, relative to the spread of the points.
        fix_scale: keep ``s = 1``.
        weights: ``(N,)`` positive weight of each pair (None: all equal).

    Returns:
        ``(s, R (3, 3), T (3,))``.

    Raises:
        SlamError: fewer than 2 points, or a degenerate configuration.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    check_shape("src", src, (None, 3))
    check_shape("dst", dst, (src.shape[0], 3))
    if src.shape[0] < 2:
        raise SlamError("fit_similarity: needs at least 2 points")
    w = _pair_weights(weights, src.shape[0], "fit_similarity")
    (mu_s, a), (mu_d, b) = _centred(src, w), _centred(dst, w)
    H = b.T @ a  # sum_i w_i b_i a_i^T
    if up_src is not None:
        u = np.asarray(up_src, dtype=np.float64)
        u = u / np.linalg.norm(u)
        spread = float(np.sum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)))
        H = H + up_weight * max(spread, 1e-12) * np.outer([0.0, 0.0, 1.0], u)
    s, R = rotation_and_scale(a, b, H, fix_scale=fix_scale, name="fit_similarity")
    T = mu_d - s * R @ mu_s
    return s, R, T


class TwoViewStart:
    """Start-up from images (module docstring).

    Args:
        config: start-up settings.
        rig: camera height and GPS antenna offset.
        mapping: the loop's mapping settings (triangulation parallax).
        outlier_gate_px: the loop's triangulation gate.
        gps: the GPS fixes (None: the map stays in the first camera's frame).
        odometry: distance driven between two times (None: scale from the GPS).
        dem: terrain model with ``altitude_at(xy (N, 2)) -> (N,)`` (None: z from the camera
            height alone).
    """

    def __init__(
        self,
        config: InitConfig | None = None,
        rig: VehicleRig | None = None,
        *,
        mapping: MappingConfig | None = None,
        outlier_gate_px: float = 20.0,
        gps: GpsConstraints | None = None,
        odometry: OdometryDistance | None = None,
        dem=None,
    ) -> None:
        self.config = config or InitConfig()
        self.rig = rig or VehicleRig()
        self.mapping = mapping or MappingConfig()
        self.outlier_gate_px = float(outlier_gate_px)
        self.gps, self.odometry, self.dem = gps, odometry, dem
        self.georeferenced = False
        self._motion = None  # (keyframe, rad/s, m/s) of the segment before a restart
        self._spread = 0.0  # spread of the fixes of the last georeferencing, metres
        self._warned = False  # the segment's fit was reported as not following the GPS
        self._misfits = 0  # successive keyframes far from their fix after the fits stopped
        #: ``(keyframe, rms before, rms after)`` of each re-georeferencing
        self.recoveries: list[tuple[int, float, float]] = []

    # ------------------------------------------------------------------------- StartUp
    def start(self, slam_map: Map, source: ObservationSource) -> StartResult | None:
        obs = source.next_keyframe(slam_map)
        if obs is None:
            return None
        a = slam_map.add_keyframe(obs.timestamp, obs.point_ids, obs.uv)
        slam_map.set_pose(a, np.eye(3), np.zeros(3))
        return self._two_views(slam_map, source, a, speed=None)

    def restart(self, slam_map: Map, source: ObservationSource, k: int) -> StartResult | None:
        m = slam_map
        self._motion = None
        self._spread = 0.0  # the new segment is fitted to its own fixes
        self._warned = False
        self._misfits = 0
        if k >= 2 and m.segment[k - 1] == m.segment[k - 2]:  # the last motion, per second
            dt = m.timestamps[k - 1] - m.timestamps[k - 2]
            omega = so3_log(m.R_wc[k - 1] @ m.R_wc[k - 2].T) / dt
            velocity = (m.t_wc[k - 1] - m.t_wc[k - 2]) / dt
            self._motion = (k - 1, omega, velocity)
            m.set_pose(k, *self._predict(m, k))
        elif k >= 1:
            m.set_pose(k, m.R_wc[k - 1], m.t_wc[k - 1])
        logger.info("keyframe %d: new segment re-anchored at the motion model's prediction", k)
        speed = None if self._motion is None else float(np.linalg.norm(self._motion[2]))
        return self._two_views(m, source, k, speed=speed)

    def _predict(self, m: Map, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe ``k``'s pose by the last segment's motion (constant velocity)."""
        j, omega, velocity = self._motion
        dt = m.timestamps[k] - m.timestamps[j]
        return so3_exp(dt * omega) @ m.R_wc[j], m.t_wc[j] + dt * velocity

    def georeference(self, slam_map: Map, k: int) -> bool:
        if self.gps is None:
            return False
        m, cfg = slam_map, self.config
        seg = np.flatnonzero(m.segment[: k + 1] == m.segment[k])
        recovering = False
        if self.georeferenced and self._spread >= cfg.refit_distance_m:
            if not self._misfit(m, k):
                return False
            recovering = True
        fixes = [self.gps.corrected_fix_at(float(m.timestamps[j])) for j in seg]
        have = np.array([f is not None for f in fixes])
        if have.sum() < cfg.min_fixes:
            return False
        kf = seg[have]
        xy = np.array([f for f in fixes if f is not None])
        spread = float(np.max(np.linalg.norm(xy - xy[0], axis=1)))
        if spread < cfg.min_distance_m:
            return False
        up_local, up_weight = self._up(m, seg, kf)
        antenna = np.asarray(self.rig.antenna_c, dtype=np.float64)
        fix_scale = self.odometry is not None
        s, R, T = 1.0, np.eye(3), np.zeros(3)
        # the fit pairs each fix with the map at the fix's own time: a fix interpolated to a
        # keyframe's time cuts the corners of a turn (0.8 m inside a 15 m radius at 10 m/s and
        # 1 Hz), the map's keyframes a tenth of a second apart do not
        src, src_R, fit_xy, fit_w = self._pairs_at_fix_times(m, seg)
        if fit_xy.shape[0] < 3:
            src, src_R, fit_xy, fit_w = m.t_wc[kf], m.R_wc[kf], xy, None
        fit_z = np.full(fit_xy.shape[0], self.rig.camera_height_m)
        if self.dem is not None:
            fit_z = fit_z + np.asarray(self.dem.altitude_at(fit_xy), dtype=np.float64)

        def fit(target: np.ndarray, fixed: bool):
            if self.dem is None:
                # nothing measures the altitudes: a level road (z = camera height) would tilt
                # a map that climbs by its slope, so the tilt comes from the up direction alone
                return fit_level_similarity(
                    src, target, up_src=up_local, fix_scale=fixed, weights=fit_w
                )
            return fit_similarity(
                src, target, up_src=up_local, up_weight=up_weight, fix_scale=fixed,
                weights=fit_w,
            )  # fmt: skip

        for _ in range(2):  # the antenna offset depends on the rotation being fitted
            offset = np.einsum("ij,kjl,l->ki", R, src_R, antenna)[:, :2]
            target = np.column_stack([fit_xy - offset, fit_z])
            s, R, T = fit(target, fix_scale)
        # does the GPS agree on the scale? Over 100 m at least: over 50 m a GPS bias changing
        # by a metre or two on the way (a render's default GPS) called for a 6 % scale
        if fix_scale and spread >= 4 * cfg.min_distance_m:
            s_free, R_free, T_free = fit(target, False)
            if abs(s_free - 1.0) > cfg.scale_tolerance:
                logger.warning(
                    "keyframe %d: the GPS fixes call for a scale of %.3f against the odometry's "
                    "(over %.0f m): the map takes the GPS's",
                    k, s_free, spread,
                )  # fmt: skip
                s, R, T = s_free, R_free, T_free
        before = self._rms(m, kf, xy) if recovering else 0.0
        self._transform(m, seg, s, R, T)
        resid = np.linalg.norm((s * src @ R.T + T)[:, :2] + offset - fit_xy, axis=1)
        rms = float(np.sqrt(np.mean(resid**2)))
        if recovering:
            self._misfits = 0
            self.recoveries.append((int(k), before, rms))
            logger.warning(
                "keyframe %d: %d successive keyframes more than %.1f m from their GPS fix: the "
                "segment was georeferenced again (%.1f -> %.1f m rms over %d fixes)",
                k, cfg.recover_keyframes, cfg.warn_residual_m, before, rms, kf.size,
            )  # fmt: skip
        logger.log(
            logging.DEBUG if self.georeferenced else logging.INFO,
            "keyframe %d: georeferenced on %d fixes over %.0f m: scale %.3f, horizontal residual "
            "%.2f m rms",
            k, kf.size, spread, s, rms,
        )  # fmt: skip
        if rms > cfg.warn_residual_m and not self._warned:
            self._warned = True
            logger.warning(
                "keyframe %d: the map does not fit the GPS track (%.1f m rms over %d fixes, "
                "more than warn_residual_m = %.1f m): its start or its scale may be wrong, and "
                "the trajectory with it",
                k, rms, kf.size, cfg.warn_residual_m,
            )  # fmt: skip
        self.georeferenced = True
        self._spread = spread
        return True

    # ------------------------------------------------------------------------- internals
    def _misfit(self, m: Map, k: int) -> bool:
        """Keyframe ``k`` is the ``recover_keyframes``-th in a row far from its fix."""
        cfg = self.config
        fix = self.gps.corrected_fix_at(float(m.timestamps[k]))
        if cfg.recover_keyframes <= 0 or fix is None:
            return False
        far = self._rms(m, np.array([k]), fix[None]) > cfg.warn_residual_m
        self._misfits = self._misfits + 1 if far else 0
        return self._misfits >= cfg.recover_keyframes

    def _rms(self, m: Map, kf: np.ndarray, xy: np.ndarray) -> float:
        """Horizontal rms distance of the keyframes' antennas from the fixes ``xy``."""
        antenna = np.einsum("kij,j->ki", m.R_wc[kf], np.asarray(self.rig.antenna_c, float))
        d = m.t_wc[kf, :2] + antenna[:, :2] - xy
        return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))

    def _pairs_at_fix_times(
        self, m: Map, seg: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The valid fixes within the segment's time span and the map at their times.

        Returns:
            ``(positions (M, 3), rotations (M, 3, 3), fixes (M, 2), weights (M,))``: the
            optical centre interpolated between the two keyframes around each fix, the nearer
            keyframe's rotation (for the antenna offset), each fix's weight (the provider's
            ``fix_weights``: a fix to centimetres counts more than one metres off); a fix
            between keyframes further apart than the GPS's ``interpolate_gap_s`` (or, without
            one, not within ``tolerance_s`` of a keyframe) is left out.
        """
        gps, t_kf = self.gps, m.timestamps[seg]
        valid = np.all(np.isfinite(gps.xy), axis=1)
        inside = valid & (gps.timestamps >= t_kf[0]) & (gps.timestamps <= t_kf[-1])
        t_fix = gps.timestamps[inside]
        if seg.size < 2 or t_fix.size == 0:
            return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 2)), np.zeros(0)
        hi = np.clip(np.searchsorted(t_kf, t_fix), 1, seg.size - 1)
        lo = hi - 1
        gap = t_kf[hi] - t_kf[lo]
        w = np.clip((t_fix - t_kf[lo]) / np.maximum(gap, 1e-12), 0.0, 1.0)
        near_gap = np.minimum(t_fix - t_kf[lo], t_kf[hi] - t_fix)
        max_gap = gps.interpolate_gap_s
        keep = near_gap <= gps.tolerance_s if max_gap is None else gap <= max_gap
        lo, hi, w = seg[lo[keep]], seg[hi[keep]], w[keep][:, None]
        positions = (1 - w) * m.t_wc[lo] + w * m.t_wc[hi]
        nearer = np.where(w[:, 0] < 0.5, lo, hi)
        weights = gps.fix_weights()[inside][keep]
        return positions, m.R_wc[nearer], gps.corrected_xy()[inside][keep], weights

    def _up(self, m: Map, seg: np.ndarray, kf: np.ndarray) -> tuple[np.ndarray, float]:
        """The segment's up direction in the map frame and its weight in the fit: from the
        measured verticals when enough keyframes have one, else the cameras' -y axes."""
        down = m.down_c[seg]
        has = np.all(np.isfinite(down), axis=1)
        if has.sum() >= self.config.min_fixes:
            up = -np.einsum("kij,kj->i", m.R_wc[seg[has]], down[has])
            return up, self.config.measured_up_weight
        return -np.mean(m.R_wc[kf][:, :, 1], axis=0), self.config.up_weight

    def _two_views(
        self, m: Map, source: ObservationSource, a: int, speed: float | None
    ) -> StartResult | None:
        cfg = self.config
        tries = 0
        while True:
            obs = source.next_keyframe(m)
            if obs is None:
                return None
            b = m.add_keyframe(obs.timestamp, obs.point_ids, obs.uv)
            for j in range(a + 1, b):  # keyframes skipped by the start keep no observation
                m.obs_active[m.keyframe_observations(j)] = False
            if self._try_pair(m, a, b, speed):
                self._fill_between(m, a, b)
                return StartResult(np.array([a, b]), georeferenced=self.georeferenced)
            tries += 1
            few = m.obs_active[m.keyframe_observations(a)].sum() < cfg.min_matches
            if few or tries >= cfg.max_tries:  # the reference has too few usable tracks
                logger.warning(
                    "keyframes %d-%d: no two-view start; keyframe %d is the new reference", a, b, b
                )
                m.obs_active[m.keyframe_observations(a)] = False
                for j in range(a, b):  # dead-reckoned after a loss, else never placed
                    if self._motion is not None:
                        m.set_pose(j, *self._predict(m, j))
                    else:
                        m.set_pose(j, np.full((3, 3), np.nan), np.full(3, np.nan))
                    m.mark_online(j)
                if self._motion is not None:
                    m.set_pose(b, *self._predict(m, b))
                else:
                    m.set_pose(b, np.eye(3), np.zeros(3))
                m.start_segment(b)
                a, tries = b, 0

    def _try_pair(self, m: Map, a: int, b: int, speed: float | None) -> bool:
        cfg = self.config
        oa, ob = m.keyframe_observations(a), m.keyframe_observations(b)
        oa = oa[m.obs_active[oa]]
        ob = ob[m.obs_active[ob]]
        common, ia, ib = np.intersect1d(m.obs_point[oa], m.obs_point[ob], return_indices=True)
        if common.size < cfg.min_matches:
            logger.debug("two views %d-%d: %d common tracks", a, b, common.size)
            return False
        ia, ib = oa[ia], ob[ib]
        try:
            tv = two_view_init(
                m.K, m.obs_uv[ia], m.obs_uv[ib], threshold_px=cfg.threshold_px, seed=b
            )
        except SlamError as exc:
            logger.debug("two views %d-%d: %s", a, b, exc)
            return False
        if tv.inliers.sum() < cfg.min_matches:
            logger.debug("two views %d-%d: %d inliers", a, b, int(tv.inliers.sum()))
            return False
        baseline = self._baseline(m, a, b, speed)
        R_a, t_a = m.R_wc[a].copy(), m.t_wc[a].copy()
        active = m.obs_active.copy()
        m.obs_active[ia[~tv.inliers]] = False
        m.obs_active[ib[~tv.inliers]] = False
        m.set_pose(b, R_a @ tv.R_wc, t_a + baseline * (R_a @ tv.t_wc))
        n = triangulate_new(m, b, self.mapping, self.outlier_gate_px, int(m.starts[a]))
        if n < cfg.min_points:
            logger.debug("two views %d-%d: %d points triangulated", a, b, n)
            m.obs_active[:] = active
            m.triangulated[:] = False
            return False
        logger.info(
            "two-view start on keyframes %d-%d: %d inliers of %d tracks, %d points, baseline %.2f",
            a, b, int(tv.inliers.sum()), common.size, n, baseline,
        )  # fmt: skip
        return True

    def _baseline(self, m: Map, a: int, b: int, speed: float | None) -> float:
        """Length of the a-b baseline in map units."""
        dt = float(m.timestamps[b] - m.timestamps[a])
        if self.odometry is not None:
            d = self.odometry(float(m.timestamps[a]), float(m.timestamps[b]))
            if d > 1e-3:
                return d
        if speed is not None and speed * dt > 1e-6:
            return speed * dt
        return 1.0

    def _fill_between(self, m: Map, a: int, b: int) -> None:
        """Keyframes strictly between ``a`` and ``b`` (skipped by the start, no observation)
        take poses interpolated in time."""
        for j in range(a + 1, b):
            w = (m.timestamps[j] - m.timestamps[a]) / (m.timestamps[b] - m.timestamps[a])
            R = so3_exp(w * so3_log(m.R_wc[b] @ m.R_wc[a].T)) @ m.R_wc[a]
            m.set_pose(j, R, (1 - w) * m.t_wc[a] + w * m.t_wc[b])
            m.mark_online(j)
        m.mark_online(a)
        m.mark_online(b)

    @staticmethod
    def _transform(m: Map, keyframes: np.ndarray, s: float, R: np.ndarray, T: np.ndarray) -> None:
        """Move the keyframes (current and online poses) and the triangulated points by
        ``X -> s R X + T``."""
        for Rw, tw in ((m.R_wc, m.t_wc), (m.R_wc_online, m.t_wc_online)):
            Rw[keyframes] = R @ Rw[keyframes]
            tw[keyframes] = s * tw[keyframes] @ R.T + T
        tri = m.triangulated
        m.X_w[tri] = s * m.X_w[tri] @ R.T + T
