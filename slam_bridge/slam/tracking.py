"""Tracking: the pose of a new keyframe from its observations of mapped points.

The pose is the better of two candidates, each refined by OpenCV's Levenberg-Marquardt on its
inliers (reprojection error below ``pnp_threshold_px``): PnP with RANSAC
(:func:`slam_bridge.geometry.multiview.pnp`) and the constant-velocity prediction from the two
previous keyframes (which survives a RANSAC failure when the motion is smooth). With fewer than
``min_tracked`` inliers the tracking is *weak*: the pose is kept and the k-BA decides, and no
observation is gated at it; with fewer than 6 the loop first tries to *bridge* the gap from the
tracks shared with the previous keyframe (:func:`bridge_two_view`), else the tracking is *lost*
(:class:`TrackingLost`), which the loop reports and recovers from. With a good pose, the
observations erring more than ``outlier_gate_px`` are gross outliers and are deactivated.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from geoseg.errors import check_positive
from slam_bridge.errors import SlamError
from slam_bridge.geometry.camera import project
from slam_bridge.geometry.multiview import pnp
from slam_bridge.slam.map import Map

logger = logging.getLogger(__name__)

__all__ = [
    "TrackingConfig",
    "TrackingLost",
    "Tracked",
    "track_keyframe",
    "bridge_two_view",
    "reprojection_errors",
]


#: fewest PnP inliers that place a keyframe (a weak tracking below ``min_tracked``)
MIN_INLIERS = 6


class TrackingLost(SlamError):
    """Too few observations of mapped points, or too few PnP inliers, to place a keyframe."""


@dataclass
class TrackingConfig:
    """Tracking settings (module docstring).

    Attributes:
        pnp_threshold_px: PnP RANSAC and inlier threshold.
        outlier_gate_px: an observation erring more than this at the tracked pose is a gross
            outlier (deactivated). Moderate errors (a point triangulated with little parallax)
            are left to the k-BA.
        min_tracked: fewer PnP inliers make a weak tracking; fewer than 6 a lost one.
    """

    pnp_threshold_px: float = 8.0
    outlier_gate_px: float = 20.0
    min_tracked: int = 12

    def __post_init__(self) -> None:
        check_positive("pnp_threshold_px", self.pnp_threshold_px)
        check_positive("outlier_gate_px", self.outlier_gate_px)
        if self.min_tracked < 6:
            raise SlamError(f"min_tracked: expected >= 6, got {self.min_tracked}")


@dataclass
class Tracked:
    """A tracked keyframe.

    Attributes:
        R_wc: ``(3, 3)``.
        t_wc: ``(3,)``.
        inliers: PnP inliers.
        weak: fewer than ``min_tracked`` inliers.
        gated: observations deactivated as gross outliers.
    """

    R_wc: np.ndarray
    t_wc: np.ndarray
    inliers: int
    weak: bool
    gated: int


def reprojection_errors(K, R_wc, t_wc, X_w: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``(N,)`` pixel errors of ``X_w`` projected against ``uv`` (1e9 behind the camera)."""
    uv_hat, _, front = project(K, R_wc, t_wc, X_w)
    return np.where(front, np.linalg.norm(np.nan_to_num(uv_hat - uv, nan=1e9), axis=1), 1e9)


def track_keyframe(slam_map: Map, k: int, cfg: TrackingConfig) -> Tracked:
    """Pose of keyframe ``k`` (module docstring); deactivates its gross outliers in the map.

    Keyframes ``k - 1`` and ``k - 2`` must have poses (the motion model).

    Raises:
        TrackingLost: too few observations of mapped points or too few PnP inliers.
    """
    m = slam_map
    sl = m.keyframe_observations(k)
    trk = sl[m.obs_active[sl] & m.triangulated[m.obs_point[sl]]]
    if trk.size < MIN_INLIERS:
        raise TrackingLost(
            f"tracking lost at keyframe {k}: {trk.size} observations of mapped points, "
            f"fewer than {MIN_INLIERS}"
        )
    X, uv = m.X_w[m.obs_point[trk]], m.obs_uv[trk]
    R_k, t_k, n_in = _best_pose(m.K, X, uv, m.R_wc, m.t_wc, k, cfg.pnp_threshold_px)
    if n_in < MIN_INLIERS:
        raise TrackingLost(
            f"tracking lost at keyframe {k}: {n_in} PnP inliers among {trk.size} "
            f"observations of mapped points (at least {MIN_INLIERS} needed)"
        )
    weak = n_in < cfg.min_tracked
    gated = 0
    if weak:  # keep the pose, let the k-BA decide, gate nothing
        logger.warning("keyframe %d: weak tracking (%d PnP inliers)", k, n_in)
    else:
        bad = trk[reprojection_errors(m.K, R_k, t_k, X, uv) > cfg.outlier_gate_px]
        m.obs_active[bad] = False
        gated = int(bad.size)
    return Tracked(R_k, t_k, int(n_in), weak, gated)


def _best_pose(
    K: np.ndarray,
    X_w: np.ndarray,
    uv: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    k: int,
    threshold_px: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The PnP and constant-velocity candidates, each refined on its inliers; the one with
    more inliers wins.

    Returns:
        ``R_wc (3, 3)``, ``t_wc (3,)``, number of inliers.
    """
    dR = R_wc[k - 1] @ R_wc[k - 2].T
    cands = [(dR @ R_wc[k - 1], t_wc[k - 1] + dR @ (t_wc[k - 1] - t_wc[k - 2]))]
    try:
        res = pnp(K, X_w, uv, threshold_px=threshold_px, seed=k)
        cands.append((res.R_wc, res.t_wc))
    except SlamError as exc:
        logger.debug("keyframe %d: PnP RANSAC failed (%s); motion model", k, exc)
    best = None
    for R, t in cands:
        for _ in range(2):  # score, then refine on the inliers (OpenCV LM)
            inl = reprojection_errors(K, R, t, X_w, uv) < threshold_px
            if inl.sum() < 6:
                break
            rvec = cv2.Rodrigues(np.ascontiguousarray(R.T))[0].reshape(3, 1)
            tvec = np.ascontiguousarray(-(R.T @ t)).reshape(3, 1)
            rvec, tvec = cv2.solvePnPRefineLM(
                np.ascontiguousarray(X_w[inl]), np.ascontiguousarray(uv[inl]), K, None, rvec, tvec
            )
            R_cw, _ = cv2.Rodrigues(rvec)
            R, t = R_cw.T, -(R_cw.T @ tvec.reshape(3))
        n_in = int(np.sum(reprojection_errors(K, R, t, X_w, uv) < threshold_px))
        if best is None or n_in > best[2]:
            best = (R, t, n_in)
    return best


def bridge_two_view(
    slam_map: Map,
    k: int,
    *,
    distance=None,
    min_matches: int = 15,
    threshold_px: float = 1.0,
) -> Tracked | None:
    """Place keyframe ``k`` from its tracks shared with ``k - 1`` when PnP cannot.

    When the map has (almost) no point in view (a flat vehicle passing in front of the camera,
    the open ground at the edge of town), the tracks between the previous keyframe and this one
    still give their relative pose up to scale (essential matrix, MAGSAC++,
    :func:`slam_bridge.geometry.multiview.two_view_init`); the length of the baseline is the
    distance driven (``distance(t0, t1)``, wheel odometry) or, without it, the last motion's speed.
    The tracks the essential matrix rejects lose their observations. The map then goes on from
    this pose instead of starting a new segment.

    Returns:
        The pose (a weak tracking, ``inliers`` = essential-matrix inliers), or None: the
        previous keyframe is unplaced or of another segment, too few shared tracks, no
        essential matrix, no scale.
    """
    from slam_bridge.geometry.multiview import two_view_init

    m, a = slam_map, k - 1
    if a < 0 or m.segment[a] != m.segment[k] or not np.all(np.isfinite(m.t_wc[a])):
        return None
    oa, ok = m.keyframe_observations(a), m.keyframe_observations(k)
    oa, ok = oa[m.obs_active[oa]], ok[m.obs_active[ok]]
    _, ia, ik = np.intersect1d(m.obs_point[oa], m.obs_point[ok], return_indices=True)
    if ia.size < min_matches:
        return None
    ia, ik = oa[ia], ok[ik]
    try:
        tv = two_view_init(m.K, m.obs_uv[ia], m.obs_uv[ik], threshold_px=threshold_px, seed=k)
    except SlamError:
        return None
    if tv.inliers.sum() < min_matches:
        return None
    dt = float(m.timestamps[k] - m.timestamps[a])
    if distance is not None:
        length = float(distance(float(m.timestamps[a]), float(m.timestamps[k])))
    elif a >= 1 and m.segment[a - 1] == m.segment[a]:
        speed = np.linalg.norm(m.t_wc[a] - m.t_wc[a - 1]) / (m.timestamps[a] - m.timestamps[a - 1])
        length = float(speed * dt)
    else:
        return None
    if not length > 1e-3:
        return None
    outliers = np.r_[ia[~tv.inliers], ik[~tv.inliers]]
    m.obs_active[outliers] = False
    R_a, t_a = m.R_wc[a], m.t_wc[a]
    logger.info(
        "keyframe %d: placed by two views with keyframe %d (%d inliers, baseline %.2f m)",
        k, a, int(tv.inliers.sum()), length,
    )  # fmt: skip
    return Tracked(
        R_a @ tv.R_wc,
        t_a + length * (R_a @ tv.t_wc),
        int(tv.inliers.sum()),
        True,
        int(outliers.size // 2),
    )
