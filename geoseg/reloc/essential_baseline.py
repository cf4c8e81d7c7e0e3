"""Classical relative-pose baseline: keypoints -> essential matrix -> (R_ab, t_dir_ab).

The baseline against which the relative-pose head (:mod:`geoseg.models.relpose`) is judged:

1. :func:`detect_and_match`: OpenCV ORB (default) or SIFT keypoints, brute-force matching with
   Lowe's ratio test (or a cross-check);
2. :func:`relative_pose_from_matches`: ``cv2.findEssentialMat`` (MAGSAC++ or RANSAC) +
   ``cv2.recoverPose`` (cheirality), converted to the convention of
   :func:`geoseg.models.relpose.relative_pose_labels`;
3. :func:`estimate_relative_pose`: both, on two images.

Convention. OpenCV's ``recoverPose(E, pts1, pts2)`` returns ``(R, t)`` with
``X_2 = R X_1 + t`` (points in camera 2 from points in camera 1). With ``pts1`` from image a and
``pts2`` from image b this is ``X_b = R X_a + t``, hence ``X_a = R^T X_b - R^T t``, i.e.
``R_ab = R^T`` and ``t_dir_ab = -R^T t / |t|``: the unit direction from camera a's centre
towards camera b's centre in camera a's frame, the same as ``relative_pose_labels`` (with
``a`` = base image, ``b`` = query, it is the ray :func:`geoseg.reloc.retrieval.absolute_position`
casts). Scale is unobservable: only the direction is returned.

Failures are explicit: too few keypoints, matches or inliers (or no essential matrix) give a
:class:`RelativePoseEstimate` with ``ok=False``, a ``reason`` and NaN pose, never a garbage pose.
RANSAC is made deterministic with ``cv2.setRNGSeed(seed)``.

Metrics reusable by the benchmark: :func:`rotation_error_deg`, :func:`direction_error_deg`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from geoseg.errors import GeosegError, check_finite, check_positive, check_shape

logger = logging.getLogger(__name__)

__all__ = [
    "METHODS",
    "RelativePoseEstimate",
    "detect_and_match",
    "direction_error_deg",
    "estimate_relative_pose",
    "relative_pose_from_matches",
    "rotation_error_deg",
]

METHODS = ("orb", "sift")
# robust estimators of cv2.findEssentialMat; MAGSAC++ (USAC) is the default: on ORB matches it is
# several times more accurate than the classic RANSAC, which has no final refit.
ROBUST = {"magsac": "USAC_MAGSAC", "ransac": "RANSAC", "accurate": "USAC_ACCURATE"}
# The five-point solver needs 5 correspondences; below this many inliers the pose is unreliable.
DEFAULT_MIN_INLIERS = 15


@dataclass(frozen=True)
class RelativePoseEstimate:
    """Result of the essential-matrix baseline for a pair ``(a, b)``.

    Attributes:
        ok: True when a pose was recovered with at least ``min_inliers`` inliers.
        R_ab: ``(3, 3)`` float64 rotation ``R_wc_a^T R_wc_b`` (NaN when not ``ok``).
        t_dir_ab: ``(3,)`` float64 unit direction a -> b in camera a's frame (NaN when not ok).
        n_matches: number of putative correspondences.
        n_inliers: correspondences consistent with the essential matrix and in front of both
            cameras.
        reason: why ``ok`` is False ("" when ok).
        inliers: ``(n_matches,)`` bool inlier mask (empty when there were no matches).
    """

    ok: bool
    R_ab: np.ndarray
    t_dir_ab: np.ndarray
    n_matches: int
    n_inliers: int
    reason: str = ""
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))


def _failure(reason: str, n_matches: int, n_inliers: int = 0, inliers=None) -> RelativePoseEstimate:
    logger.debug("relative pose failed: %s", reason)
    return RelativePoseEstimate(
        ok=False,
        R_ab=np.full((3, 3), np.nan),
        t_dir_ab=np.full(3, np.nan),
        n_matches=int(n_matches),
        n_inliers=int(n_inliers),
        reason=reason,
        inliers=np.zeros(n_matches, dtype=bool) if inliers is None else inliers,
    )


def _check_K(K: Any) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    check_shape("K", K, (3, 3))
    check_finite("K", K)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-9 or np.any(K[2, :2] != 0):
        raise GeosegError(
            f"K: expected a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
            f"got {K.tolist()}"
        )
    return K


# ============================================================================ geometry


def relative_pose_from_matches(
    uv_a: Any,
    uv_b: Any,
    K: Any,
    *,
    ransac_threshold_px: float = 1.0,
    confidence: float = 0.999,
    min_inliers: int = DEFAULT_MIN_INLIERS,
    robust: str = "magsac",
    min_parallax_px: float = 1.0,
    seed: int = 0,
) -> RelativePoseEstimate:
    """Relative pose from point correspondences (essential matrix, RANSAC, cheirality).

    Both images are assumed taken with the same pinhole camera ``K`` (undistorted pixels).

    Args:
        uv_a: ``(N, 2)`` pixel coordinates in image a.
        uv_b: ``(N, 2)`` corresponding pixel coordinates in image b.
        K: ``(3, 3)`` intrinsics.
        ransac_threshold_px: RANSAC inlier threshold (pixels, point-to-epipolar-line), > 0.
        confidence: RANSAC confidence in ``(0, 1)``.
        min_inliers: fewest inliers (after ``recoverPose``'s cheirality check) accepted, >= 5.
        robust: ``findEssentialMat``'s estimator: ``"magsac"`` (``cv2.USAC_MAGSAC``, MAGSAC++,
            default), ``"ransac"`` (``cv2.RANSAC``, classic) or ``"accurate"``
            (``cv2.USAC_ACCURATE``).
        min_parallax_px: minimum median parallax of the inliers once the rotation is removed
            (``|uv_b - pi(K R K^-1 uv_a)|``, pixels); below it the views differ by a pure
            rotation (or not at all) and the translation direction is undefined: ``ok=False``.
        seed: OpenCV RNG seed (``cv2.setRNGSeed``), for repeatable RANSAC.

    Returns:
        :class:`RelativePoseEstimate` (``ok=False`` with a reason when there are fewer than
        ``min_inliers`` matches or inliers, or no essential matrix is found).
    """
    import cv2

    a = np.asarray(uv_a, dtype=np.float64)
    b = np.asarray(uv_b, dtype=np.float64)
    check_shape("uv_a", a, (None, 2))
    check_shape("uv_b", b, (a.shape[0], 2))
    check_finite("uv_a", a)
    check_finite("uv_b", b)
    K = _check_K(K)
    check_positive("ransac_threshold_px", ransac_threshold_px)
    check_positive("min_parallax_px", min_parallax_px, strict=False)
    if not 0.0 < confidence < 1.0:
        raise GeosegError(f"confidence: expected a value in (0, 1), got {confidence}")
    if isinstance(min_inliers, bool) or not isinstance(min_inliers, int) or min_inliers < 5:
        raise GeosegError(f"min_inliers: expected an int >= 5, got {min_inliers!r}")
    if robust not in ROBUST:
        raise GeosegError(f"robust: expected one of {tuple(ROBUST)}, got {robust!r}")
    n = a.shape[0]
    if n < min_inliers:
        return _failure(f"too few matches ({n} < {min_inliers})", n)
    still = float(np.median(np.linalg.norm(b - a, axis=1)))
    if still < min_parallax_px:
        return _failure(
            f"insufficient parallax (median displacement {still:.2f} px < {min_parallax_px} px: "
            "identical views)",
            n,
        )
    cv2.setRNGSeed(int(seed))
    try:
        return _solve_essential(
            cv2, a, b, K, robust, confidence, ransac_threshold_px, min_inliers, min_parallax_px
        )
    except cv2.error as err:  # degenerate input OpenCV refuses: a failure, not a crash
        msg = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
        return _failure(f"OpenCV could not estimate the pose ({msg[:200]})", n)


def _solve_essential(
    cv2: Any,
    a: np.ndarray,
    b: np.ndarray,
    K: np.ndarray,
    robust: str,
    confidence: float,
    ransac_threshold_px: float,
    min_inliers: int,
    min_parallax_px: float,
) -> RelativePoseEstimate:
    """``findEssentialMat`` + ``recoverPose`` + checks (see :func:`relative_pose_from_matches`)."""
    n = a.shape[0]
    E, mask = cv2.findEssentialMat(
        a,
        b,
        K,
        method=getattr(cv2, ROBUST[robust]),
        prob=float(confidence),
        threshold=float(ransac_threshold_px),
    )
    if E is None or mask is None or E.shape[0] < 3:
        return _failure("no essential matrix found", n)
    mask = mask.ravel().astype(bool)
    if mask.sum() < min_inliers:
        return _failure(
            f"too few RANSAC inliers ({int(mask.sum())} < {min_inliers})", n, mask.sum()
        )
    best = None
    # findEssentialMat may return several stacked 3x3 solutions: keep the best-supported one
    for s in range(E.shape[0] // 3):
        Es = np.ascontiguousarray(E[3 * s : 3 * s + 3])
        m_in = (mask.astype(np.uint8) * 255).reshape(-1, 1)
        good, R, t, m_out = cv2.recoverPose(Es, a, b, K, mask=m_in.copy())
        if best is None or good > best[0]:
            best = (int(good), R, t, m_out)
    good, R, t, m_out = best
    inliers = m_out.ravel() > 0
    if good < min_inliers:
        return _failure(
            f"too few inliers in front of both cameras ({good} < {min_inliers})", n, good, inliers
        )
    t = t.ravel()
    norm = np.linalg.norm(t)
    if not np.isfinite(norm) or norm < 1e-12:
        return _failure("degenerate translation (zero baseline)", n, good, inliers)
    # parallax left once the rotation is compensated (pure rotation: x_b ~ K R K^-1 x_a)
    H = K @ R @ np.linalg.inv(K)
    pa = np.c_[a[inliers], np.ones(int(inliers.sum()))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        parallax = np.linalg.norm(pa[:, :2] / pa[:, 2:3] - b[inliers], axis=1)
    med = float(np.nanmedian(parallax)) if parallax.size else 0.0
    if not med >= min_parallax_px:
        return _failure(
            f"insufficient parallax ({med:.2f} px < {min_parallax_px} px: pure rotation or no "
            "baseline, the translation direction is undefined)",
            n,
            good,
            inliers,
        )
    R_ab = R.T
    t_dir_ab = -(R.T @ t) / norm
    return RelativePoseEstimate(
        ok=True,
        R_ab=R_ab,
        t_dir_ab=t_dir_ab,
        n_matches=n,
        n_inliers=good,
        reason="",
        inliers=inliers,
    )


# ============================================================================ features


def _gray(name: str, image: Any) -> np.ndarray:
    import cv2

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        if img.dtype != np.uint8:
            raise GeosegError(f"{name}: expected a uint8 image, got dtype {img.dtype}")
        return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.ndim == 2:
        if img.dtype != np.uint8:
            raise GeosegError(f"{name}: expected a uint8 image, got dtype {img.dtype}")
        return img
    raise GeosegError(f"{name}: expected an (H, W, 3) RGB or (H, W) gray image, got {img.shape}")


def detect_and_match(
    image_a: Any,
    image_b: Any,
    *,
    method: str = "orb",
    max_features: int = 4000,
    ratio: float | None = 0.8,
    cross_check: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Detect keypoints in two images and match their descriptors.

    Args:
        image_a: ``(H, W, 3)`` RGB or ``(H, W)`` gray uint8.
        image_b: same, image b (any size).
        method: ``"orb"`` (binary descriptors, Hamming distance) or ``"sift"`` (L2).
        max_features: keypoints kept per image.
        ratio: Lowe's ratio-test threshold (best / second-best distance); None to skip it.
        cross_check: keep only mutual nearest neighbours (may combine with ``ratio``).

    Returns:
        ``(uv_a (N, 2), uv_b (N, 2))`` float64 pixel coordinates of the matches (``N`` may be 0).
    """
    import cv2

    if method not in METHODS:
        raise GeosegError(f"method: expected one of {METHODS}, got {method!r}")
    if isinstance(max_features, bool) or not isinstance(max_features, int) or max_features < 8:
        raise GeosegError(f"max_features: expected an int >= 8, got {max_features!r}")
    if ratio is not None and not 0.0 < ratio <= 1.0:
        raise GeosegError(f"ratio: expected a value in (0, 1] or None, got {ratio}")
    ga, gb = _gray("image_a", image_a), _gray("image_b", image_b)
    if method == "orb":
        detector = cv2.ORB_create(nfeatures=max_features)
        norm = cv2.NORM_HAMMING
    else:
        detector = cv2.SIFT_create(nfeatures=max_features)
        norm = cv2.NORM_L2
    kp_a, des_a = detector.detectAndCompute(ga, None)
    kp_b, des_b = detector.detectAndCompute(gb, None)
    empty = np.zeros((0, 2))
    if des_a is None or des_b is None or len(kp_a) < 2 or len(kp_b) < 2:
        return empty, empty.copy()
    pairs: list[tuple[int, int]] = []
    if ratio is None:
        matcher = cv2.BFMatcher(norm, crossCheck=bool(cross_check))
        pairs = [(m.queryIdx, m.trainIdx) for m in matcher.match(des_a, des_b)]
    else:
        matcher = cv2.BFMatcher(norm)
        knn = matcher.knnMatch(des_a, des_b, k=2)
        for cand in knn:
            if len(cand) == 2 and cand[0].distance < ratio * cand[1].distance:
                pairs.append((cand[0].queryIdx, cand[0].trainIdx))
        if cross_check and pairs:
            back = {m.queryIdx: m.trainIdx for m in matcher.match(des_b, des_a)}
            pairs = [(qa, tb) for qa, tb in pairs if back.get(tb) == qa]
    if not pairs:
        return empty, empty.copy()
    uv_a = np.array([kp_a[i].pt for i, _ in pairs], dtype=np.float64)
    uv_b = np.array([kp_b[j].pt for _, j in pairs], dtype=np.float64)
    return uv_a, uv_b


def estimate_relative_pose(
    image_a: Any,
    image_b: Any,
    K: Any,
    *,
    method: str = "orb",
    max_features: int = 4000,
    ratio: float | None = 0.8,
    cross_check: bool = False,
    ransac_threshold_px: float = 1.0,
    confidence: float = 0.999,
    min_inliers: int = DEFAULT_MIN_INLIERS,
    robust: str = "magsac",
    min_parallax_px: float = 1.0,
    seed: int = 0,
) -> RelativePoseEstimate:
    """The full baseline on two images taken with the same camera ``K``.

    Args:
        image_a: ``(H, W, 3)`` RGB or ``(H, W)`` gray uint8 (e.g. the base image).
        image_b: same, the second image (e.g. the query).
        K: ``(3, 3)`` intrinsics.
        method, max_features, ratio, cross_check: see :func:`detect_and_match`.
        ransac_threshold_px, confidence, min_inliers, robust, min_parallax_px, seed: see
            :func:`relative_pose_from_matches`.

    Returns:
        :class:`RelativePoseEstimate` for ``(a, b)`` in the ``relative_pose_labels`` convention.

    Raises:
        GeosegError: the two images differ in size (one ``K`` cannot hold for both), or the
            principal point lies outside them (``K`` is another size's).
    """
    K = _check_K(K)
    (ha, wa), (hb, wb) = np.shape(image_a)[:2], np.shape(image_b)[:2]
    if (ha, wa) != (hb, wb):
        raise GeosegError(
            f"image_a, image_b: {wa}x{ha} and {wb}x{hb} pixels; one K holds for one image size "
            "(resize one of them, or use per-image intrinsics)"
        )
    if not (0.0 <= K[0, 2] <= wa and 0.0 <= K[1, 2] <= ha):
        raise GeosegError(
            f"K: principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {wa}x{ha} images "
            "(intrinsics of another image size?)"
        )
    uv_a, uv_b = detect_and_match(
        image_a,
        image_b,
        method=method,
        max_features=max_features,
        ratio=ratio,
        cross_check=cross_check,
    )
    return relative_pose_from_matches(
        uv_a,
        uv_b,
        K,
        ransac_threshold_px=ransac_threshold_px,
        confidence=confidence,
        min_inliers=min_inliers,
        robust=robust,
        min_parallax_px=min_parallax_px,
        seed=seed,
    )


# ============================================================================ metrics


def rotation_error_deg(R_est: Any, R_gt: Any) -> np.ndarray | float:
    """Geodesic angle between rotations, ``arccos((tr(R_gt^T R_est) - 1) / 2)`` in degrees.

    Args:
        R_est: ``(3, 3)`` or ``(N, 3, 3)`` estimated rotations.
        R_gt: same shape, ground truth.

    Returns:
        A float for single rotations, else ``(N,)`` float64 (NaN where ``R_est`` is NaN).
    """
    a = np.asarray(R_est, dtype=np.float64)
    b = np.asarray(R_gt, dtype=np.float64)
    if a.shape[-2:] != (3, 3) or a.shape != b.shape:
        raise GeosegError(
            f"R_est, R_gt: expected matching (3, 3) or (N, 3, 3) shapes, got {a.shape}, {b.shape}"
        )
    tr = np.einsum("...ij,...ij->...", b, a)  # tr(b^T a)
    ang = np.degrees(np.arccos(np.clip((tr - 1.0) * 0.5, -1.0, 1.0)))
    return float(ang) if ang.ndim == 0 else ang


def direction_error_deg(t_est: Any, t_gt: Any) -> np.ndarray | float:
    """Angle between translation directions in degrees (both normalised here).

    Args:
        t_est: ``(3,)`` or ``(N, 3)`` estimated directions.
        t_gt: same shape, ground truth.

    Returns:
        A float for single vectors, else ``(N,)`` float64 (NaN where a vector is NaN or zero).
    """
    a = np.asarray(t_est, dtype=np.float64)
    b = np.asarray(t_gt, dtype=np.float64)
    if a.shape[-1:] != (3,) or a.shape != b.shape:
        raise GeosegError(
            f"t_est, t_gt: expected matching (3,) or (N, 3) shapes, got {a.shape}, {b.shape}"
        )
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.einsum("...i,...i->...", a, b) / (na * nb)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    ang = np.where((na > 0) & (nb > 0), ang, np.nan)
    return float(ang) if ang.ndim == 0 else ang
