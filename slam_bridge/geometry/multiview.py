"""Multi-view geometry for map building: triangulation, two-view initialisation, PnP.

Poses follow :mod:`slam_bridge.geometry.camera` (``R_wc``, ``t_wc``, OpenCV camera frame).

* :func:`triangulate`: linear DLT over all views of each point (vectorised over points: the
  ``4 x 4`` normal matrices ``A^T A`` are summed per point and their smallest eigenvectors taken
  in one batched ``eigh``), then optional Gauss-Newton refinement of the reprojection error with
  the cameras fixed (also vectorised). Each point is checked for cheirality (in front of every
  view) and parallax (the largest angle between its first view's ray and any other view's ray).
* :func:`two_view_init`: essential matrix (``cv2.findEssentialMat``, MAGSAC++ or RANSAC) and
  ``cv2.recoverPose``; camera 1 is the world frame, the baseline has unit length.
* :func:`pnp`: ``cv2.solvePnPRansac`` then ``cv2.solvePnPRefineLM`` on the inliers.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from geoseg.errors import check_finite, check_shape
from slam_bridge.errors import SlamError
from slam_bridge.geometry.camera import DEFAULT_EPS, _check_K, project, project_with_jacobians
from slam_bridge.geometry.sums import _segment_sum

logger = logging.getLogger(__name__)

__all__ = [
    "TriangulationResult",
    "ray_parallax_deg",
    "triangulate",
    "TwoViewResult",
    "two_view_init",
    "PnPResult",
    "pnp",
]


@dataclass
class TriangulationResult:
    """Triangulated points.

    Attributes:
        X_w: ``(P, 3)`` points (NaN where the DLT failed, e.g. a point at infinity).
        valid: ``(P,)`` bool, finite, in front of all its views, parallax >= the threshold,
            and at least two views.
        in_front: ``(P,)`` bool, in front of every view.
        parallax_deg: ``(P,)`` largest ray angle to the first view (degrees).
        num_views: ``(P,)`` int.
        rms_px: ``(P,)`` RMS reprojection error (pixels; NaN if invalid).
    """

    X_w: np.ndarray
    valid: np.ndarray
    in_front: np.ndarray
    parallax_deg: np.ndarray
    num_views: np.ndarray
    rms_px: np.ndarray


def ray_parallax_deg(
    centres: np.ndarray, X_obs: np.ndarray, points: np.ndarray, num_points: int
) -> np.ndarray:
    """Parallax of each point: the largest angle between its first view's ray and any other
    view's ray (the first view = its first row).

    Args:
        centres: ``(M, 3)`` optical centre of each view (observation).
        X_obs: ``(M, 3)`` the observed point's position, per view.
        points: ``(M,)`` point index of each view, in ``0..num_points-1``.
        num_points: ``P``.

    Returns:
        ``(P,)`` degrees (0 for points with fewer than two views).
    """
    rays = X_obs - centres
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-300)
    first = np.full(num_points, -1, dtype=np.int64)
    order = np.argsort(points, kind="stable")
    uniq, idx = np.unique(points[order], return_index=True)
    first[uniq] = order[idx]
    cosang = np.einsum("mi,mi->m", rays, rays[first[points]])
    parallax = np.zeros(num_points)
    np.maximum.at(parallax, points, np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))))
    return parallax


def triangulate(
    K: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    obs_cameras: np.ndarray,
    obs_points: np.ndarray,
    uv: np.ndarray,
    *,
    num_points: int | None = None,
    refine_iterations: int = 5,
    min_parallax_deg: float = 1.0,
    eps: float = DEFAULT_EPS,
) -> TriangulationResult:
    """Triangulate points from two or more calibrated views.

    Args:
        K: ``(3, 3)`` shared or ``(C, 3, 3)`` per-camera calibration.
        R_wc: ``(C, 3, 3)`` camera-to-world rotations (finite for the cameras observed).
        t_wc: ``(C, 3)`` optical centres.
        obs_cameras: ``(M,)`` camera index of each observation.
        obs_points: ``(M,)`` point index of each observation (``0..P-1``).
        uv: ``(M, 2)`` pixels.
        num_points: ``P`` (default ``max(obs_points) + 1``).
        refine_iterations: Gauss-Newton iterations on the reprojection error (0: DLT only).
        min_parallax_deg: parallax threshold for ``valid``.
        eps: minimal depth.

    Returns:
        A :class:`TriangulationResult`.
    """
    K = _check_K(K)
    R_wc = np.asarray(R_wc, dtype=np.float64)
    t_wc = np.asarray(t_wc, dtype=np.float64)
    check_shape("R_wc", R_wc, (None, 3, 3))
    check_shape("t_wc", t_wc, (R_wc.shape[0], 3))
    cams = np.asarray(obs_cameras, dtype=np.int64).reshape(-1)
    pts = np.asarray(obs_points, dtype=np.int64).reshape(-1)
    uv = np.asarray(uv, dtype=np.float64)
    M = cams.size
    check_shape("obs_points", pts, (M,))
    check_shape("uv", uv, (M, 2))
    check_finite("uv", uv)
    if M and (cams.min() < 0 or cams.max() >= R_wc.shape[0]):
        raise SlamError("obs_cameras: index out of range")
    used = np.unique(cams)  # cameras no observation refers to may be unset (NaN)
    check_finite("R_wc", R_wc[used])
    check_finite("t_wc", t_wc[used])
    if M and pts.min() < 0:
        raise SlamError("obs_points: negative index")
    P = int(num_points if num_points is not None else (pts.max() + 1 if M else 0))
    if M and pts.max() >= P:
        raise SlamError(f"obs_points: index {pts.max()} >= num_points {P}")
    Km = K if K.ndim == 2 else K[cams]
    Kinv = np.linalg.inv(Km)
    h = np.concatenate([uv, np.ones((M, 1))], axis=1)
    xn = (Kinv @ h[:, :, None])[:, :, 0] if Kinv.ndim == 3 else h @ Kinv.T
    xn = xn[:, :2] / xn[:, 2:]
    # world -> camera projection matrices, in a frame centred on the mean optical centre of the
    # cameras given (the map's keyframes). Centring on each point's observing cameras instead
    # was measured worse on the chapter-3 grid (docs/lessons.md).
    centre = np.nanmean(t_wc, axis=0) if t_wc.shape[0] else np.zeros(3)
    Rt = np.swapaxes(R_wc[cams], 1, 2)  # R_cw (M, 3, 3)
    tc = -(Rt @ (t_wc[cams] - centre)[:, :, None])[:, :, 0]
    Pm = np.concatenate([Rt, tc[:, :, None]], axis=2)  # (M, 3, 4)
    rows = np.stack(
        [xn[:, :1] * Pm[:, 2] - Pm[:, 0], xn[:, 1:] * Pm[:, 2] - Pm[:, 1]], axis=1
    )  # (M, 2, 4)
    rows /= np.linalg.norm(rows, axis=2, keepdims=True)
    AtA = _segment_sum(pts, np.swapaxes(rows, 1, 2) @ rows, P)  # (P, 4, 4)
    num_views = np.bincount(pts, minlength=P)
    _, vecs = np.linalg.eigh(AtA)
    v = vecs[:, :, 0]
    w = v[:, 3]
    finite = (np.abs(w) > 1e-12 * np.linalg.norm(v, axis=1)) & (num_views >= 2)
    X = np.full((P, 3), np.nan)
    X[finite] = v[finite, :3] / w[finite, None] + centre
    for _ in range(refine_iterations):
        X = _refine_step(K, R_wc, t_wc, cams, pts, uv, X, finite, P, eps)
    # checks
    Xo = np.where(finite[:, None], X, 0.0)[pts]
    uv_hat, z, front = project(Km, R_wc[cams], t_wc[cams], Xo, eps)
    in_front = (_segment_sum(pts, (~front).astype(float)[:, None], P)[:, 0] == 0) & finite
    parallax = ray_parallax_deg(t_wc[cams], Xo, pts, P)
    err2 = np.where(front, np.sum((uv_hat - uv) ** 2, axis=1), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(_segment_sum(pts, err2[:, None], P)[:, 0] / np.maximum(num_views, 1))
    rms[~in_front] = np.nan
    valid = finite & in_front & (parallax >= min_parallax_deg) & (num_views >= 2)
    return TriangulationResult(X, valid, in_front, parallax, num_views, rms)


def _refine_step(K, R_wc, t_wc, cams, pts, uv, X, finite, P, eps):
    Km = K if K.ndim == 2 else K[cams]
    Xo = np.where(finite[:, None], X, 0.0)
    uv_hat, _, front, _, Jp = project_with_jacobians(Km, R_wc[cams], t_wc[cams], Xo[pts], eps)
    r = np.where(front[:, None], uv_hat - uv, 0.0)
    JT = np.swapaxes(Jp, 1, 2)
    H = _segment_sum(pts, JT @ Jp, P)
    g = _segment_sum(pts, (JT @ r[:, :, None])[:, :, 0], P)
    H += 1e-9 * np.eye(3) * np.maximum(np.trace(H, axis1=1, axis2=2), 1e-12)[:, None, None] / 3
    ok = finite & (np.linalg.det(H) > 0)
    dX = np.zeros((P, 3))
    if np.any(ok):
        dX[ok] = -np.linalg.solve(H[ok], g[ok][:, :, None])[:, :, 0]
    return np.where(finite[:, None], X + dX, X)


@dataclass
class TwoViewResult:
    """Relative pose of view 2 (view 1 = world frame, unit baseline).

    Attributes:
        R_wc: ``(3, 3)`` view 2's camera-to-world rotation.
        t_wc: ``(3,)`` view 2's optical centre (``||t_wc|| = 1``).
        inliers: ``(N,)`` bool, essential-matrix inliers that passed ``recoverPose``'s
            cheirality test.
        E: ``(3, 3)`` essential matrix (``x2^T E x1 = 0`` in normalised coordinates).
    """

    R_wc: np.ndarray
    t_wc: np.ndarray
    inliers: np.ndarray
    E: np.ndarray


def two_view_init(
    K: np.ndarray,
    uv1: np.ndarray,
    uv2: np.ndarray,
    *,
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    seed: int = 0,
    method: str = "magsac",
) -> TwoViewResult:
    """Essential-matrix initialisation of a monocular map.

    Args:
        K: ``(3, 3)`` calibration shared by both views.
        uv1: ``(N, 2)`` pixels in view 1 (``N >= 5``).
        uv2: ``(N, 2)`` matching pixels in view 2.
        threshold_px: RANSAC inlier threshold.
        confidence: RANSAC confidence.
        seed: OpenCV RNG seed (determinism).
        method: ``"magsac"`` (``cv2.USAC_MAGSAC``, MAGSAC++: on image tracks its relative
            rotations were several times closer to the truth than plain RANSAC's) or ``"ransac"``.

    Returns:
        A :class:`TwoViewResult`.
    """
    K = _check_K(K)
    uv1 = np.asarray(uv1, dtype=np.float64)
    uv2 = np.asarray(uv2, dtype=np.float64)
    check_shape("uv1", uv1, (None, 2))
    check_shape("uv2", uv2, (uv1.shape[0], 2))
    check_finite("uv1", uv1)
    check_finite("uv2", uv2)
    if uv1.shape[0] < 5:
        raise SlamError(f"two_view_init: needs >= 5 correspondences, got {uv1.shape[0]}")
    estimators = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}
    if method not in estimators:
        raise SlamError(f"method: expected one of {sorted(estimators)}, got {method!r}")
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(uv1, uv2, K, estimators[method], confidence, threshold_px)
    if E is None or E.shape[0] < 3 or E.shape[1] != 3:
        raise SlamError("two_view_init: no essential matrix found (degenerate motion?)")
    E = E[:3]  # several stacked solutions: the first, best-supported one
    n_good, R, t, mask2 = cv2.recoverPose(E, uv1, uv2, K, mask=mask.copy())
    if n_good < 5:
        raise SlamError(f"two_view_init: only {n_good} points pass the cheirality test")
    # X_c2 = R X_c1 + t, camera 1 = world
    R_wc = R.T
    t_wc = -(R.T @ t.reshape(3))
    t_wc /= np.linalg.norm(t_wc)
    return TwoViewResult(R_wc, t_wc, mask2.reshape(-1) > 0, E)


@dataclass
class PnPResult:
    """Absolute pose from 2D-3D matches.

    Attributes:
        R_wc: ``(3, 3)``.
        t_wc: ``(3,)``.
        inliers: ``(N,)`` bool.
        rms_px: RMS reprojection error over the inliers.
    """

    R_wc: np.ndarray
    t_wc: np.ndarray
    inliers: np.ndarray
    rms_px: float


def pnp(
    K: np.ndarray,
    X_w: np.ndarray,
    uv: np.ndarray,
    *,
    threshold_px: float = 2.0,
    iterations: int = 200,
    confidence: float = 0.999,
    min_inliers: int = 6,
    seed: int = 0,
) -> PnPResult:
    """Camera pose from 2D-3D correspondences (RANSAC + LM refinement).

    Args:
        K: ``(3, 3)``.
        X_w: ``(N, 3)`` world points (``N >= 4``).
        uv: ``(N, 2)`` pixels.
        threshold_px: RANSAC reprojection threshold.
        iterations: RANSAC iterations.
        confidence: RANSAC confidence.
        min_inliers: fewest inliers accepted.
        seed: OpenCV RNG seed.

    Returns:
        A :class:`PnPResult`.
    """
    K = _check_K(K)
    X_w = np.asarray(X_w, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    check_shape("X_w", X_w, (None, 3))
    check_shape("uv", uv, (X_w.shape[0], 2))
    check_finite("X_w", X_w)
    check_finite("uv", uv)
    if X_w.shape[0] < 4:
        raise SlamError(f"pnp: needs >= 4 correspondences, got {X_w.shape[0]}")
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        X_w,
        uv,
        K,
        None,
        iterationsCount=iterations,
        reprojectionError=threshold_px,
        confidence=confidence,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or idx is None or len(idx) < min_inliers:
        raise SlamError(
            f"pnp: RANSAC failed ({0 if idx is None else len(idx)} inliers < {min_inliers})"
        )
    inl = np.zeros(X_w.shape[0], dtype=bool)
    inl[idx.reshape(-1)] = True
    rvec, tvec = cv2.solvePnPRefineLM(X_w[inl], uv[inl], K, None, rvec, tvec)
    R_cw, _ = cv2.Rodrigues(rvec)
    R_wc = R_cw.T
    t_wc = -(R_cw.T @ tvec.reshape(3))
    uv_hat, _, front = project(K, R_wc, t_wc, X_w)
    err = np.sqrt(np.sum((uv_hat - uv) ** 2, axis=1))
    inl &= front & (err < threshold_px)
    rms = float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else float("nan")
    return PnPResult(R_wc, t_wc, inl, rms)
