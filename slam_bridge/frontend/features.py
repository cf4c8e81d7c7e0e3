"""Stateless image operations of the visual front end (:mod:`slam_bridge.frontend.image_tracks`).

* corners: :func:`detect_corners` (Shi-Tomasi, ``cv2.goodFeaturesToTrack``) away from the live
  tracks, :func:`grid_top_up` (grid bucketing);
* trackability of a Lucas-Kanade window, from the gradients (:func:`gradients`): the eigenvalue
  ratio of its structure tensor (:func:`isotropic`: an edge has the aperture problem: a track
  on it slides along it), and its fixed point under a change of scale (:func:`centre`);
* motion statistics over the ``k`` nearest tracks: :func:`flow_consistent` (a track that moves
  unlike its neighbours is stuck or has jumped) and :func:`local_affine` (the local deformation of
  the image since the last keyframe);
* photometry: :class:`GammaNormaliser` (dark frames brightened by a global, slowly varying
  lookup table);
* geometry: :func:`epipolar_inliers` (essential-matrix RANSAC, guarded against the degenerate
  cases);
* descriptors: :class:`OrbDescriptors` (upright ORB at given pixels) and
  :func:`match_in_radius` (descriptor matching within a pixel radius, ratio test, one-to-one).

:class:`TrackSet` holds the live tracks. Pixels follow OpenCV: ``uv = (x right, y down)``,
pixel centres at integers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "TrackSet",
    "GammaNormaliser",
    "epipolar_inliers",
    "Gradients",
    "gradients",
    "isotropic",
    "centre",
    "detect_corners",
    "grid_cells",
    "predicted_velocity",
    "grid_top_up",
    "neighbours",
    "flow_consistent",
    "local_affine",
    "OrbDescriptors",
    "match_in_radius",
]

DESCRIPTOR_BYTES = 32
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


@dataclass
class TrackSet:
    """Live tracks, ``N`` of them, in parallel arrays.

    Attributes:
        ids: ``(N,)`` int64 point ids.
        uv: ``(N, 2)`` float32 pixels in the current frame.
        vel: ``(N, 2)`` float32 last frame-to-frame displacement (NaN: not tracked yet).
        uv_kf: ``(N, 2)`` float32 pixels at the last keyframe.
        A: ``(N, 2, 2)`` local linear map of the image accumulated since the track's birth.
        ref_kf: ``(N,)`` int64 the keyframe whose patch is the track's reference (-1: none
            yet; :mod:`slam_bridge.frontend.patch_alignment`).
        ref_uv: ``(N, 2)`` float32 the track's pixel in that keyframe.
    """

    ids: np.ndarray
    uv: np.ndarray
    vel: np.ndarray
    uv_kf: np.ndarray
    A: np.ndarray
    ref_kf: np.ndarray
    ref_uv: np.ndarray

    @classmethod
    def empty(cls) -> TrackSet:
        z = np.zeros((0, 2), dtype=np.float32)
        ids = np.zeros(0, np.int64)
        return cls(ids, z, z.copy(), z.copy(), np.zeros((0, 2, 2)), ids.copy(), z.copy())

    def __len__(self) -> int:
        return int(self.ids.size)

    def keep(self, mask: np.ndarray) -> None:
        for name in ("ids", "uv", "vel", "uv_kf", "A", "ref_kf", "ref_uv"):
            setattr(self, name, getattr(self, name)[mask])

    def append(self, ids: np.ndarray, uv: np.ndarray) -> None:
        uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
        self.ids = np.concatenate([self.ids, ids])
        self.uv = np.concatenate([self.uv, uv])
        self.vel = np.concatenate([self.vel, np.full_like(uv, np.nan)])
        self.uv_kf = np.concatenate([self.uv_kf, uv])
        self.A = np.concatenate([self.A, np.broadcast_to(np.eye(2), (len(ids), 2, 2))])
        self.ref_kf = np.concatenate([self.ref_kf, np.full(len(ids), -1, dtype=np.int64)])
        self.ref_uv = np.concatenate([self.ref_uv, uv])


class GammaNormaliser:
    """Global gamma lookup that maps the median grey level to ``target`` (brightens only).

    The gamma follows a running median (weight 0.2 per frame) and is quantised to 0.05, so that
    consecutive frames almost always share one table and brightness constancy (Lucas-Kanade's
    assumption) holds between them.

    Args:
        target: share of 255 for the median grey level, in (0, 1).
    """

    def __init__(self, target: float) -> None:
        self.target = target
        self.gamma = 1.0
        self._median: float | None = None
        self._lut: np.ndarray | None = None

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        """``(H, W)`` uint8 -> the normalised image (the input itself when gamma is 1)."""
        median = float(np.median(gray[::8, ::8])) + 0.5
        self._median = median if self._median is None else 0.8 * self._median + 0.2 * median
        m = min(max(self._median / 255.0, 1e-3), 0.999)
        gamma = min(1.0, max(0.2, round(math.log(self.target) / math.log(m) * 20) / 20))
        if gamma >= 1.0:
            return gray
        if self._lut is None or gamma != self.gamma:
            self.gamma = gamma
            self._lut = np.round(255.0 * (np.arange(256) / 255.0) ** gamma).astype(np.uint8)
        return cv2.LUT(gray, self._lut)


def epipolar_inliers(
    uv0: np.ndarray,
    uv1: np.ndarray,
    K: np.ndarray,
    *,
    magsac: bool = True,
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    seed: int = 0,
    min_tracks: int = 15,
    min_motion_px: float = 1.0,
    min_inlier_share: float = 0.3,
) -> np.ndarray | None:
    """Tracks consistent with one essential matrix (``cv2.findEssentialMat``).

    Args:
        uv0: ``(N, 2)`` pixels in the first view.
        uv1: ``(N, 2)`` the same tracks in the second view.
        K: ``(3, 3)`` intrinsics.
        magsac: ``cv2.USAC_MAGSAC`` (else ``cv2.RANSAC``).
        threshold_px: inlier threshold.
        confidence: RANSAC confidence.
        seed: OpenCV RNG seed.
        min_tracks: fewer tracks: no check.
        min_motion_px: smaller median displacement: no check (no motion, no model).
        min_inlier_share: a model explaining fewer tracks is no model.

    Returns:
        ``(N,)`` bool, or None when the check is skipped.
    """
    n = uv0.shape[0]
    if n < max(min_tracks, 5) or np.median(np.linalg.norm(uv1 - uv0, axis=1)) < min_motion_px:
        return None
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(
        uv0.astype(np.float64),
        uv1.astype(np.float64),
        K,
        cv2.USAC_MAGSAC if magsac else cv2.RANSAC,
        confidence,
        threshold_px,
    )
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    inl = mask.reshape(-1) > 0
    return inl if inl.sum() >= min_inlier_share * n else None


@dataclass
class Gradients:
    """Sobel gradients of an image, ``(H, W)`` float32 each."""

    Ix: np.ndarray
    Iy: np.ndarray


def gradients(gray: np.ndarray) -> Gradients:
    """Gradients of ``gray`` ``(H, W)`` uint8 (3x3 Sobel)."""
    Ix = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    Iy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    return Gradients(Ix, Iy)


def _window_gradients(
    grads: Gradients, uv: np.ndarray, window: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gradients in the ``window`` x ``window`` square centred at the pixel nearest to each
    point of ``uv`` ``(N, 2)`` (clamped at the border): ``gx, gy (N, w * w)`` and the pixel
    coordinates ``U (N, w)``, ``V (N, w)`` of its columns and rows."""
    H, W = grads.Ix.shape
    off = np.arange(-(window // 2), window // 2 + 1)
    U = np.clip(np.round(uv[:, 0]).astype(np.int64)[:, None] + off, 0, W - 1)
    V = np.clip(np.round(uv[:, 1]).astype(np.int64)[:, None] + off, 0, H - 1)
    flat = (V[:, :, None] * W + U[:, None, :]).reshape(uv.shape[0], -1)  # row-major
    return grads.Ix.ravel()[flat], grads.Iy.ravel()[flat], U, V


def isotropic(grads: Gradients, uv: np.ndarray, window: int, min_ratio: float) -> np.ndarray:
    """``(N,)`` bool: the structure tensor of the window at ``uv`` ``(N, 2)`` has
    ``lambda_min >= min_ratio * lambda_max`` (a corner, not an edge)."""
    if uv.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    gx, gy, _, _ = _window_gradients(grads, uv, window)
    a = np.einsum("ij,ij->i", gx, gx)
    b = np.einsum("ij,ij->i", gy, gy)
    c = np.einsum("ij,ij->i", gx, gy)
    half_tr = 0.5 * (a + b)
    disc = np.sqrt(np.maximum(half_tr * half_tr - (a * b - c * c), 0.0))
    return half_tr - disc >= min_ratio * np.maximum(half_tr + disc, 1e-12)


def centre(grads: Gradients, uv: np.ndarray, window: int, iterations: int = 3) -> np.ndarray:
    """Move points to the point that Lucas-Kanade follows under a change of scale.

    Under a scaling by ``s`` about ``o``, the translation that LK finds for a window at ``p`` is
    ``(s - 1) (c - o)`` with ``c = G^-1 sum_x(g g^T x)`` (``g`` the gradient at pixel ``x`` of
    the window, ``G = sum_x(g g^T)``): LK follows ``c``, not ``p``, so a track started at
    ``p != c`` drifts by ``(s - 1) (c - p)`` at every frame while the camera approaches (or
    leaves) its surface. A track started at the fixed point ``p = c`` does not. Each iteration
    sets ``p <- c(p)`` (steps clipped to 1 px).

    Args:
        grads: the image's gradients.
        uv: ``(N, 2)`` points.
        window: LK window side (pixels).
        iterations: fixed-point iterations.

    Returns:
        ``(N, 2)`` float64 centred points.
    """
    p = np.asarray(uv, dtype=np.float64).copy()
    n = p.shape[0]
    if n == 0 or iterations <= 0:
        return p
    w = window // 2 * 2 + 1
    for _ in range(iterations):
        gx, gy, U, V = _window_gradients(grads, p, window)
        xx = np.broadcast_to((U - p[:, :1])[:, None, :], (n, w, w)).reshape(n, -1)
        yy = np.broadcast_to((V - p[:, 1:])[:, :, None], (n, w, w)).reshape(n, -1)
        a, b, c = gx * gx, gy * gy, gx * gy
        Sa, Sb, Sc = a.sum(axis=1), b.sum(axis=1), c.sum(axis=1)
        mx = np.einsum("ij,ij->i", a, xx) + np.einsum("ij,ij->i", c, yy)
        my = np.einsum("ij,ij->i", c, xx) + np.einsum("ij,ij->i", b, yy)
        det = Sa * Sb - Sc * Sc
        det = np.where(det > 1e-9 * (Sa + Sb) ** 2, det, np.inf)  # flat window: no step
        step = np.stack([(Sb * mx - Sc * my) / det, (Sa * my - Sc * mx) / det], axis=1)
        p += np.clip(step, -1.0, 1.0)
    return p


def detect_corners(
    gray: np.ndarray,
    *,
    max_corners: int,
    quality_level: float,
    min_distance: float,
    border: float,
    block_size: int = 3,
    avoid: np.ndarray | None = None,
) -> np.ndarray:
    """Shi-Tomasi corners, strongest first.

    Args:
        gray: ``(H, W)`` uint8.
        max_corners: most corners returned by OpenCV (before ``avoid``).
        quality_level: share of the strongest corner's response.
        min_distance: least distance between corners, and to the points of ``avoid``.
        border: corners stay this far inside the image.
        block_size: Shi-Tomasi neighbourhood.
        avoid: ``(M, 2)`` points (live tracks) near which no corner is returned.

    Returns:
        ``(K, 2)`` float32.
    """
    H, W = gray.shape
    b = int(math.ceil(border))
    if W <= 2 * b or H <= 2 * b:
        return np.zeros((0, 2), dtype=np.float32)
    mask = np.zeros((H, W), dtype=np.uint8)
    mask[b : H - b, b : W - b] = 255
    pts = cv2.goodFeaturesToTrack(
        gray,
        maxCorners=int(max_corners),
        qualityLevel=quality_level,
        minDistance=min_distance,
        mask=mask,
        blockSize=block_size,
    )
    if pts is None:
        return np.zeros((0, 2), dtype=np.float32)
    pts = pts.reshape(-1, 2)
    if avoid is not None and len(avoid):
        d, _ = cKDTree(avoid).query(pts, k=1, distance_upper_bound=min_distance)
        pts = pts[~np.isfinite(d)]
    return pts.astype(np.float32)


def predicted_velocity(
    tracks: TrackSet, grid: tuple[int, int], image_size: tuple[int, int]
) -> np.ndarray:
    """``(N, 2)`` each track's last displacement; new tracks (NaN) take the mean of their grid
    cell's, else the median of all, else zero (also when fewer than 3 tracks have a
    displacement: after a blank frame or a sharp turn, one survivor's jump is no prediction)."""
    vel = tracks.vel.copy()
    known = np.isfinite(vel[:, 0])
    if known.all():
        return vel
    if known.sum() < 3:
        vel[~known] = 0.0
        return vel
    cells = grid_cells(tracks.uv, grid, image_size)
    ncell = grid[0] * grid[1]
    count = np.bincount(cells[known], minlength=ncell)
    mean = (
        np.stack(
            [np.bincount(cells[known], weights=vel[known, d], minlength=ncell) for d in (0, 1)],
            axis=1,
        )
        / np.maximum(count, 1)[:, None]
    )
    fill = np.where(count[cells][:, None] > 0, mean[cells], np.median(vel[known], axis=0))
    vel[~known] = fill[~known]
    return vel


def grid_cells(uv: np.ndarray, grid: tuple[int, int], image_size: tuple[int, int]) -> np.ndarray:
    """``(N,)`` cell index (row-major) of each point of ``uv`` in a ``(columns, rows)`` grid."""
    gx, gy = grid
    W, H = image_size
    cx = np.clip((uv[:, 0] * gx / W).astype(np.int64), 0, gx - 1)
    cy = np.clip((uv[:, 1] * gy / H).astype(np.int64), 0, gy - 1)
    return cy * gx + cx


def _rank_within_cells(cells: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Rank of each active entry among the active entries of its cell (in array order);
    inactive entries get a rank beyond any quota."""
    rank = np.full(cells.size, np.iinfo(np.int64).max // 2, dtype=np.int64)
    idx = np.flatnonzero(active)
    order = np.argsort(cells[idx], kind="stable")
    sorted_cells = cells[idx][order]
    first = np.searchsorted(sorted_cells, sorted_cells, side="left")
    r = np.empty(idx.size, dtype=np.int64)
    r[order] = np.arange(idx.size) - first
    rank[idx] = r
    return rank


def grid_top_up(
    cand_cells: np.ndarray, live_cells: np.ndarray, quota: np.ndarray, room: int
) -> np.ndarray:
    """Which candidates (strongest first) become tracks: up to ``quota`` tracks per cell
    (counting the live ones), then what ``room`` is left up to ``2 * quota`` per cell.

    Args:
        cand_cells: ``(M,)`` cell of each candidate, candidates sorted strongest first.
        live_cells: ``(N,)`` cell of each live track.
        quota: ``(C,)`` tracks per cell.
        room: most candidates chosen.

    Returns:
        ``(M,)`` bool.
    """
    num_cells = quota.size
    count = np.bincount(live_cells, minlength=num_cells)
    chosen = np.zeros(cand_cells.size, dtype=bool)
    for limit in (quota[cand_cells], 2 * quota[cand_cells]):
        left = room - int(chosen.sum())
        if left <= 0:
            break
        rank = _rank_within_cells(cand_cells, ~chosen)
        ok = np.flatnonzero(~chosen & (rank + count[cand_cells] < limit))[:left]
        chosen[ok] = True
        count += np.bincount(cand_cells[ok], minlength=num_cells)
    return chosen


def neighbours(uv: np.ndarray, k: int) -> np.ndarray:
    """``(N, k)`` indices of the ``k`` nearest other points of each point (``N > k``)."""
    _, nb = cKDTree(uv).query(uv, k=k + 1)
    return nb[:, 1:]


def flow_consistent(
    uv0: np.ndarray,
    uv1: np.ndarray,
    nb: np.ndarray,
    abs_px: float,
    rel: float,
    radius: float = math.inf,
) -> np.ndarray:
    """``(N,)`` bool: each displacement ``uv1 - uv0`` lies within ``abs_px + rel * |m|`` of
    the median displacement ``m`` of its neighbours ``nb`` ``(N, k)``, or the track is
    isolated: its neighbours lie farther than ``radius`` (median distance in ``uv1``), on other
    surfaces at other depths, and tell nothing of its motion."""
    d = (uv1 - uv0).astype(np.float64)
    med = np.median(d[nb], axis=1)
    ok = np.linalg.norm(d - med, axis=1) <= abs_px + rel * np.linalg.norm(med, axis=1)
    if math.isfinite(radius):
        spread = np.median(np.linalg.norm(uv1[nb] - uv1[:, None], axis=2), axis=1)
        ok |= spread > radius
    return ok


def local_affine(uv0: np.ndarray, uv1: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """``(N, 2, 2)`` least-squares linear map ``A`` of each point's neighbourhood:
    ``uv1[j] - uv1[i] ~ A (uv0[j] - uv0[i])`` over its neighbours ``j`` in ``nb`` ``(N, k)``;
    the identity where the neighbours are (nearly) collinear. A neighbour on a nearer or farther
    surface counts too: a track next to a depth edge is as unreliable as a deformed one."""
    D0 = (uv0[nb] - uv0[:, None, :]).astype(np.float64)  # (N, k, 2)
    D1 = (uv1[nb] - uv1[:, None, :]).astype(np.float64)
    M00 = np.einsum("nki,nkj->nij", D0, D0)
    M10 = np.einsum("nki,nkj->nij", D1, D0)
    det = M00[:, 0, 0] * M00[:, 1, 1] - M00[:, 0, 1] ** 2
    good = det > 1e-6 * np.maximum(np.trace(M00, axis1=1, axis2=2), 1e-12) ** 2
    A = np.broadcast_to(np.eye(2), M00.shape).copy()
    if good.any():
        A[good] = M10[good] @ np.linalg.inv(M00[good])
    return A


class OrbDescriptors:
    """Upright ORB descriptors (256 bits) at given pixels, one pyramid level.

    The tracks follow the scale, and a camera on a vehicle hardly rolls, so upright
    single-scale descriptors are more distinctive than the rotation-invariant ones.
    """

    def __init__(self) -> None:
        self._orb = cv2.ORB_create(nlevels=1, edgeThreshold=16, patchSize=31)

    def compute(self, gray: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M, 32)`` uint8 descriptors at ``uv`` ``(M, 2)`` and ``(M,)`` bool (False within
        16 px of the border, where ORB gives none)."""
        m = uv.shape[0]
        desc = np.zeros((m, DESCRIPTOR_BYTES), dtype=np.uint8)
        has = np.zeros(m, dtype=bool)
        if m == 0:
            return desc, has
        kps = [
            cv2.KeyPoint(float(x), float(y), 31.0, 0.0, 0.0, 0, j)
            for j, (x, y) in enumerate(uv.tolist())
        ]
        kps, d = self._orb.compute(gray, kps)
        if d is not None and len(kps):
            idx = np.array([k.class_id for k in kps], dtype=np.int64)
            desc[idx] = d
            has[idx] = True
        return desc, has


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(N,)`` Hamming distances between the rows of two ``(N, 32)`` uint8 arrays."""
    return _POPCOUNT[a ^ b].sum(axis=1, dtype=np.int64)


def match_in_radius(
    uv: np.ndarray,
    desc: np.ndarray,
    cand_uv: np.ndarray,
    cand_desc: np.ndarray,
    *,
    radius: float,
    max_distance: int,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Match points to candidates within ``radius`` pixels by descriptor.

    A point takes its best candidate when the Hamming distance is at most ``max_distance`` and
    below ``ratio`` times the second best's (if any); a candidate keeps only its closest point
    (ties: the lower index).

    Args:
        uv: ``(P, 2)`` predicted pixels.
        desc: ``(P, 32)`` their descriptors.
        cand_uv: ``(C, 2)`` candidate pixels.
        cand_desc: ``(C, 32)`` their descriptors.
        radius: search radius (pixels).
        max_distance: largest Hamming distance.
        ratio: ratio test.

    Returns:
        ``(point indices (R,), candidate indices (R,))``.
    """
    empty = np.zeros(0, dtype=np.int64)
    if uv.shape[0] == 0 or cand_uv.shape[0] == 0:
        return empty, empty
    pairs = cKDTree(uv).sparse_distance_matrix(
        cKDTree(cand_uv.astype(np.float64)), radius, output_type="ndarray"
    )
    if pairs.size == 0:
        return empty, empty
    pi, cj = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    ham = hamming(desc[pi], cand_desc[cj])
    order = np.lexsort((cj, ham, pi))  # per point: best first
    pi, cj, ham = pi[order], cj[order], ham[order]
    start = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
    nxt = np.minimum(start + 1, pi.size - 1)
    second = np.where((start + 1 < pi.size) & (pi[nxt] == pi[start]), ham[nxt], 1 << 30)
    best = ham[start]
    ok = (best <= max_distance) & (best < ratio * second)
    mp, mc, mh = pi[start][ok], cj[start][ok], best[ok]
    order = np.lexsort((mp, mh))  # one point per candidate: the closest descriptor
    mp, mc = mp[order], mc[order]
    _, first = np.unique(mc, return_index=True)
    return mp[first], mc[first]
