"""The facade each map point really lies on, from a render's instance and depth maps (the
chapter-4 truth).

``geoseg render`` writes, per frame, the class of every pixel (``labels/``) and, for building
pixels, the true facade they show and their depth (``geometry/*.npz``: ``instance``, ``depth``).
A map point's true facade is the majority of those of its observations' pixels (building pixels
vote their facade, other pixels vote "none"): the ``oracle`` association (the upper bound of
chapter 4) when the votes are gathered while the SLAM runs. Given the true poses, each
observation's pixel and depth also give the point's true position (the median over its
observations): a point at a building's corner lies on two facades, and an association with
either is right (:meth:`FacadeTruth.lies_on`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from geoseg.classes import BUILDING
from slam_bridge.bridge.association import Association
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError
from slam_bridge.slam.map import Map

__all__ = ["FacadeTruth"]


class FacadeTruth:
    """Votes of map points' observations for the true facade at their pixels.

    Args:
        folder: a ``geoseg render`` output (``labels/``, ``geometry/``, one file per frame).
        timestamps: ``(F,)`` the frames' timestamps (to find a keyframe's frame).
        poses: ``(R_wc (F, 3, 3), t_wc (F, 3), K (3, 3))`` the frames' true poses and the
            camera, for the points' true positions (None: facade votes only).
    """

    def __init__(self, folder: str | Path, timestamps: np.ndarray, poses=None) -> None:
        self.folder = Path(folder)
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.poses = poses
        # (points, facades, true positions or None) per keyframe
        self._votes: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._seen: set[int] = set()

    def observe(self, slam_map: Map, k: int, obs=None) -> None:
        """Add keyframe ``k``'s observations' votes (once per keyframe; the loop's hook
        signature, so it can run beside the SLAM)."""
        if k in self._seen or not 0 <= k < slam_map.num_keyframes:
            return
        self._seen.add(k)
        idx = slam_map.keyframe_observations(k)
        if idx.size == 0:
            return
        frame = int(np.searchsorted(self.timestamps, slam_map.timestamps[k]))
        instance, labels, depth = self._frame(frame)
        H, W = labels.shape
        uv = np.rint(slam_map.obs_uv[idx]).astype(np.int64)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        u, v = uv[inside, 0], uv[inside, 1]
        facade = np.where(labels[v, u] == BUILDING, instance[v, u], -1).astype(np.int64)
        X_w = None
        if self.poses is not None:  # the pixel's ray at its rendered z-depth (0: sky)
            R_wc, t_wc, K = self.poses
            z = np.where(depth[v, u] > 0, depth[v, u], np.nan).astype(np.float64)
            uv1 = np.column_stack([slam_map.obs_uv[idx][inside], np.ones(u.size)])
            X_c = (uv1 @ np.linalg.inv(K).T) * z[:, None]
            X_w = X_c @ R_wc[frame].T + t_wc[frame]
        # one append of everything: a thread reading the votes never sees half a keyframe
        self._votes.append((slam_map.obs_point[idx][inside].astype(np.int64), facade, X_w))

    def observe_all(self, slam_map: Map) -> FacadeTruth:
        """Votes of every keyframe of a finished map; returns ``self``."""
        for k in range(slam_map.num_keyframes):
            self.observe(slam_map, k)
        return self

    def true_facade_ids(self, num_points: int) -> np.ndarray:
        """``(num_points,)`` the majority true facade id of each point (-1: none, or no vote)."""
        out = np.full(num_points, -1, np.int64)
        votes = list(self._votes)
        if not votes:
            return out
        pts = np.concatenate([p for p, _, _ in votes])
        fac = np.concatenate([f for _, f, _ in votes])
        keep = pts < num_points
        pairs, counts = np.unique(np.stack([pts[keep], fac[keep]], 1), axis=0, return_counts=True)
        order = np.lexsort((-counts, pairs[:, 0]))  # per point, the most voted first
        first = order[np.r_[True, pairs[order][1:, 0] != pairs[order][:-1, 0]]]
        out[pairs[first, 0]] = pairs[first, 1]
        return out

    def true_positions(self, num_points: int) -> np.ndarray:
        """``(num_points, 3)`` each point's true position, the median over its observations
        (NaN: no observation with a depth, or no poses given)."""
        out = np.full((num_points, 3), np.nan)
        votes = [(p, x) for p, _, x in list(self._votes) if x is not None]
        if not votes:
            return out
        pts = np.concatenate([p for p, _ in votes])
        X = np.concatenate([x for _, x in votes])
        keep = (pts < num_points) & np.isfinite(X).all(1)
        pts, X = pts[keep], X[keep]
        if pts.size == 0:
            return out
        for c in range(3):  # per point, the middle of its sorted values
            order = np.lexsort((X[:, c], pts))
            p_sorted = pts[order]
            starts = np.r_[0, np.flatnonzero(np.diff(p_sorted)) + 1]
            counts = np.diff(np.r_[starts, p_sorted.size])
            out[p_sorted[starts], c] = X[order][starts + (counts - 1) // 2, c]
        return out

    def lies_on(
        self, world: Facades, rows: np.ndarray, facades: Facades, tol_m: float = 0.2
    ) -> np.ndarray:
        """``(P,)`` whether each point's true position lies within ``tol_m`` of the true facade
        that row ``rows[i]`` of ``facades`` models (False for -1 rows).

        Args:
            world: the true facades (every row its own truth: the exact model).
            rows: ``(P,)`` rows of ``facades`` (an association's).
            facades: the model ``rows`` refer to (the exact model or a GIS model).
        """
        rows = np.asarray(rows)
        on = np.zeros(rows.size, bool)
        world_row = {int(t): r for r, t in enumerate(world.true_facade_id) if t >= 0}
        target = np.full(rows.size, -1, np.int64)
        has = rows >= 0
        target[has] = [world_row.get(int(facades.true_facade_id[r]), -1) for r in rows[has]]
        X = self.true_positions(rows.size)
        pt, fc, _ = world.near(np.where((target >= 0)[:, None], X, np.nan), tol_m)
        on[pt[fc == target[pt]]] = True
        return on

    def model_rows(self, facades: Facades, num_points: int) -> np.ndarray:
        """``(num_points,)`` each point's true facade as a row of ``facades`` (-1: none, or
        the model lacks that facade, as a GIS model missing the building)."""
        ids = self.true_facade_ids(num_points)
        row_of = {int(t): r for r, t in enumerate(facades.true_facade_id) if t >= 0}
        return np.array([row_of.get(int(i), -1) for i in ids], np.int64)

    def oracle(self, facades: Facades, points: np.ndarray, radius_m: float) -> Association:
        """The oracle association: every triangulated point within ``radius_m`` of its true
        facade on it, weight 1 (the radius every method keeps: the upper bound of the same
        rule, not a pull on points the map has placed far off).

        Args:
            points: ``(P, 3)`` map points (NaN rows: not triangulated).
        """
        rows = self.model_rows(facades, points.shape[0])
        pt, fc, _ = facades.near(np.where((rows >= 0)[:, None], points, np.nan), radius_m)
        near = np.zeros(points.shape[0], bool)
        near[pt[fc == rows[pt]]] = True
        rows[~near] = -1
        return Association(rows, near.astype(np.float64), "oracle")

    def _frame(self, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        stem = f"{frame:06d}"
        try:
            with np.load(self.folder / "geometry" / f"{stem}.npz") as g:
                instance = g["instance"]
                depth = g["depth"] if self.poses is not None else None
        except (OSError, KeyError) as exc:
            raise SlamError(f"{self.folder}: frame {stem} has no instance map ({exc})") from exc
        labels = cv2.imread(str(self.folder / "labels" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        if labels is None or labels.shape != instance.shape:
            raise SlamError(f"{self.folder}: labels/{stem}.png unreadable or not {instance.shape}")
        return instance, labels, depth
