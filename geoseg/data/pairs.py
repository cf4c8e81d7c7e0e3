"""Positives, triplets and relative-pose pairs mined from camera poses (thesis §5.1, eq. 5.1/5.2).

Everything here works on plain pose arrays, independently of the renderer: a *traversal* is a
pair ``(R_wc (N, 3, 3), t_wc (N, 3))`` of camera-to-world poses (``X_w = R_wc X_c + t_wc``,
OpenCV camera frame, so the viewing direction is ``R_wc[:, :, 2]``), or a :class:`Traversal`.

Two images show *the same place* when their camera centres are within ``max_distance_m``
(Euclidean, metres) **and** their optical axes are within ``max_angle_deg`` of each other.

* :func:`positive_mask` / :func:`truth_sets`: the ``(Q, M)`` same-place relation between a query
  traversal and a database traversal, and the per-query sets that
  :func:`geoseg.reloc.retrieval.recall_at_k` expects.
* :func:`sample_triplets`: ``(ref, match, other)`` index triplets for eq. 5.1: ``ref`` from the
  query traversal, ``match`` a database positive, ``other`` a database image at least
  ``min_negative_distance_m`` away (uniformly, or among the closest in embedding space: hard
  negatives).
* :func:`sample_relpose_pairs`: index pairs with a baseline in a range and overlapping views,
  with their :func:`geoseg.models.relpose.relative_pose_labels` targets (eq. 5.2).
* :class:`TripletDataset` / :class:`RelPosePairDataset`: torch datasets over precomputed
  layer-21 features ``(N, C, h, w)`` or over any items (images, paths) with a feature-extractor
  callable.

Sampling is deterministic given the seed (``numpy.random.default_rng(seed)``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from geoseg.errors import GeosegError, check_finite, check_positive, check_shape
from geoseg.models.relpose import relative_pose_labels

logger = logging.getLogger(__name__)

__all__ = [
    "NoEligiblePairError",
    "RelPosePairDataset",
    "RelPosePairs",
    "Traversal",
    "TripletDataset",
    "positive_mask",
    "sample_relpose_pairs",
    "sample_triplets",
    "truth_sets",
]


# ============================================================================ poses


@dataclass(frozen=True)
class Traversal:
    """Camera poses of one traversal.

    Attributes:
        R_wc: ``(N, 3, 3)`` float64 camera-to-world rotations.
        t_wc: ``(N, 3)`` float64 camera centres in the world frame (metres).
    """

    R_wc: np.ndarray
    t_wc: np.ndarray

    def __len__(self) -> int:
        return int(self.t_wc.shape[0])

    @property
    def axes(self) -> np.ndarray:
        """``(N, 3)`` unit optical axes (camera ``+z``) in the world frame."""
        return self.R_wc[:, :, 2]


def as_traversal(name: str, value: Any) -> Traversal:
    """Validate a :class:`Traversal` or an ``(R_wc (N, 3, 3), t_wc (N, 3))`` pair.

    Raises:
        GeosegError: naming ``name``: wrong shapes, NaN, or an empty traversal.
    """
    if isinstance(value, Traversal):
        R, t = value.R_wc, value.t_wc
    else:
        try:
            R, t = value
        except (TypeError, ValueError):
            raise GeosegError(
                f"{name}: expected a Traversal or a pair (R_wc (N, 3, 3), t_wc (N, 3))"
            ) from None
    R = np.asarray(R.detach().cpu() if hasattr(R, "detach") else R, dtype=np.float64)
    t = np.asarray(t.detach().cpu() if hasattr(t, "detach") else t, dtype=np.float64)
    check_shape(f"{name}.R_wc", R, (None, 3, 3))
    check_shape(f"{name}.t_wc", t, (R.shape[0], 3))
    if R.shape[0] == 0:
        raise GeosegError(f"{name}: empty traversal (no poses)")
    check_finite(f"{name}.R_wc", R)
    check_finite(f"{name}.t_wc", t)
    return Traversal(R, t)


def _rng(seed: int | np.random.Generator) -> np.random.Generator:
    if isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise GeosegError(f"rng: expected an int seed or a numpy Generator, got {seed!r}")
    return np.random.default_rng(int(seed))


def _check_count(name: str, n: Any) -> int:
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise GeosegError(f"{name}: expected an int >= 1, got {n!r}")
    return int(n)


def _distances(db: Traversal, query: Traversal) -> np.ndarray:
    """``(Q, M)`` Euclidean distances between query and database camera centres."""
    from scipy.spatial.distance import cdist

    return cdist(query.t_wc, db.t_wc)


def _axis_angles_deg(db: Traversal, query: Traversal) -> np.ndarray:
    """``(Q, M)`` angles (degrees) between query and database optical axes."""
    cos = np.clip(query.axes @ db.axes.T, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def positive_mask(
    db: Any,
    query: Any,
    *,
    max_distance_m: float = 5.0,
    max_angle_deg: float = 30.0,
) -> np.ndarray:
    """Same-place relation between query and database images.

    ``mask[q, m]`` is True when ``|t_wc_q - t_wc_m| <= max_distance_m`` and the angle between
    the two optical axes is ``<= max_angle_deg``.

    Args:
        db: database traversal, ``M`` poses (:class:`Traversal` or ``(R_wc, t_wc)``).
        query: query traversal, ``Q`` poses.
        max_distance_m: distance threshold between camera centres (metres), > 0.
        max_angle_deg: threshold on the angle between viewing directions (degrees), > 0.

    Returns:
        ``(Q, M)`` bool.
    """
    dbt, qt = as_traversal("db", db), as_traversal("query", query)
    check_positive("max_distance_m", max_distance_m)
    check_positive("max_angle_deg", max_angle_deg)
    return (_distances(dbt, qt) <= max_distance_m) & (_axis_angles_deg(dbt, qt) <= max_angle_deg)


def truth_sets(
    db: Any,
    query: Any,
    *,
    max_distance_m: float = 5.0,
    max_angle_deg: float = 30.0,
) -> list[np.ndarray]:
    """Per query, the database indices of the same place (the ground truth of Recall@k).

    Args:
        db, query, max_distance_m, max_angle_deg: as in :func:`positive_mask`.

    Returns:
        ``Q`` int64 arrays of database indices, sorted by increasing camera distance. A query
        with no database image of the same place gets an empty array; drop such queries before
        :func:`geoseg.reloc.retrieval.recall_at_k`, which rejects empty sets
        (``keep = [len(t) > 0 for t in sets]``).
    """
    mask = positive_mask(db, query, max_distance_m=max_distance_m, max_angle_deg=max_angle_deg)
    dist = _distances(as_traversal("db", db), as_traversal("query", query))
    out = []
    for q in range(mask.shape[0]):
        cols = np.flatnonzero(mask[q])
        out.append(cols[np.argsort(dist[q, cols], kind="stable")].astype(np.int64))
    n_empty = sum(t.size == 0 for t in out)
    if n_empty:
        logger.debug("%d of %d queries have no positive in the database", n_empty, len(out))
    return out


# ============================================================================ triplets


def sample_triplets(
    db: Any,
    query: Any,
    n: int,
    *,
    rng: int | np.random.Generator = 0,
    max_distance_m: float = 5.0,
    max_angle_deg: float = 30.0,
    min_negative_distance_m: float = 25.0,
    hard_negatives: Any = None,
    hard_k: int = 10,
    exclude_same_index: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample ``n`` triplets ``(ref, match, other)`` for eq. 5.1.

    ``ref`` indexes the query traversal; ``match`` and ``other`` index the database. Each ref is
    drawn uniformly among the queries that have at least one positive and one negative (with
    replacement), ``match`` uniformly among its positives (:func:`positive_mask`), ``other``
    among the database images whose camera centre is farther than ``min_negative_distance_m``
    from the ref's (so never a positive, whatever the viewing angles). With
    ``hard_negatives`` (embedding distances), ``other`` is drawn uniformly among the
    ``hard_k`` valid negatives closest to the ref in embedding space.

    Args:
        db: database traversal (``M`` poses).
        query: query traversal (``Q`` poses); pass the same traversal as ``db`` with
            ``exclude_same_index=True`` to mine triplets within one traversal.
        n: number of triplets, >= 1.
        rng: seed or ``numpy.random.Generator``.
        max_distance_m, max_angle_deg: positive thresholds (:func:`positive_mask`).
        min_negative_distance_m: minimum camera distance of a negative (metres), must be
            ``>= max_distance_m``.
        hard_negatives: ``(Q, M)`` embedding distances between queries and database images
            (e.g. from the current network), or None for uniform negatives.
        hard_k: size of the hard-negative pool per ref, >= 1.
        exclude_same_index: never use ``match == ref`` (same traversal as db and query).

    Returns:
        ``(ref_idx, match_idx, other_idx)``, three ``(n,)`` int64 arrays.

    Raises:
        GeosegError: bad thresholds or shapes, or no query with both a positive and a negative.
    """
    dbt, qt = as_traversal("db", db), as_traversal("query", query)
    n = _check_count("n", n)
    hard_k = _check_count("hard_k", hard_k)
    check_positive("min_negative_distance_m", min_negative_distance_m)
    if min_negative_distance_m < max_distance_m:
        raise GeosegError(
            f"min_negative_distance_m: expected >= max_distance_m ({max_distance_m}), "
            f"got {min_negative_distance_m}"
        )
    if exclude_same_index and len(dbt) != len(qt):
        raise GeosegError(
            f"exclude_same_index: db and query must have the same length, got {len(dbt)} and "
            f"{len(qt)}"
        )
    pos = positive_mask(dbt, qt, max_distance_m=max_distance_m, max_angle_deg=max_angle_deg)
    if exclude_same_index:
        np.fill_diagonal(pos, False)
    neg = _distances(dbt, qt) > min_negative_distance_m
    hard = None
    if hard_negatives is not None:
        hard = np.asarray(
            hard_negatives.detach().cpu() if hasattr(hard_negatives, "detach") else hard_negatives,
            dtype=np.float64,
        )
        check_shape("hard_negatives", hard, (len(qt), len(dbt)))
        check_finite("hard_negatives", hard)
    valid = np.flatnonzero(pos.any(axis=1) & neg.any(axis=1))
    if valid.size == 0:
        raise GeosegError(
            "db, query: no query image has both a positive (within "
            f"{max_distance_m} m and {max_angle_deg} deg) and a negative (beyond "
            f"{min_negative_distance_m} m) in the database"
        )
    gen = _rng(rng)
    ref = valid[gen.integers(0, valid.size, size=n)]
    match = np.empty(n, dtype=np.int64)
    other = np.empty(n, dtype=np.int64)
    pools: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for i, r in enumerate(ref.tolist()):
        if r not in pools:
            cand = np.flatnonzero(neg[r])
            if hard is not None and cand.size > hard_k:
                cand = cand[np.argsort(hard[r, cand], kind="stable")[:hard_k]]
            pools[r] = (np.flatnonzero(pos[r]), cand)
        p, cand = pools[r]
        match[i] = p[gen.integers(0, p.size)]
        other[i] = cand[gen.integers(0, cand.size)]
    return ref.astype(np.int64), match, other


# ============================================================================ relative pose


#: camera centres closer than this are one place: no direction between them (metres)
_COINCIDENT_M = 1e-9


class NoEligiblePairError(GeosegError):
    """Two traversals have no pair of views meeting the baseline and angle thresholds."""


@dataclass(frozen=True)
class RelPosePairs:
    """Index pairs with their relative-pose targets (:func:`relative_pose_labels`).

    Attributes:
        idx_a: ``(n,)`` int64 indices into traversal a (the base camera of the pair).
        idx_b: ``(n,)`` int64 indices into traversal b (the query).
        R_ab: ``(n, 3, 3)`` float64, ``R_wc_a^T R_wc_b``.
        t_dir_ab: ``(n, 3)`` float64 unit direction a -> b in camera a's frame.
        baseline_m: ``(n,)`` float64 distance between the camera centres.

    Where the centres coincide (baseline 0, possible with ``min_baseline_m = 0``) the direction
    is undefined and ``t_dir_ab`` is ``(0, 0, 0)``.
    """

    idx_a: np.ndarray
    idx_b: np.ndarray
    R_ab: np.ndarray
    t_dir_ab: np.ndarray
    baseline_m: np.ndarray

    def __len__(self) -> int:
        return int(self.idx_a.shape[0])


def sample_relpose_pairs(
    a: Any,
    b: Any,
    n: int,
    *,
    rng: int | np.random.Generator = 0,
    min_baseline_m: float = 0.5,
    max_baseline_m: float = 10.0,
    max_angle_deg: float = 30.0,
    min_angle_deg: float = 0.0,
) -> RelPosePairs:
    """Sample ``n`` pairs ``(a_i, b_j)`` of overlapping views for the relative-pose head.

    A pair is eligible when the baseline ``|t_wc_b - t_wc_a|`` lies in
    ``[min_baseline_m, max_baseline_m]`` (``min_baseline_m`` 0 admits views from one place, whose
    direction target is ``(0, 0, 0)``: see :class:`RelPosePairs`) and the
    angle between the optical axes lies in ``[min_angle_deg, max_angle_deg]`` (with the default
    ``min_angle_deg`` 0: the views overlap; a positive one asks for turned views, e.g. the
    crossing street or the opposite direction at the same place). Pairs are drawn uniformly
    with replacement among eligible pairs. ``a`` and ``b`` may be the same traversal (the
    positive baseline bound already excludes ``i == j``).

    Args:
        a: traversal of the first images (``Na`` poses).
        b: traversal of the second images (``Nb`` poses).
        n: number of pairs, >= 1.
        rng: seed or ``numpy.random.Generator``.
        min_baseline_m: minimum baseline (metres), >= 0.
        max_baseline_m: maximum baseline (metres), ``>= min_baseline_m``.
        max_angle_deg: maximum angle between the optical axes (degrees).
        min_angle_deg: minimum angle between the optical axes (degrees), ``<= max_angle_deg``.

    Returns:
        :class:`RelPosePairs` with labels from :func:`relative_pose_labels`.

    Raises:
        GeosegError: bad thresholds or shapes, or no eligible pair.
    """
    ta, tb = as_traversal("a", a), as_traversal("b", b)
    n = _check_count("n", n)
    if not min_baseline_m >= 0:
        raise GeosegError(f"min_baseline_m: expected >= 0, got {min_baseline_m}")
    check_positive("max_baseline_m", max_baseline_m)
    check_positive("max_angle_deg", max_angle_deg)
    if max_baseline_m < min_baseline_m:
        raise GeosegError(
            f"max_baseline_m: expected >= min_baseline_m ({min_baseline_m}), got {max_baseline_m}"
        )
    if not 0.0 <= min_angle_deg <= max_angle_deg:
        raise GeosegError(
            f"min_angle_deg: expected in [0, max_angle_deg ({max_angle_deg})], got {min_angle_deg}"
        )
    dist = _distances(ta, tb).T  # (Na, Nb)
    ang = _axis_angles_deg(ta, tb).T
    ok = (dist >= min_baseline_m) & (dist <= max_baseline_m)
    ok &= (ang >= min_angle_deg) & (ang <= max_angle_deg)
    ia, ib = np.nonzero(ok)
    if ia.size == 0:
        raise NoEligiblePairError(
            f"a, b: no pair with a baseline in [{min_baseline_m}, {max_baseline_m}] m and "
            f"viewing directions {min_angle_deg}-{max_angle_deg} deg apart"
        )
    pick = _rng(rng).integers(0, ia.size, size=n)
    ia, ib = ia[pick].astype(np.int64), ib[pick].astype(np.int64)
    baseline = dist[ia, ib]
    R_ab = ta.R_wc[ia].transpose(0, 2, 1) @ tb.R_wc[ib]
    t_dir = np.zeros((n, 3))
    apart = baseline > _COINCIDENT_M  # a direction exists
    if apart.any():
        _, t_dir[apart] = relative_pose_labels(
            ta.R_wc[ia[apart]], ta.t_wc[ia[apart]], tb.R_wc[ib[apart]], tb.t_wc[ib[apart]]
        )
    return RelPosePairs(ia, ib, R_ab, t_dir, baseline)


# ============================================================================ datasets


class _FeatureSource:
    """Index -> ``(C, h, w)`` float32 tensor, from precomputed features or items + extractor."""

    def __init__(self, name: str, items: Any, feature_fn: Callable[[Any], Any] | None) -> None:
        self.name = name
        self.feature_fn = feature_fn
        if feature_fn is None:
            if isinstance(items, np.ndarray):
                items = torch.from_numpy(items)
            if not isinstance(items, torch.Tensor):
                raise GeosegError(
                    f"{name}: without feature_fn, expected precomputed features (N, C, h, w) "
                    f"as a tensor or array, got {type(items).__name__}"
                )
            if items.ndim != 4 or min(items.shape) == 0:
                raise GeosegError(
                    f"{name}: expected features of shape (N, C, h, w), got {tuple(items.shape)}"
                )
            if not items.is_floating_point():
                raise GeosegError(f"{name}: expected floating-point features, got {items.dtype}")
            self.shape: tuple[int, ...] | None = tuple(items.shape[1:])
        else:
            if not callable(feature_fn):
                raise GeosegError(f"feature_fn: expected a callable, got {type(feature_fn)}")
            self.shape = None
        self.items = items
        try:
            self.n = len(items)
        except TypeError:
            raise GeosegError(f"{name}: expected a sized sequence, got {type(items)}") from None

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> torch.Tensor:
        if self.feature_fn is None:
            return self.items[i].float()
        out = self.feature_fn(self.items[i])
        t = torch.as_tensor(np.asarray(out) if not isinstance(out, torch.Tensor) else out)
        if t.ndim != 3 or not t.is_floating_point():
            raise GeosegError(
                f"feature_fn: expected a float (C, h, w) feature map for {self.name}[{i}], got "
                f"{tuple(t.shape)} {t.dtype}"
            )
        return t.float()


def _check_indices(name: str, idx: Any, size: int) -> np.ndarray:
    arr = np.asarray(idx)
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise GeosegError(
            f"{name}: expected a 1-D integer index array, got {arr.dtype} {arr.shape}"
        )
    if arr.size and (arr.min() < 0 or arr.max() >= size):
        raise GeosegError(
            f"{name}: indices must lie in [0, {size}), got [{arr.min()}, {arr.max()}]"
        )
    return arr.astype(np.int64)


def _same_shapes(names: Sequence[str], tensors: Sequence[torch.Tensor]) -> None:
    shapes = [tuple(t.shape) for t in tensors]
    if len(set(shapes)) > 1:
        desc = ", ".join(f"{n} {s}" for n, s in zip(names, shapes))
        raise GeosegError(f"feature maps of mismatched sizes: {desc}")


class TripletDataset(Dataset):
    """Triplets ``(ref, match, other)`` of layer-21 features for eq. 5.1.

    Two ways to give the images:

    * precomputed features (``feature_fn=None``): ``query_items`` ``(Q, C, h, w)`` and
      ``db_items`` ``(M, C, h, w)`` tensors or arrays (e.g. the frozen trunk's layer-21 output,
      computed once); their ``(C, h, w)`` must agree;
    * any indexable items (RGB arrays, paths, ...) with ``feature_fn(item) -> (C, h, w)``
      float tensor (e.g. a frozen trunk plus image loading and augmentation); sizes are checked
      per sample.

    Args:
        query_items: the ``ref`` images' features or items.
        db_items: the ``match`` / ``other`` images' features or items.
        triplets: ``(ref_idx, match_idx, other_idx)`` from :func:`sample_triplets`.
        feature_fn: feature extractor for non-precomputed items, or None.

    Items are ``{"ref", "match", "other"}`` float32 ``(C, h, w)`` tensors plus ``"index"``
    ``(3,)`` int64 (ref, match, other).
    """

    def __init__(
        self,
        query_items: Any,
        db_items: Any,
        triplets: tuple[Any, Any, Any],
        *,
        feature_fn: Callable[[Any], Any] | None = None,
    ) -> None:
        self.query = _FeatureSource("query_items", query_items, feature_fn)
        self.db = _FeatureSource("db_items", db_items, feature_fn)
        if self.query.shape is not None and self.query.shape != self.db.shape:
            raise GeosegError(
                f"feature maps of mismatched sizes: query_items (*, {self.query.shape}) vs "
                f"db_items (*, {self.db.shape})"
            )
        if len(triplets) != 3:
            raise GeosegError("triplets: expected (ref_idx, match_idx, other_idx)")
        self.ref = _check_indices("triplets[0]", triplets[0], len(self.query))
        self.match = _check_indices("triplets[1]", triplets[1], len(self.db))
        self.other = _check_indices("triplets[2]", triplets[2], len(self.db))
        if not self.ref.size == self.match.size == self.other.size:
            raise GeosegError(
                f"triplets: index arrays of different lengths {self.ref.size}, "
                f"{self.match.size}, {self.other.size}"
            )

    def __len__(self) -> int:
        return int(self.ref.size)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        r, m, o = int(self.ref[i]), int(self.match[i]), int(self.other[i])
        ref, match, other = self.query[r], self.db[m], self.db[o]
        if self.query.shape is None:
            _same_shapes((f"ref[{r}]", f"match[{m}]", f"other[{o}]"), (ref, match, other))
        return {
            "ref": ref,
            "match": match,
            "other": other,
            "index": torch.tensor([r, m, o], dtype=torch.int64),
        }


class RelPosePairDataset(Dataset):
    """Pairs of layer-21 features with their relative pose (eq. 5.2).

    Items given as in :class:`TripletDataset` (precomputed ``(N, C, h, w)`` features, or items
    with ``feature_fn``).

    Args:
        items_a: features or items of traversal a (the base camera of each pair).
        items_b: features or items of traversal b (the query).
        pairs: :class:`RelPosePairs` from :func:`sample_relpose_pairs`.
        feature_fn: feature extractor for non-precomputed items, or None.

    Items are ``{"feat_a", "feat_b"}`` float32 ``(C, h, w)``, ``"R_ab"`` float32 ``(3, 3)``,
    ``"t_dir_ab"`` float32 ``(3,)`` and ``"index"`` ``(2,)`` int64.
    """

    def __init__(
        self,
        items_a: Any,
        items_b: Any,
        pairs: RelPosePairs,
        *,
        feature_fn: Callable[[Any], Any] | None = None,
    ) -> None:
        if not isinstance(pairs, RelPosePairs):
            raise GeosegError(f"pairs: expected RelPosePairs, got {type(pairs).__name__}")
        self.a = _FeatureSource("items_a", items_a, feature_fn)
        self.b = _FeatureSource("items_b", items_b, feature_fn)
        if self.a.shape is not None and self.a.shape != self.b.shape:
            raise GeosegError(
                f"feature maps of mismatched sizes: items_a (*, {self.a.shape}) vs "
                f"items_b (*, {self.b.shape})"
            )
        self.idx_a = _check_indices("pairs.idx_a", pairs.idx_a, len(self.a))
        self.idx_b = _check_indices("pairs.idx_b", pairs.idx_b, len(self.b))
        self.R_ab = torch.as_tensor(pairs.R_ab, dtype=torch.float32)
        self.t_dir_ab = torch.as_tensor(pairs.t_dir_ab, dtype=torch.float32)

    def __len__(self) -> int:
        return int(self.idx_a.size)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        ia, ib = int(self.idx_a[i]), int(self.idx_b[i])
        fa, fb = self.a[ia], self.b[ib]
        if self.a.shape is None:
            _same_shapes((f"items_a[{ia}]", f"items_b[{ib}]"), (fa, fb))
        return {
            "feat_a": fa,
            "feat_b": fb,
            "R_ab": self.R_ab[i],
            "t_dir_ab": self.t_dir_ab[i],
            "index": torch.tensor([ia, ib], dtype=torch.int64),
        }
