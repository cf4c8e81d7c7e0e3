"""Trajectory and reconstruction metrics against ground truth (thesis §3.7).

* **Errors** against ground truth, per keyframe: translation ``e_T = ||T_est - T_gt||`` (metres)
  and rotation ``e_R = ||log_SO3(R_est^T R_gt)||`` (radians, as the thesis); summarised by mean,
  standard deviation and median (``mu``, ``sigma``, ``m`` of Table 3.1). The reconstruction is
  compared in the world frame directly: the GPS fusion georeferences it, so no alignment is
  applied (:func:`align_similarity` is there for unfused runs). The translation error is also
  split into its horizontal part (what the GPS constrains) and its vertical part (the GPS
  altitude is ignored, eq. B.7, so only vision holds the altitude).
* **Inliers** (§3.7): a triangulated point is an inlier iff *all* its (kept) reprojection errors
  are below 2 px; the **inlier loss** of a method is ``max(0, (N_0 - N) / N_0)`` against ``n = 0``
  (``N_0``) under the same GPS setting (Table 3.2). Two readings are reported. ``inliers``
  (primary): the points are re-triangulated from their kept observations with the *final*
  camera poses (structure-only refinement, :func:`count_inliers` with ``retriangulate=True``),
  so the count measures whether the final trajectory still satisfies the multi-view
  constraints, whatever happened to the stored points. ``inliers_raw``: the stored points as the
  SLAM left them. The two differ for the hybrids: a pose-graph camera keeps moving (fusion)
  after its points left the problem, so the stored points of old keyframes go stale.
  ``inliers_truth``: the same points and observations re-triangulated with the *true* poses,
  the count a perfect trajectory would score. With 1 px noise per axis a correct observation
  fails the 2 px test with probability ``exp(-2) = 13.5 %``, so most points seen ~12 times fail
  even at the truth: the count measures small departures from the truth's consistency (on the
  bench drive ~400 points have their worst error within 0.1 px of the threshold). So the net
  loss is the difference of two large churns: ``<method>_<setting>_inliers_lost`` (inliers of
  ``n = 0`` that the method's poses fail) and ``..._inliers_gained`` (the reverse), and
  ``..._inlier_loss_noise`` is ``sqrt(lost + gained) / N_0``, the standard deviation the net
  loss would have if each of those points had flipped either way by chance (a sign test): a
  loss within one or two of it is not evidence of a worse trajectory.
"""

from __future__ import annotations

import numpy as np

from geoseg.errors import check_shape
from slam_bridge.errors import SlamError
from slam_bridge.geometry.alignment import rotation_and_scale
from slam_bridge.geometry.camera import project
from slam_bridge.geometry.lie import so3_log

__all__ = [
    "rotation_errors",
    "translation_errors",
    "error_stats",
    "align_similarity",
    "count_inliers",
    "inlier_mask",
    "inlier_loss",
    "inlier_churn",
]


def rotation_errors(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Angles of ``R_est^T R_gt``.

    Args:
        R_est: ``(N, 3, 3)`` estimated rotations.
        R_gt: ``(N, 3, 3)`` true rotations.

    Returns:
        ``(N,)`` radians in ``[0, pi]``.
    """
    R_est = np.asarray(R_est, dtype=np.float64)
    R_gt = np.asarray(R_gt, dtype=np.float64)
    check_shape("R_est", R_est, (None, 3, 3))
    check_shape("R_gt", R_gt, (R_est.shape[0], 3, 3))
    if R_est.shape[0] == 0:
        return np.zeros(0)
    return np.linalg.norm(so3_log(np.swapaxes(R_est, 1, 2) @ R_gt), axis=-1).reshape(-1)


def translation_errors(t_est: np.ndarray, t_gt: np.ndarray) -> np.ndarray:
    """``||t_est - t_gt||`` per row: ``(N, 3)``, ``(N, 3)`` -> ``(N,)`` metres."""
    t_est = np.asarray(t_est, dtype=np.float64)
    t_gt = np.asarray(t_gt, dtype=np.float64)
    check_shape("t_est", t_est, (None, 3))
    check_shape("t_gt", t_gt, (t_est.shape[0], 3))
    return np.linalg.norm(t_est - t_gt, axis=1)


def error_stats(e: np.ndarray) -> dict[str, float]:
    """``{"mean", "std", "median", "max"}`` of ``e (N,)``; raises on NaN (never silent)."""
    e = np.asarray(e, dtype=np.float64).reshape(-1)
    if e.size == 0:
        raise SlamError("error_stats: no error to summarise")
    if not np.all(np.isfinite(e)):
        raise SlamError("error_stats: non-finite errors (a NaN trajectory?)")
    return {
        "mean": float(e.mean()),
        "std": float(e.std()),
        "median": float(np.median(e)),
        "max": float(e.max()),
    }


def align_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991).

    Args:
        src: ``(N, 3)`` points (N >= 3, not collinear).
        dst: ``(N, 3)`` points.

    Returns:
        ``s``, ``R (3, 3)``, ``t (3,)``.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    check_shape("src", src, (None, 3))
    check_shape("dst", dst, (src.shape[0], 3))
    if src.shape[0] < 3:
        raise SlamError("align_similarity: needs at least 3 points")
    ms, md = src.mean(0), dst.mean(0)
    xs, xd = src - ms, dst - md
    s, R = rotation_and_scale(xs, xd, xd.T @ xs, fix_scale=False, name="align_similarity")
    return s, R, md - s * R @ ms


def inlier_mask(
    K: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    obs_keyframe: np.ndarray,
    obs_point: np.ndarray,
    uv: np.ndarray,
    *,
    used: np.ndarray | None = None,
    triangulated: np.ndarray | None = None,
    threshold_px: float = 2.0,
    retriangulate: bool = False,
) -> np.ndarray:
    """Points whose reprojection errors are all below ``threshold_px`` (§3.7).

    Args:
        K: ``(3, 3)``.
        R_wc: ``(C, 3, 3)`` keyframe rotations.
        t_wc: ``(C, 3)`` optical centres.
        X_w: ``(P, 3)`` points (NaN rows = not reconstructed).
        obs_keyframe: ``(M,)`` keyframe of each observation.
        obs_point: ``(M,)`` point of each observation.
        uv: ``(M, 2)`` measured pixels.
        used: ``(M,)`` bool, observations the reconstruction kept (default all).
        triangulated: ``(P,)`` bool (default: finite rows of ``X_w``).
        threshold_px: the inlier threshold.
        retriangulate: re-estimate the points from their kept observations with the given
            poses (DLT + Gauss-Newton, no parallax requirement) before the test.

    Returns:
        ``(P,)`` bool: the inlier points (each with at least one kept observation).
    """
    X_w = np.asarray(X_w, dtype=np.float64)
    P = X_w.shape[0]
    tri = np.all(np.isfinite(X_w), axis=1) if triangulated is None else np.asarray(triangulated)
    keep = np.ones(len(obs_keyframe), dtype=bool) if used is None else np.asarray(used, bool)
    keep = keep & tri[obs_point] & (obs_keyframe < R_wc.shape[0])
    kf, pt = obs_keyframe[keep], obs_point[keep]
    if retriangulate and kf.size:
        from slam_bridge.geometry.multiview import triangulate

        res = triangulate(
            K, R_wc, t_wc, kf, pt, uv[keep], num_points=P, min_parallax_deg=0.0,
            refine_iterations=5,
        )  # fmt: skip
        X_w = np.where(tri[:, None], res.X_w, np.nan)
    uv_hat, _, front = project(K, R_wc[kf], t_wc[kf], np.nan_to_num(X_w[pt]))
    err = np.where(front, np.linalg.norm(np.nan_to_num(uv_hat - uv[keep], nan=1e9), axis=1), 1e9)
    seen = np.bincount(pt, minlength=P) > 0
    bad = np.bincount(pt, weights=(err >= threshold_px).astype(float), minlength=P) > 0
    return seen & ~bad


def count_inliers(*args, **kwargs) -> int:
    """The number of inlier points: :func:`inlier_mask` (same arguments) summed."""
    return int(np.sum(inlier_mask(*args, **kwargs)))


def inlier_loss(n_method: int, n_reference: int) -> float:
    """``max(0, (N_0 - N) / N_0)`` (a share in ``[0, 1]``)."""
    if n_reference <= 0:
        raise SlamError("inlier_loss: the reference has no inlier")
    return max(0.0, (n_reference - n_method) / n_reference)


def inlier_churn(reference: np.ndarray | None, method: np.ndarray | None) -> tuple[int, int] | None:
    """``(lost, gained)``: points inlier for the reference (``n = 0``) but not for the method,
    and the reverse (module docstring), from two ``(P,)`` bool masks of the same points; None
    when a mask is missing.

    Raises:
        SlamError: masks of different lengths (runs of different sequences).
    """
    if reference is None or method is None:
        return None
    ref, met = np.asarray(reference, dtype=bool), np.asarray(method, dtype=bool)
    if ref.shape != met.shape:
        raise SlamError(f"inlier masks of shapes {ref.shape} and {met.shape}: not the same points")
    return int(np.sum(ref & ~met)), int(np.sum(~ref & met))
