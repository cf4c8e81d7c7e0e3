"""Ground-truth evaluation of keyframe tracks (a front end's output) with rendered depth.

The *true error* of an observation: each point id's first observation (its reference) is
back-projected with the rendered depth and the true pose of its frame, and projected with the
true pose of every later observation's frame; the error is the distance in pixels to the observed
pixel. Depth edges and the sky are handled apart (several depth candidates, the smallest error;
points at infinity), and a point on a moving vehicle counts as static, so its later observations
are bad, as they are for the SLAM.

:func:`evaluate_tracks` gives per-observation errors and a summary: ``bad_share`` (errors above
``threshold_px``), ``bad_share_consistency`` (the distance to the best static point at the true
poses: what would pull the SLAM away from the truth, blind to a drift along the epipolar lines),
error percentiles, reference kinds, tracks per keyframe, track lengths and re-observations. The
rules in full: ``docs/frontend.md`` ("Measuring the tracks against the truth").

:class:`RenderTruth` reads the truth from a ``geoseg render`` folder (``poses.csv``,
``camera.json``, ``geometry/NNNNNN.npz``); :class:`TruthMap` keeps a map at the truth while a
front end runs, for tests and benchmarks without the SLAM loop.
"""

from __future__ import annotations

import csv
import json
import logging
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geoseg.errors import check_shape
from slam_bridge.errors import SlamError
from slam_bridge.frontend.base import KeyframeObservations
from slam_bridge.geometry.camera import project

logger = logging.getLogger(__name__)

__all__ = ["RenderTruth", "TrackTable", "TrackEvaluation", "flatten_tracks", "evaluate_tracks"]

SKY_DISTANCE = 1e7  # metres: where a sky reference is put (a point at infinity, in effect)
KIND_SURFACE, KIND_EDGE, KIND_SKY = 0, 1, 2


class RenderTruth:
    """True poses and depth of a ``geoseg render`` folder.

    Args:
        folder: the render folder.
        cache: depth maps kept in memory (least recently used out).

    Attributes:
        K: ``(3, 3)``.
        image_size: ``(W, H)``.
        timestamps: ``(F,)``.
        R_wc: ``(F, 3, 3)`` camera-to-world rotations.
        t_wc: ``(F, 3)`` optical centres.
    """

    def __init__(self, folder: str | Path, cache: int = 8) -> None:
        self.folder = Path(folder)
        poses, cam = self.folder / "poses.csv", self.folder / "camera.json"
        for p in (poses, cam):
            if not p.is_file():
                raise SlamError(f"{p}: not found (expected a geoseg render folder)")
        meta = json.loads(cam.read_text())
        self.K = np.asarray(meta["K"], dtype=np.float64)
        self.image_size = (int(meta["image_size"][0]), int(meta["image_size"][1]))
        with poses.open(newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            raise SlamError(f"{poses}: no rows")
        col = lambda *names: np.array([[float(r[n]) for n in names] for r in rows])  # noqa: E731
        self.timestamps = col("timestamp")[:, 0]
        self.t_wc = col("tx", "ty", "tz")
        self.R_wc = col(*(f"r{i}{j}" for i in range(3) for j in range(3))).reshape(-1, 3, 3)
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cache_size = cache

    def __len__(self) -> int:
        return int(self.timestamps.size)

    def depth(self, index: int) -> np.ndarray:
        """``(H, W)`` float32 z-depth of frame ``index`` (0 on sky)."""
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        path = self.folder / "geometry" / f"{index:06d}.npz"
        if not path.is_file():
            raise SlamError(f"{path}: not found (depth of frame {index})")
        with np.load(path) as data:
            d = np.asarray(data["depth"], dtype=np.float32)
        self._cache[index] = d
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return d


@dataclass
class TrackTable:
    """Keyframe observations flattened (``M`` observations, keyframe order).

    Attributes:
        keyframe: ``(M,)`` keyframe index (position in the list given).
        frame: ``(M,)`` source frame index.
        point: ``(M,)`` point id.
        uv: ``(M, 2)`` pixels.
    """

    keyframe: np.ndarray
    frame: np.ndarray
    point: np.ndarray
    uv: np.ndarray


def flatten_tracks(keyframes: Sequence[KeyframeObservations]) -> TrackTable:
    """One row per observation of ``keyframes`` (a front end's output, in order)."""
    n = [k.point_ids.size for k in keyframes]
    kf = np.repeat(np.arange(len(keyframes)), n)
    frame = np.repeat(np.array([k.frame_index for k in keyframes], dtype=np.int64), n)
    point = np.concatenate([k.point_ids for k in keyframes]) if keyframes else np.zeros(0)
    uv = np.concatenate([k.uv for k in keyframes]) if keyframes else np.zeros((0, 2))
    return TrackTable(kf, frame, point.astype(np.int64), np.asarray(uv, dtype=np.float64))


@dataclass
class TrackEvaluation:
    """Per-observation true errors and their summary (module docstring).

    Attributes:
        table: the observations.
        error_px: ``(M,)`` true reprojection error (0 on references).
        reference: ``(M,)`` bool, the point's first observation.
        kind: ``(M,)`` the kind of the point's reference: 0 surface, 1 edge, 2 sky.
        reobserved: ``(M,)`` bool, the point was missing from the previous keyframe.
        summary: figures (module docstring); all floats.
        fit_error_px: ``(M,)`` distance to the best-fitting static point's projection.
    """

    table: TrackTable
    error_px: np.ndarray
    reference: np.ndarray
    kind: np.ndarray
    reobserved: np.ndarray
    summary: dict[str, float] = field(default_factory=dict)
    fit_error_px: np.ndarray | None = None


EDGE_RADIUS = 2  # pixels: an edge reference also tries the nearest and farthest depth this close


def _reference_points(
    K: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    depth: np.ndarray,
    uv: np.ndarray,
    edge_tolerance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate world points of references seen from one frame (module docstring).

    Args:
        K: ``(3, 3)``.
        R_wc: ``(3, 3)`` the frame's true rotation.
        t_wc: ``(3,)`` its optical centre.
        depth: ``(H, W)`` z-depth, 0 on sky.
        uv: ``(R, 2)`` reference pixels.
        edge_tolerance: relative depth spread below which the 2x2 neighbourhood agrees.

    Returns:
        ``X (R, 7, 3)`` candidates (the 2x2 neighbours' depths, the nearest and farthest depth
        within ``EDGE_RADIUS`` pixels, infinity), ``valid (R, 7)`` bool (a surface reference has
        one: the interpolated depth), ``kind (R,)``.
    """
    H, W = depth.shape
    u = np.clip(uv[:, 0], 0.0, W - 1.0)
    v = np.clip(uv[:, 1], 0.0, H - 1.0)
    u0 = np.minimum(np.floor(u).astype(np.int64), W - 2)
    v0 = np.minimum(np.floor(v).astype(np.int64), H - 2)
    au, av = u - u0, v - v0
    d = np.stack(
        [depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]], axis=1
    ).astype(np.float64)  # (R, 4)
    wts = np.stack([(1 - au) * (1 - av), au * (1 - av), (1 - au) * av, au * av], axis=1)
    sky = d <= 0
    dmin = np.where(sky, np.inf, d).min(axis=1)
    dmax = np.where(sky, 0.0, d).max(axis=1)
    surface = ~sky.any(axis=1) & (dmax - dmin <= edge_tolerance * dmin)
    kind = np.where(surface, KIND_SURFACE, np.where(sky.all(axis=1), KIND_SKY, KIND_EDGE))
    # the neighbourhood of an edge reference: nearest and farthest surface, and the sky
    off = np.arange(-EDGE_RADIUS, EDGE_RADIUS + 1)
    pu = np.clip(np.round(u).astype(np.int64)[:, None, None] + off[None, None, :], 0, W - 1)
    pv = np.clip(np.round(v).astype(np.int64)[:, None, None] + off[None, :, None], 0, H - 1)
    patch = depth[pv, pu].reshape(uv.shape[0], -1).astype(np.float64)
    hit = patch > 0
    near = np.where(hit, patch, np.inf).min(axis=1)
    far = np.where(hit, patch, 0.0).max(axis=1)
    cand = np.column_stack(
        [np.where(sky, SKY_DISTANCE, d), near, far, np.full(d.shape[0], SKY_DISTANCE)]
    )
    valid = np.column_stack([np.ones_like(sky), hit.any(axis=1), hit.any(axis=1), ~hit.all(axis=1)])
    cand[~valid] = 1.0
    with np.errstate(divide="ignore"):
        interp = 1.0 / np.sum(wts / np.where(sky, np.inf, d), axis=1)
    cand[surface, 0] = interp[surface]
    valid[surface, 1:] = False
    ray = np.column_stack([uv, np.ones(uv.shape[0])]) @ np.linalg.inv(K).T  # z = 1
    X_c = cand[:, :, None] * ray[:, None, :]  # (R, 7, 3)
    X_w = X_c @ R_wc.T + t_wc
    return X_w, valid, kind


def evaluate_tracks(
    keyframes: Sequence[KeyframeObservations] | TrackTable,
    K: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    depth: Callable[[int], np.ndarray],
    *,
    threshold_px: float = 2.0,
    edge_tolerance: float = 0.05,
    active: np.ndarray | None = None,
) -> TrackEvaluation:
    """True reprojection errors of tracks (module docstring).

    Args:
        keyframes: a front end's keyframes, in order (or their :class:`TrackTable`).
        K: ``(3, 3)`` intrinsics.
        R_wc: ``(F, 3, 3)`` true camera-to-world rotation of every source frame.
        t_wc: ``(F, 3)`` true optical centres.
        depth: ``frame_index -> (H, W)`` rendered z-depth (0 on sky), e.g.
            :meth:`RenderTruth.depth`.
        threshold_px: an observation is bad above this error.
        edge_tolerance: relative depth spread of a surface reference's 2x2 neighbourhood.
        active: optional ``(M,)`` bool, observations that count in the shares (e.g. those the
            loop kept); default all.

    Returns:
        A :class:`TrackEvaluation`.
    """
    table = keyframes if isinstance(keyframes, TrackTable) else flatten_tracks(keyframes)
    K = np.asarray(K, dtype=np.float64)
    R_wc = np.asarray(R_wc, dtype=np.float64)
    t_wc = np.asarray(t_wc, dtype=np.float64)
    check_shape("K", K, (3, 3))
    check_shape("R_wc", R_wc, (None, 3, 3))
    check_shape("t_wc", t_wc, (R_wc.shape[0], 3))
    M = table.point.size
    if M and table.frame.max() >= R_wc.shape[0]:
        raise SlamError(
            f"R_wc: {R_wc.shape[0]} frames, but an observation refers to frame {table.frame.max()}"
        )
    active = np.ones(M, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    check_shape("active", active, (M,))
    # references: the first observation of each point (the table is in keyframe order)
    uniq, ref_idx, inverse = np.unique(table.point, return_index=True, return_inverse=True)
    reference = np.zeros(M, dtype=bool)
    reference[ref_idx] = True
    P = uniq.size
    X = np.zeros((P, 7, 3))
    valid = np.zeros((P, 7), dtype=bool)
    kind_p = np.zeros(P, dtype=np.int64)
    ref_frames = table.frame[ref_idx]
    for f in np.unique(ref_frames):
        sel = np.flatnonzero(ref_frames == f)
        X[sel], valid[sel], kind_p[sel] = _reference_points(
            K, R_wc[f], t_wc[f], depth(int(f)), table.uv[ref_idx[sel]], edge_tolerance
        )
    # every observation against its point's candidates
    err = np.full((M, X.shape[1]), np.inf)
    Xo = X[inverse]
    for c in range(X.shape[1]):
        uv_hat, _, front = project(K, R_wc[table.frame], t_wc[table.frame], Xo[:, c])
        e = np.linalg.norm(uv_hat - table.uv, axis=1)
        ok = valid[inverse, c] & front
        err[ok, c] = e[ok]
    error = err.min(axis=1)
    error[reference] = 0.0
    kind = kind_p[inverse]
    # re-observation: the point's previous observation is not in the previous keyframe
    order = np.lexsort((table.keyframe, table.point))
    prev_kf = np.full(M, -1)
    same = table.point[order][1:] == table.point[order][:-1]
    prev_kf[order[1:][same]] = table.keyframe[order][:-1][same]
    reobserved = ~reference & (prev_kf != table.keyframe - 1)
    summary = _summary(table, error, reference, kind, reobserved, active, threshold_px)
    fit = _best_fit_errors(K, R_wc, t_wc, table, inverse, P)
    counted = ~reference & active
    summary["bad_share_consistency"] = (
        float(np.mean(fit[counted] > threshold_px)) if counted.any() else 0.0
    )
    return TrackEvaluation(table, error, reference, kind, reobserved, summary, fit)


def _best_fit_errors(
    K: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray, table: TrackTable, inverse, P: int
) -> np.ndarray:
    """``(M,)`` distance of each observation to the projection of its point's best-fitting
    static point at the true poses (inf where that point is behind the camera)."""
    from slam_bridge.geometry.multiview import triangulate

    M = table.point.size
    if M == 0:
        return np.zeros(0)
    res = triangulate(
        K, R_wc, t_wc, table.frame, inverse, table.uv, num_points=P, min_parallax_deg=0.0
    )
    X = np.nan_to_num(res.X_w[inverse])
    uv_hat, _, front = project(K, R_wc[table.frame], t_wc[table.frame], X)
    err = np.where(front, np.linalg.norm(uv_hat - table.uv, axis=1), np.inf)
    single = np.bincount(inverse, minlength=P)[inverse] < 2
    err[single] = 0.0
    return err


def _summary(
    table: TrackTable,
    error: np.ndarray,
    reference: np.ndarray,
    kind: np.ndarray,
    reobserved: np.ndarray,
    active: np.ndarray,
    threshold_px: float,
) -> dict[str, float]:
    counted = ~reference & active
    e = error[counted]
    n = max(int(counted.sum()), 1)
    per_kf = np.bincount(
        table.keyframe, minlength=int(table.keyframe.max() + 1 if table.keyframe.size else 0)
    )
    _, length = np.unique(table.point, return_counts=True)
    pct = lambda a, q: float(np.percentile(a, q)) if a.size else float("nan")  # noqa: E731
    out = {
        "keyframes": float(per_kf.size),
        "observations": float(table.point.size),
        "points": float(length.size),
        "evaluated": float(counted.sum()),
        "bad_share": float(np.sum(e > threshold_px)) / n,
        "threshold_px": float(threshold_px),
        "error_median_px": pct(e, 50),
        "error_p90_px": pct(e, 90),
        "error_p99_px": pct(e, 99),
        "edge_reference_share": float(np.mean(kind[counted] == KIND_EDGE))
        if counted.any()
        else 0.0,
        "bad_share_surface": _share(error, counted & (kind == KIND_SURFACE), threshold_px),
        "bad_share_edge": _share(error, counted & (kind == KIND_EDGE), threshold_px),
        "tracks_per_keyframe_mean": float(per_kf.mean()) if per_kf.size else 0.0,
        "tracks_per_keyframe_min": float(per_kf.min()) if per_kf.size else 0.0,
        "track_length_mean": float(length.mean()) if length.size else 0.0,
        "track_length_median": pct(length, 50),
        "track_length_p90": pct(length, 90),
        "track_length_max": float(length.max()) if length.size else 0.0,
        "tracks_3plus_share": float(np.mean(length >= 3)) if length.size else 0.0,
        "reobservations": float(reobserved.sum()),
        "bad_share_reobserved": _share(error, counted & reobserved, threshold_px),
    }
    return out


def _share(error: np.ndarray, sel: np.ndarray, threshold: float) -> float:
    return float(np.mean(error[sel] > threshold)) if sel.any() else float("nan")


class TruthMap:
    """A :class:`~slam_bridge.slam.map.Map` kept at ground truth while a source runs (tests and
    benchmarks of a front end without the SLAM loop).

    Each keyframe added gets its true pose. Points get positions in one of two ways:

    * ``points="depth"``: the true position from the point's reference (surface references only,
      module docstring), marked triangulated once two keyframes observe it;
    * ``points="triangulate"``: what a loop with perfect poses would estimate: the points of each
      new keyframe seen at least twice are triangulated from all their observations at the true
      poses (:func:`slam_bridge.geometry.multiview.triangulate`, ``min_parallax_deg``); drifting
      tracks thus get drifting points, as in the loop.

    With ``reject_px``, each new observation whose reprojection error against its point exceeds
    it is marked inactive, as the loop's outlier rejection would.

    Args:
        K: ``(3, 3)``.
        image_size: ``(W, H)``.
        R_wc: ``(F, 3, 3)`` true rotation of every source frame.
        t_wc: ``(F, 3)`` true optical centres.
        depth: ``frame_index -> (H, W)`` z-depth.
        points: ``depth`` or ``triangulate``.
        reject_px: optional rejection threshold.
        min_parallax_deg: triangulation parallax threshold (``triangulate``).
    """

    def __init__(
        self,
        K: np.ndarray,
        image_size: tuple[int, int],
        R_wc: np.ndarray,
        t_wc: np.ndarray,
        depth: Callable[[int], np.ndarray],
        *,
        points: str = "depth",
        reject_px: float | None = None,
        min_parallax_deg: float = 1.0,
    ) -> None:
        from slam_bridge.slam.map import Map

        if points not in ("depth", "triangulate"):
            raise SlamError(f"points: expected 'depth' or 'triangulate', got {points!r}")
        self.map = Map(K, image_size)
        self.K = np.asarray(K, dtype=np.float64)
        self.R_wc, self.t_wc = np.asarray(R_wc), np.asarray(t_wc)
        self.depth = depth
        self.points = points
        self.reject_px = reject_px
        self.min_parallax_deg = min_parallax_deg
        self._X = np.full((0, 3), np.nan)
        self._count = np.zeros(0, dtype=np.int64)

    def add(self, kf: KeyframeObservations) -> int:
        """Append ``kf`` with its true pose; returns its keyframe index."""
        m = self.map
        k = m.add_keyframe(kf.timestamp, kf.point_ids, kf.uv)
        f = kf.frame_index
        m.set_pose(k, self.R_wc[f], self.t_wc[f])
        m.mark_online(k)
        ids = kf.point_ids
        if ids.size and ids.max() >= self._X.shape[0]:
            n = int(ids.max()) + 1
            self._X = np.vstack([self._X, np.full((n - self._X.shape[0], 3), np.nan)])
            self._count = np.concatenate([self._count, np.zeros(n - self._count.size, np.int64)])
        new = self._count[ids] == 0
        if new.any() and self.points == "depth":
            X, _, kind = _reference_points(
                self.K, self.R_wc[f], self.t_wc[f], self.depth(f), kf.uv[new], 0.05
            )
            self._X[ids[new]] = np.where((kind == KIND_SURFACE)[:, None], X[:, 0], np.nan)
        self._count[ids] += 1
        if self.reject_px is not None and ids.size:
            X = self._X[ids]
            uv_hat, _, front = project(self.K, self.R_wc[f], self.t_wc[f], np.nan_to_num(X))
            err = np.linalg.norm(uv_hat - kf.uv, axis=1)
            bad = front & np.isfinite(X[:, 0]) & (err > self.reject_px)
            m.obs_active[m.keyframe_observations(k)[bad]] = False
        if self.points == "triangulate":
            self._triangulate(ids[self._count[ids] >= 2])
        seen = ids[self._count[ids] >= 2]
        m.X_w[seen] = self._X[seen]
        m.triangulated[seen] = np.isfinite(self._X[seen, 0])
        return k

    def _triangulate(self, ids: np.ndarray) -> None:
        from slam_bridge.geometry.multiview import triangulate

        m = self.map
        obs = np.flatnonzero(np.isin(m.obs_point, ids) & m.obs_active)
        if obs.size == 0:
            return
        uniq, local = np.unique(m.obs_point[obs], return_inverse=True)
        res = triangulate(
            self.K,
            m.R_wc,
            m.t_wc,
            m.obs_keyframe[obs],
            local,
            m.obs_uv[obs],
            num_points=uniq.size,
            min_parallax_deg=self.min_parallax_deg,
        )
        self._X[uniq] = np.where(res.valid[:, None], res.X_w, np.nan)
