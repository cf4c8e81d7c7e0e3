"""Relocalisation against a georeferenced image base (thesis §5.1, figs. 5.5-5.6).

Two steps:

1. **Retrieval** (§5.1.1): :class:`RetrievalIndex` holds the embeddings of the base images (from
   :func:`geoseg.models.reloc.reloc_head` or the raw layer-21 baseline
   :class:`geoseg.models.reloc.RawFeatureEmbedder`) with their georeferenced positions and
   poses, and returns each query's ``k`` nearest base images by Euclidean (L2) distance,
   optionally only among the base images within ``radius_m`` of the query's GPS position (the
   thesis's GPS window: 7.2 % -> 0.4 % wrong top-1 matches). Metrics: :func:`recall_at_k` and
   :func:`triplet_accuracy`.
2. **Absolute position** (§5.1.2, fig. 5.6): the relative-pose head predicts, for each retrieved
   base camera, the unit direction from that camera towards the query, in the base camera's
   frame. :func:`absolute_position` rotates these directions into the world frame and
   :func:`intersect_rays` returns the point closest (least squares) to the rays, robustly
   (RANSAC over ray pairs + refit on the inliers) and with a degeneracy flag for near-parallel
   ray sets. When the head also predicts the baseline (``predict_distance``), each ray carries a
   range and :func:`locate_from_ranged_rays` fuses rays and ranges by weighted least squares:
   one base image then suffices and bases collinear with the query (a straight street, where
   rays alone are degenerate) still place it. :func:`rerank_by_distance` orders retrieved
   candidates by the predicted baseline (the nearest base first); with a GPS fix,
   :func:`fuse_gps_distance` first fuses that baseline with the fix's distance to each base.

Frames (docs/architecture.md, conventions): world metric, z up; camera-to-world poses ``X_w = R_wc X_c + t_wc``; GPS
positions are in the world frame's ``(x, y)`` (projected), in metres.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from geoseg.errors import GeosegError, check_finite, check_positive, check_shape

logger = logging.getLogger(__name__)

# Below this many base embeddings a dense matrix product beats building a sklearn index.
_DENSE_MAX = 4096
# Query blocks for the dense path, to bound memory at (block, M) distances.
_QUERY_BLOCK = 1024


def _to_numpy(name: str, value: Any) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    arr = np.asarray(value)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise GeosegError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
    return arr.astype(np.float64, copy=False)


# ============================================================================ retrieval


class RetrievalIndex:
    """Nearest-neighbour index over base-image embeddings, with an optional GPS window.

    Distances are Euclidean (L2) in embedding space, as in eq. 5.1 and §5.1.1. Up to 4096 base
    images a dense matrix product is used; above, scikit-learn's ``NearestNeighbors``.

    Args:
        embeddings: ``(M, D)`` base embeddings, ``M >= 1``.
        positions: ``(M, 2)`` or ``(M, 3)`` world positions of the base images (metres); the
            GPS window uses the first two coordinates. Defaults to ``t_wc[:, :2]`` when poses
            are given; without positions the GPS window is unavailable.
        R_wc: ``(M, 3, 3)`` base camera rotations (camera-to-world), optional.
        t_wc: ``(M, 3)`` base camera centres in the world frame, optional.

    Attributes:
        embeddings: ``(M, D)`` float64.
        positions: ``(M, 2)`` float64 or None.
        R_wc, t_wc: ``(M, 3, 3)`` and ``(M, 3)`` float64 or None.
    """

    def __init__(
        self,
        embeddings: Any,
        *,
        positions: Any = None,
        R_wc: Any = None,
        t_wc: Any = None,
    ) -> None:
        emb = _to_numpy("embeddings", embeddings)
        check_shape("embeddings", emb, (None, None))
        if emb.shape[0] == 0 or emb.shape[1] == 0:
            raise GeosegError(f"embeddings: the base is empty (shape {emb.shape})")
        check_finite("embeddings", emb)
        m = emb.shape[0]
        self.embeddings = np.ascontiguousarray(emb)
        self.R_wc = self.t_wc = None
        if (R_wc is None) != (t_wc is None):
            raise GeosegError("R_wc, t_wc: give both base rotations and centres, or neither")
        if R_wc is not None:
            R = _to_numpy("R_wc", R_wc)
            t = _to_numpy("t_wc", t_wc)
            check_shape("R_wc", R, (m, 3, 3))
            check_shape("t_wc", t, (m, 3))
            check_finite("R_wc", R)
            check_finite("t_wc", t)
            self.R_wc, self.t_wc = R, t
        if positions is None and self.t_wc is not None:
            positions = self.t_wc[:, :2]
        self.positions = None
        if positions is not None:
            pos = _to_numpy("positions", positions)
            check_shape("positions", pos, (m, None))
            if pos.shape[1] not in (2, 3):
                raise GeosegError(
                    f"positions: expected shape ({m}, 2) or ({m}, 3), got {pos.shape}"
                )
            check_finite("positions", pos)
            self.positions = np.ascontiguousarray(pos[:, :2])
        self._nn = None
        if m > _DENSE_MAX:
            from sklearn.neighbors import NearestNeighbors

            self._nn = NearestNeighbors(metric="euclidean").fit(self.embeddings)
        self._sq_norms = np.einsum("md,md->m", self.embeddings, self.embeddings)
        logger.debug("retrieval index over %d embeddings of dimension %d", m, emb.shape[1])

    def __len__(self) -> int:
        return self.embeddings.shape[0]

    @property
    def dim(self) -> int:
        """Embedding dimension ``D``."""
        return int(self.embeddings.shape[1])

    def _dense_dist(self, q: np.ndarray, cols: np.ndarray | None = None) -> np.ndarray:
        """``(Q, M')`` Euclidean distances from queries ``(Q, D)`` to (a subset of) the base."""
        base = self.embeddings if cols is None else self.embeddings[cols]
        sq = self._sq_norms if cols is None else self._sq_norms[cols]
        d2 = np.einsum("qd,qd->q", q, q)[:, None] + sq[None, :] - 2.0 * q @ base.T
        return np.sqrt(np.maximum(d2, 0.0))

    def distances(self, embeddings: Any) -> np.ndarray:
        """Every query's distance to every base image (for :mod:`geoseg.reloc.route_filter`).

        Args:
            embeddings: ``(Q, D)`` query embeddings.

        Returns:
            ``(Q, M)`` Euclidean distances, float64.
        """
        q = _to_numpy("embeddings", embeddings)
        check_shape("embeddings", q, (None, self.dim))
        check_finite("embeddings", q)
        blocks = [
            self._dense_dist(q[s : s + _QUERY_BLOCK]) for s in range(0, q.shape[0], _QUERY_BLOCK)
        ]
        return np.concatenate(blocks) if blocks else np.zeros((0, len(self)))

    def query(
        self,
        embeddings: Any,
        k: int = 1,
        *,
        gps: Any = None,
        radius_m: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest base images of each query.

        Args:
            embeddings: ``(Q, D)`` query embeddings (same ``D`` as the base).
            k: number of neighbours, ``>= 1``.
            gps: ``(Q, 2)`` or ``(Q, 3)`` query positions in the world frame (metres); needed
                when ``radius_m`` is given.
            radius_m: GPS window radius; only base images whose position lies within
                ``radius_m`` (horizontal distance, inclusive) of the query's GPS are candidates.

        Returns:
            ``(indices (Q, k) int64, distances (Q, k) float64)`` sorted by increasing distance.
            When a query has fewer than ``k`` candidates (small base, or few base images in its
            GPS window), the missing slots hold index ``-1`` and distance ``+inf``.
        """
        q = _to_numpy("embeddings", embeddings)
        check_shape("embeddings", q, (None, self.dim))
        check_finite("embeddings", q)
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise GeosegError(f"k: expected an int >= 1, got {k!r}")
        k = int(k)
        n_q = q.shape[0]
        idx = np.full((n_q, k), -1, dtype=np.int64)
        dist = np.full((n_q, k), np.inf)
        if n_q == 0:
            return idx, dist
        if radius_m is None:
            if gps is not None:
                logger.debug("gps given without radius_m: the GPS window is not applied")
            kk = min(k, len(self))
            if self._nn is not None:
                d, i = self._nn.kneighbors(q, n_neighbors=kk)
                idx[:, :kk], dist[:, :kk] = i, d
            else:
                for s in range(0, n_q, _QUERY_BLOCK):
                    dd = self._dense_dist(q[s : s + _QUERY_BLOCK])
                    part = np.argpartition(dd, kk - 1, axis=1)[:, :kk] if kk < dd.shape[1] else None
                    cand = (
                        np.broadcast_to(np.arange(dd.shape[1]), dd.shape) if part is None else part
                    )
                    cd = np.take_along_axis(dd, cand, axis=1)
                    order = np.argsort(cd, axis=1, kind="stable")
                    idx[s : s + _QUERY_BLOCK, :kk] = np.take_along_axis(cand, order, axis=1)
                    dist[s : s + _QUERY_BLOCK, :kk] = np.take_along_axis(cd, order, axis=1)
            return idx, dist
        check_positive("radius_m", radius_m)
        if gps is None:
            raise GeosegError("gps: required when radius_m (the GPS window) is given")
        if self.positions is None:
            raise GeosegError(
                "positions: this index has no base positions; the GPS window needs positions= "
                "or R_wc=/t_wc= at construction"
            )
        g = _to_numpy("gps", gps)
        check_shape("gps", g, (n_q, None))
        if g.shape[1] not in (2, 3):
            raise GeosegError(f"gps: expected shape ({n_q}, 2) or ({n_q}, 3), got {g.shape}")
        check_finite("gps", g)
        from scipy.spatial import cKDTree

        tree = cKDTree(self.positions)
        cands = tree.query_ball_point(g[:, :2], r=float(radius_m))
        for j, c in enumerate(cands):
            if not c:
                continue
            cols = np.asarray(sorted(c), dtype=np.int64)
            dd = self._dense_dist(q[j : j + 1], cols)[0]
            order = np.argsort(dd, kind="stable")[:k]
            idx[j, : order.size] = cols[order]
            dist[j, : order.size] = dd[order]
        return idx, dist


def recall_at_k(ranked: Any, truth_sets: Sequence[Any], k: int | None = None) -> float:
    """Fraction of queries with at least one correct base image among their first ``k``.

    Args:
        ranked: ``(Q, K)`` base indices per query, best first (``-1`` = padding, never correct).
        truth_sets: ``Q`` collections of correct base indices (an int, a set, a list or an
            array each); each must be non-empty.
        k: cut-off, ``1 <= k <= K``; ``K`` when None.

    Returns:
        Recall@k in ``[0, 1]``.
    """
    r = np.asarray(ranked)
    check_shape("ranked", r, (None, None))
    if not np.issubdtype(r.dtype, np.integer):
        raise GeosegError(f"ranked: expected integer indices, got dtype {r.dtype}")
    if len(truth_sets) != r.shape[0]:
        raise GeosegError(f"truth_sets: expected {r.shape[0]} entries, got {len(truth_sets)}")
    if r.shape[0] == 0:
        raise GeosegError("ranked: no queries")
    kk = r.shape[1] if k is None else k
    if isinstance(kk, bool) or not isinstance(kk, int | np.integer) or not 1 <= kk <= r.shape[1]:
        raise GeosegError(f"k: expected an int in [1, {r.shape[1]}], got {k!r}")
    hits = 0
    for j, truth in enumerate(truth_sets):
        if isinstance(truth, set | frozenset | list | tuple):
            t = {int(x) for x in truth}
        elif np.ndim(truth) == 0:
            t = {int(truth)}
        else:
            t = {int(x) for x in np.asarray(truth).ravel()}
        if not t:
            raise GeosegError(f"truth_sets[{j}]: empty; every query needs a correct base image")
        hits += any(int(x) in t for x in r[j, :kk] if x >= 0)
    return hits / r.shape[0]


def evaluate_retrieval(
    index: RetrievalIndex,
    queries: Any,
    truth_sets: Sequence[Any],
    *,
    ks: Sequence[int] = (1, 3, 5),
    gps: Any = None,
    radius_m: float | None = None,
) -> dict[str, float]:
    """Recall@k for several ``k`` in one query (the §5.1.1 figures).

    Args:
        index: the base.
        queries: ``(Q, D)`` query embeddings.
        truth_sets: ``Q`` collections of correct base indices (see :func:`recall_at_k`).
        ks: cut-offs.
        gps: ``(Q, 2)`` query positions, with ``radius_m`` for the GPS window.
        radius_m: GPS window radius in metres (None: whole base).

    Returns:
        ``{"recall@1": ..., "recall@3": ..., ...}``.
    """
    if not ks:
        raise GeosegError("ks: expected at least one cut-off")
    ranked, _ = index.query(queries, k=max(int(k) for k in ks), gps=gps, radius_m=radius_m)
    return {f"recall@{int(k)}": recall_at_k(ranked, truth_sets, k=int(k)) for k in ks}


def triplet_accuracy(ref: Any, match: Any, other: Any) -> float:
    """Fraction of triplets with ``d(ref, match) < d(ref, other)`` (L2), as in §5.1.1.

    Args:
        ref, match, other: ``(B, D)`` embeddings (NumPy arrays or torch tensors).

    Returns:
        Accuracy in ``[0, 1]``.
    """
    a = _to_numpy("ref", ref)
    check_shape("ref", a, (None, None))
    if a.shape[0] == 0:
        raise GeosegError("ref: no triplets")
    p = _to_numpy("match", match)
    n = _to_numpy("other", other)
    check_shape("match", p, a.shape)
    check_shape("other", n, a.shape)
    for name, v in (("ref", a), ("match", p), ("other", n)):
        check_finite(name, v)
    d_pos = np.linalg.norm(a - p, axis=1)
    d_neg = np.linalg.norm(a - n, axis=1)
    return float(np.mean(d_pos < d_neg))


# ============================================================================ rays


@dataclass(frozen=True)
class RayIntersection:
    """The point closest to a set of rays.

    Attributes:
        point: ``(3,)`` least-squares point (refit on the inliers); all NaN when ``degenerate``.
        residuals: ``(N,)`` distance (metres) of ``point`` to each ray's line; NaN when
            degenerate.
        inliers: ``(N,)`` bool, the rays used for the final fit.
        degenerate: True when the inlier rays are (nearly) parallel or fewer than 2, i.e. the
            point is not determined; ``point`` is then NaN rather than a meaningless value.
        condition: ``lambda_max / lambda_min`` of the normal matrix ``sum (I - d d^T)`` over
            the inliers (``inf`` when singular).
        min_eigenvalue: ``lambda_min / n_inliers`` in ``[0, 1]``; for two rays at angle
            ``theta`` it is ``sin^2(theta / 2)``.
    """

    point: np.ndarray
    residuals: np.ndarray
    inliers: np.ndarray
    degenerate: bool
    condition: float
    min_eigenvalue: float


def _normal_equations(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A = sum (I - d d^T)`` ``(3, 3)`` and ``b = sum (I - d d^T) o`` ``(3,)``."""
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    return proj.sum(axis=0), np.einsum("nij,nj->i", proj, o)


def _line_distances(p: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``(N,)`` distances from ``p`` ``(3,)`` to the lines ``o + s d`` (``d`` unit)."""
    v = p[None, :] - o
    return np.linalg.norm(v - np.einsum("ni,ni->n", v, d)[:, None] * d, axis=1)


def _solve(o: np.ndarray, d: np.ndarray, min_eig: float) -> tuple[np.ndarray, float, float, bool]:
    if d.shape[0] < 2:
        return np.full(3, np.nan), np.inf, 0.0, True
    a, b = _normal_equations(o, d)
    w = np.linalg.eigvalsh(a)
    lam_min = max(float(w[0]), 0.0) / d.shape[0]
    cond = float(w[-1] / w[0]) if w[0] > 0 else np.inf
    degenerate = d.shape[0] < 2 or lam_min < min_eig
    if degenerate:
        return np.full(3, np.nan), cond, lam_min, True
    return np.linalg.solve(a, b), cond, lam_min, False


def _angular_errors(p: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Angle (radians) between each ray direction and the direction from its origin to ``p``."""
    v = p[None, :] - o
    norm = np.linalg.norm(v, axis=1)
    cos = np.einsum("ni,ni->n", v, d) / np.maximum(norm, 1e-300)
    ang = np.arccos(np.clip(cos, -1.0, 1.0))
    return np.where(norm > 0, ang, 0.0)


def intersect_rays(
    origins: Any,
    directions: Any,
    *,
    robust: bool = True,
    inlier_angle_deg: float = 2.0,
    min_eigenvalue: float = 1e-4,
    max_pairs: int = 500,
    seed: int = 0,
) -> RayIntersection:
    """Least-squares point closest to ``N`` rays, optionally robust (RANSAC over pairs).

    The point minimises ``sum_n |(I - d_n d_n^T)(p - o_n)|^2``, i.e. solves
    ``(sum P_n) p = sum P_n o_n`` with ``P_n = I - d_n d_n^T``.

    Robust mode: each pair of rays proposes the point closest to both; a ray is an inlier of a
    proposal when the angle between its direction and the direction from its origin to the
    point is below ``inlier_angle_deg`` (a ray is a half-line: a point behind it is an
    outlier). The proposal with most inliers (ties: smallest summed angle) wins, then the point
    is refit by least squares on its inliers, and inliers are re-evaluated once and refit. All
    pairs are tried when there are at most ``max_pairs`` of them, else ``max_pairs`` random
    pairs (``numpy.random.default_rng(seed)``).

    Degeneracy: the normal matrix of ``n`` unit rays has eigenvalues in ``[0, n]``; the set is
    flagged degenerate when ``lambda_min / n < min_eigenvalue`` (default ``1e-4``: two rays
    closer than ~1.15 degrees to parallel, where a 0.1 degree direction error already moves the
    point by ~10 % of the range), or when fewer than 2 rays are inliers (robust mode, e.g. two
    rays that only meet behind their origins).

    Args:
        origins: ``(N, 3)`` ray origins (world frame), ``N >= 2``.
        directions: ``(N, 3)`` ray directions (normalised here; zero vectors are rejected).
        robust: RANSAC + refit when True, plain least squares on all rays when False.
        inlier_angle_deg: RANSAC inlier threshold on the angular error, degrees.
        min_eigenvalue: degeneracy threshold on ``lambda_min / n`` (see above).
        max_pairs: cap on the number of RANSAC pair proposals.
        seed: seed of the pair sampling (only used when pairs are sampled).

    Returns:
        :class:`RayIntersection`.
    """
    o = _to_numpy("origins", origins)
    d = _to_numpy("directions", directions)
    check_shape("origins", o, (None, 3))
    check_shape("directions", d, (o.shape[0], 3))
    check_finite("origins", o)
    check_finite("directions", d)
    n = o.shape[0]
    if n < 2:
        raise GeosegError(f"origins: at least 2 rays are needed, got {n}")
    norms = np.linalg.norm(d, axis=1)
    if (norms < 1e-12).any():
        raise GeosegError("directions: zero-length direction vector")
    check_positive("inlier_angle_deg", inlier_angle_deg)
    check_positive("min_eigenvalue", min_eigenvalue, strict=False)
    d = d / norms[:, None]
    inliers = np.ones(n, dtype=bool)
    if robust and n > 2:
        thr = np.deg2rad(inlier_angle_deg)
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
        if len(pairs) > max_pairs:
            rng = np.random.default_rng(seed)
            pairs = [pairs[i] for i in rng.choice(len(pairs), size=max_pairs, replace=False)]
        best: tuple[int, float] | None = None
        for i, j in pairs:
            p, _, _, deg = _solve(o[[i, j]], d[[i, j]], min_eigenvalue)
            if deg:
                continue
            ang = _angular_errors(p, o, d)
            inl = ang < thr
            key = (int(inl.sum()), -float(np.minimum(ang, thr).sum()))
            if best is None or key > best:
                best, inliers = key, inl
        if best is None:
            inliers = np.ones(n, dtype=bool)  # every pair is parallel: report degenerate below
        else:
            for _ in range(2):
                p, _, _, deg = _solve(o[inliers], d[inliers], min_eigenvalue)
                if deg:
                    break
                new = _angular_errors(p, o, d) < thr
                if new.sum() < 2 or np.array_equal(new, inliers):
                    break
                inliers = new
    if robust and inliers.sum() >= 2:
        # rays are half-lines: the inliers must see the point in front, within the threshold
        p, _, _, deg = _solve(o[inliers], d[inliers], min_eigenvalue)
        if not deg:
            inliers = inliers & (_angular_errors(p, o, d) < np.deg2rad(inlier_angle_deg))
    point, cond, lam_min, degenerate = _solve(o[inliers], d[inliers], min_eigenvalue)
    if not degenerate and not np.isfinite(point).all():  # overflow: report it, never a NaN point
        point, degenerate = np.full(3, np.nan), True
    if degenerate:
        logger.debug("degenerate ray set: lambda_min/n = %.3g, %d inliers", lam_min, inliers.sum())
        residuals = np.full(n, np.nan)
    else:
        residuals = _line_distances(point, o, d)
    return RayIntersection(
        point=point,
        residuals=residuals,
        inliers=inliers,
        degenerate=bool(degenerate),
        condition=cond,
        min_eigenvalue=lam_min,
    )


def absolute_position(
    base_R_wc: Any,
    base_t_wc: Any,
    directions_in_base_camera: Any,
    distances: Any = None,
    **kwargs: Any,
) -> RayIntersection:
    """Absolute position of a query from ``N >= 2`` georeferenced base cameras (fig. 5.6).

    Each base camera ``n`` casts a ray from its centre ``t_wc[n]`` along
    ``R_wc[n] @ dir[n]``, where ``dir[n]`` is the unit direction from base camera ``n`` towards
    the query expressed in base camera ``n``'s frame (the ``direction`` output of the
    relative-pose head for the pair (base, query), or ``t_dir_ab`` of
    :func:`geoseg.models.relpose.relative_pose_labels` with ``a`` = base, ``b`` = query).

    With ``distances`` (the head's predicted baselines) the rays are ranged and
    :func:`locate_from_ranged_rays` places the query, from ``N >= 1`` base cameras.

    Args:
        base_R_wc: ``(N, 3, 3)`` base camera-to-world rotations.
        base_t_wc: ``(N, 3)`` base camera centres in the world frame.
        directions_in_base_camera: ``(N, 3)`` directions base -> query, base camera frame.
        distances: ``(N,)`` baselines base -> query in metres, or None (rays only).
        **kwargs: forwarded to :func:`intersect_rays` (``robust``, ``inlier_angle_deg``, ...)
            or, with ``distances``, to :func:`locate_from_ranged_rays` (``angle_sigma_deg``,
            ``range_sigma``, ...).

    Returns:
        :class:`RayIntersection` with ``point`` the query's camera centre in the world frame.
    """
    R = _to_numpy("base_R_wc", base_R_wc)
    t = _to_numpy("base_t_wc", base_t_wc)
    dc = _to_numpy("directions_in_base_camera", directions_in_base_camera)
    check_shape("base_R_wc", R, (None, 3, 3))
    n = R.shape[0]
    check_shape("base_t_wc", t, (n, 3))
    check_shape("directions_in_base_camera", dc, (n, 3))
    check_finite("base_R_wc", R)
    dw = np.einsum("nij,nj->ni", R, dc)
    if distances is not None:
        return locate_from_ranged_rays(t, dw, distances, **kwargs)
    return intersect_rays(t, dw, **kwargs)


# ============================================================================ ranged rays


def _ranged_information(
    d: np.ndarray, r: np.ndarray, angle_sigma: float, range_sigma: float
) -> np.ndarray:
    """``(N, 3, 3)`` information matrices of the points ``o + r d``: across the ray
    ``(I - d d^T) / (r sigma_angle)^2``, along it ``d d^T / (r sigma_range)^2``."""
    along = d[:, :, None] * d[:, None, :]
    proj = np.eye(3)[None] - along
    return (
        proj / (r * angle_sigma)[:, None, None] ** 2 + along / (r * range_sigma)[:, None, None] ** 2
    )


def _ranged_chi2(
    p: np.ndarray,
    o: np.ndarray,
    d: np.ndarray,
    r: np.ndarray,
    angle_sigma: float,
    range_sigma: float,
) -> np.ndarray:
    """``(N,)`` normalised squared errors of ``p`` against each ranged ray: angle between the ray
    and ``p - o`` over ``sigma_angle``, log range ratio over ``sigma_range``."""
    v = p[None, :] - o
    dist = np.linalg.norm(v, axis=1)
    ang = _angular_errors(p, o, d)
    log_ratio = np.log(np.maximum(dist, 1e-9) / r)
    return (ang / angle_sigma) ** 2 + (log_ratio / range_sigma) ** 2


def locate_from_ranged_rays(
    origins: Any,
    directions: Any,
    ranges: Any,
    *,
    angle_sigma_deg: float = 3.0,
    range_sigma: float = 0.25,
    robust: bool = True,
    inlier_chi2: float = 9.0,
) -> RayIntersection:
    """The point seen from ``N >= 1`` origins along given directions at given ranges.

    Each ranged ray proposes the point ``q_n = o_n + r_n d_n`` with an anisotropic Gaussian error:
    across the ray ``r_n sigma_angle`` (an angular error grows with the range), along it
    ``r_n sigma_range`` (a relative range error). The estimate is the weighted least-squares
    point ``(sum A_n)^-1 sum A_n q_n`` with ``A_n = P_n / (r_n sigma_angle)^2 +
    d_n d_n^T / (r_n sigma_range)^2``, ``P_n = I - d_n d_n^T``: where rays cross, their
    directions fix the point (the ray intersection of :func:`intersect_rays`, range-weighted);
    along near-parallel rays the ranges fix it, so there is no degenerate configuration.

    Robust mode (``N > 1``): each ``q_n`` is a hypothesis; a ray is its inlier when its angular
    and log-range errors (over their sigmas) have a squared sum below ``inlier_chi2``; the
    hypothesis with most inliers (ties: smallest summed, capped error) wins and the point is
    refit on its inliers, re-evaluated once and refit.

    Args:
        origins: ``(N, 3)`` ray origins (world frame).
        directions: ``(N, 3)`` directions (normalised here).
        ranges: ``(N,)`` distances from each origin to the point, metres, > 0.
        angle_sigma_deg: standard deviation of the direction error, degrees, > 0.
        range_sigma: standard deviation of ``log(range)`` (~ the relative range error), > 0.
        robust: hypothesise-and-verify + refit when True; all rays when False.
        inlier_chi2: inlier threshold on the normalised squared error (9: 3 sigma in one term).

    Returns:
        :class:`RayIntersection`; ``degenerate`` is always False, ``residuals`` are the
        distances of the point to each ray's line, ``condition`` and ``min_eigenvalue`` those of
        the information matrix ``sum A_n`` (``min_eigenvalue`` in m^-2, not normalised).

    Raises:
        GeosegError: mismatched shapes, no ray, zero directions, ranges <= 0, bad sigmas.
    """
    o = _to_numpy("origins", origins)
    d = _to_numpy("directions", directions)
    r = _to_numpy("ranges", ranges)
    check_shape("origins", o, (None, 3))
    n = o.shape[0]
    if n < 1:
        raise GeosegError("origins: at least 1 ranged ray is needed, got 0")
    check_shape("directions", d, (n, 3))
    check_shape("ranges", r, (n,))
    for name, v in (("origins", o), ("directions", d), ("ranges", r)):
        check_finite(name, v)
    if (r <= 0).any():
        raise GeosegError("ranges: expected distances > 0 m")
    norms = np.linalg.norm(d, axis=1)
    if (norms < 1e-12).any():
        raise GeosegError("directions: zero-length direction vector")
    check_positive("angle_sigma_deg", angle_sigma_deg)
    check_positive("range_sigma", range_sigma)
    check_positive("inlier_chi2", inlier_chi2)
    d = d / norms[:, None]
    sig_a = float(np.deg2rad(angle_sigma_deg))
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        info = _ranged_information(d, r, sig_a, range_sigma)
        q = o + r[:, None] * d
    if not (np.isfinite(info).all() and np.isfinite(q).all()):
        raise GeosegError(
            "origins, ranges: the ranged-ray fit is not finite (ranges or coordinates far "
            f"outside metres-scale values: ranges {r.min():.3g}..{r.max():.3g} m)"
        )

    def fit(mask: np.ndarray) -> np.ndarray:
        a = info[mask].sum(axis=0)
        return np.linalg.solve(a, np.einsum("nij,nj->i", info[mask], q[mask]))

    inliers = np.ones(n, dtype=bool)
    if robust and n > 1:
        best: tuple[int, float] | None = None
        for k in range(n):
            chi2 = _ranged_chi2(q[k], o, d, r, sig_a, range_sigma)
            inl = chi2 < inlier_chi2
            key = (int(inl.sum()), -float(np.minimum(chi2, inlier_chi2).sum()))
            if best is None or key > best:
                best, inliers = key, inl
        for _ in range(2):
            new = _ranged_chi2(fit(inliers), o, d, r, sig_a, range_sigma) < inlier_chi2
            if not new.any() or np.array_equal(new, inliers):
                break
            inliers = new
    point = fit(inliers)
    w = np.linalg.eigvalsh(info[inliers].sum(axis=0))
    if not (np.isfinite(point).all() and np.isfinite(w).all()):
        raise GeosegError(
            "origins, ranges: the ranged-ray fit is not finite (ranges or coordinates far "
            "outside metres-scale values?)"
        )
    return RayIntersection(
        point=point,
        residuals=_line_distances(point, o, d),
        inliers=inliers,
        degenerate=False,
        condition=float(w[-1] / w[0]),
        min_eigenvalue=float(w[0]),
    )


def rerank_by_distance(
    ranked: Any,
    distances: Any,
    *,
    appearance: Any | None = None,
    appearance_weight: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reorder each query's retrieved candidates by the predicted baseline, nearest first.

    Retrieval ranks base images by appearance; on a street of regularly spaced base images the
    two neighbours of a query look alike and the farther one can win. The relative-pose head's
    distance output tells which of them is nearer. Where the head nearly ties (the base 3 m
    behind the query against the one 9 m ahead), the appearance distance is independent
    evidence: with ``appearance_weight`` ``w > 0`` the order is by
    ``log(distance) + w * appearance`` (a log so that the weight means the same at 3 m and at
    20 m: the head's error is relative).

    Args:
        ranked: ``(Q, K)`` base indices per query, best first (``-1`` = padding).
        distances: ``(Q, K)`` predicted baselines (metres) query <-> candidate; ignored at
            padding slots.
        appearance: ``(Q, K)`` retrieval distances of the same candidates (embedding space,
            :meth:`RetrievalIndex.query`); needed when ``appearance_weight > 0``.
        appearance_weight: ``w >= 0``, log-distance units per unit of appearance distance.

    Returns:
        ``(ranked (Q, K) int64, distances (Q, K) float64, order (Q, K) int64)``: sorted by the
        key above per query (stable: ties keep the appearance order), padding last; ``order``
        is the permutation (``ranked_out = take(ranked, order)``), to reorder anything else
        held per candidate.
    """
    idx = np.asarray(ranked)
    check_shape("ranked", idx, (None, None))
    if not np.issubdtype(idx.dtype, np.integer):
        raise GeosegError(f"ranked: expected integer indices, got dtype {idx.dtype}")
    dist = _to_numpy("distances", distances)
    check_shape("distances", dist, idx.shape)
    valid = idx >= 0
    if not np.isfinite(dist[valid]).all():
        raise GeosegError("distances: NaN or inf at a candidate slot")
    check_positive("appearance_weight", appearance_weight, strict=False)
    key = np.where(valid, dist, np.inf)
    if appearance_weight > 0:
        if appearance is None:
            raise GeosegError("appearance: required with appearance_weight > 0")
        app = _to_numpy("appearance", appearance)
        check_shape("appearance", app, idx.shape)
        if not np.isfinite(app[valid]).all():
            raise GeosegError("appearance: NaN or inf at a candidate slot")
        if (dist[valid] <= 0).any():
            raise GeosegError("distances: expected > 0 m with appearance_weight > 0 (a log)")
        with np.errstate(divide="ignore", invalid="ignore"):
            key = np.where(valid, np.log(key) + appearance_weight * app, np.inf)
    order = np.argsort(key, axis=1, kind="stable")
    return (
        np.take_along_axis(idx, order, axis=1).astype(np.int64),
        np.take_along_axis(np.where(valid, dist, np.inf), order, axis=1),
        order.astype(np.int64),
    )


def fuse_gps_distance(
    predicted_m: Any, gps_m: Any, *, relative_sigma: float, gps_sigma_m: float
) -> np.ndarray:
    """Fuse the head's predicted baseline with the GPS fix's distance to each candidate.

    Two independent readings of the same query-candidate distance: the relative-pose head's
    ``d`` (its error grows with the distance: standard deviation ``relative_sigma * d``) and
    ``|p_candidate - p_gps|`` (standard deviation ``gps_sigma_m``). Their inverse-variance
    mean is what :func:`rerank_by_distance` should sort by when the query has a GPS fix: the
    GPS alone cannot separate two neighbours ~9 m apart, but it breaks the head's near-ties
    between a base 3 m behind the query and one 9 m ahead of it.

    Args:
        predicted_m: ``(...)`` predicted baselines, metres (> 0).
        gps_m: ``(...)`` horizontal distances candidate <-> GPS fix, metres (same shape;
            ``inf`` allowed: padding).
        relative_sigma: the head's relative distance error (> 0).
        gps_sigma_m: the GPS fix's standard deviation per axis, metres (> 0).

    Returns:
        ``(...)`` fused distances, metres.
    """
    d = _to_numpy("predicted_m", predicted_m)
    g = _to_numpy("gps_m", gps_m)
    check_shape("gps_m", g, d.shape)
    check_positive("relative_sigma", relative_sigma)
    check_positive("gps_sigma_m", gps_sigma_m)
    if np.any(d <= 0) or np.isnan(d).any() or np.isnan(g).any() or (g < 0).any():
        raise GeosegError("predicted_m, gps_m: expected positive distances, no NaN")
    # the inverse-variance mean written with variances, (v_gps d + v_head g) / (v_head + v_gps):
    # no 1 / 0 when a variance underflows, no inf / inf when one overflows
    with np.errstate(over="ignore", invalid="ignore"):
        v_head = np.square(relative_sigma * d)
        v_gps = np.square(float(gps_sigma_m))
        total = v_head + v_gps
        safe = np.where((total > 0) & np.isfinite(total), total, 1.0)
        w_g = np.where(total > 0, v_head / safe, 0.5)  # the GPS reading's weight
        w_d = np.where(total > 0, v_gps / safe, 0.5)
        w_g, w_d = np.where(np.isfinite(v_head), w_g, 1.0), np.where(np.isfinite(v_head), w_d, 0.0)
        fused = w_d * d + w_g * g
    return np.where(np.isfinite(d) & np.isfinite(g) & np.isfinite(fused), fused, np.inf)
