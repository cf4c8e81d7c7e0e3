"""What the visual front end remembers of each point, to observe it again once its track is lost.

:class:`PointMemory` keeps, per point id: the ORB descriptor of its latest appearance, the last
keyframe that observed it and where, and whether a check *retired* it (a track dropped by a
geometric check is never resurrected); plus the images of the last few keyframes. At a keyframe,
:class:`~slam_bridge.frontend.image_tracks.ImageTracks` asks it for

* :meth:`PointMemory.projected`: the map's triangulated points of the current segment that no
  live track follows, projected with the keyframe's pose estimate;
* :meth:`PointMemory.reacquire`: pyramidal LK from the last keyframe image that saw each of them
  (when still kept) to the new keyframe, started at its projection, forward-backward checked and
  within the search radius: precise, and robust to the small changes of scale and view of a few
  keyframes (the points lost behind a passing pole, or in a blank frame);
* :meth:`PointMemory.match`: for the others, the stored descriptors against the new corners
  within the search radius (:func:`slam_bridge.frontend.features.match_in_radius`).

The caller verifies both kinds of match against the pose (PnP) before giving the old ids again.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from slam_bridge.frontend import features as ft
from slam_bridge.geometry.camera import project

if TYPE_CHECKING:
    from collections.abc import Callable

    from slam_bridge.frontend.base import MapView

__all__ = ["PointMemory", "Projected"]

Projected = tuple[np.ndarray, np.ndarray, np.ndarray]  # ids (P,), uv (P, 2), X_w (P, 3)


def _grow(a: np.ndarray, n: int, fill) -> np.ndarray:
    """``a`` with at least ``n`` rows (doubling), new rows set to ``fill``."""
    if n <= a.shape[0]:
        return a
    out = np.full((max(n, 2 * a.shape[0], 1024), *a.shape[1:]), fill, dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


class PointMemory:
    """Per-point memory of a front end (module docstring).

    Args:
        keyframes: keyframe images kept for :meth:`reacquire` (0: none).
    """

    def __init__(self, keyframes: int) -> None:
        self.keyframes = keyframes
        self.desc = np.zeros((0, ft.DESCRIPTOR_BYTES), dtype=np.uint8)
        self.has_desc = np.zeros(0, dtype=bool)
        self.retired = np.zeros(0, dtype=bool)
        self.last_kf = np.zeros(0, dtype=np.int64)  # -1: never
        self.last_uv = np.zeros((0, 2), dtype=np.float32)
        self.first_id = 0  # ids below belong to earlier segments
        self._grays: dict[int, np.ndarray] = {}
        self._count = 0

    def store_descriptors(self, ids: np.ndarray, desc: np.ndarray, has: np.ndarray) -> None:
        """Remember ``desc`` ``(N, 32)`` for ``ids`` ``(N,)`` where ``has`` ``(N,)``."""
        if ids.size == 0:
            return
        n = int(ids.max()) + 1
        self.desc = _grow(self.desc, n, 0)
        self.has_desc = _grow(self.has_desc, n, False)
        self.desc[ids[has]] = desc[has]
        self.has_desc[ids[has]] = True

    def copy_descriptors(self, old: np.ndarray, new: np.ndarray) -> None:
        """Give the points ``new`` the descriptors of ``old`` (renamed tracks)."""
        ok = old < self.has_desc.size
        self.store_descriptors(new[ok], self.desc[old[ok]], self.has_desc[old[ok]])

    def retire(self, ids: np.ndarray) -> None:
        """Never observe ``ids`` again (a check dropped their tracks)."""
        if ids.size:
            self.retired = _grow(self.retired, int(ids.max()) + 1, False)
            self.retired[ids] = True

    def remember(self, gray: np.ndarray, ids: np.ndarray, uv: np.ndarray) -> None:
        """Record a keyframe: its image ``(H, W)`` and where it sees the points ``ids``."""
        if self.keyframes <= 0:
            return
        self._grays[self._count] = gray
        self._grays.pop(self._count - self.keyframes, None)
        if ids.size:
            n = int(ids.max()) + 1
            self.last_kf = _grow(self.last_kf, n, -1)
            self.last_uv = _grow(self.last_uv, n, 0.0)
            self.last_kf[ids] = self._count
            self.last_uv[ids] = uv
        self._count += 1

    def projected(
        self,
        slam_map: MapView,
        pose: tuple[np.ndarray, np.ndarray],
        K: np.ndarray,
        live: np.ndarray,
        inside: Callable[[np.ndarray], np.ndarray],
    ) -> Projected | None:
        """The map's triangulated points of this segment that no live track follows, that were
        not retired and have a descriptor, projected with ``pose`` ``(R_wc, t_wc)`` inside the
        image (``inside(uv) -> bool``); None when there is none."""
        ids, X = slam_map.triangulated_points()
        sel = (ids >= self.first_id) & (ids < self.has_desc.size)
        ids, X = ids[sel], X[sel]
        sel = self.has_desc[ids] & np.isfinite(X).all(axis=1) & ~np.isin(ids, live)
        retired = ids < self.retired.size
        sel[retired] &= ~self.retired[ids[retired]]
        ids, X = ids[sel], X[sel]
        if ids.size == 0:
            return None
        uv, _, front = project(K, pose[0], pose[1], X)
        ok = front & inside(np.where(front[:, None], uv, -1.0))
        return (ids[ok], uv[ok], X[ok]) if ok.any() else None

    def reacquire(
        self,
        proj: Projected,
        gray: np.ndarray,
        *,
        radius: float,
        lk: dict,
        fb_threshold: float,
        inside: Callable[[np.ndarray], np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """LK from the keyframe that last saw each projected point (if kept) to ``gray``.

        Args:
            proj: :meth:`projected`'s points.
            gray: ``(H, W)`` the new keyframe.
            radius: largest distance between the result and the projection (pixels).
            lk: ``cv2.calcOpticalFlowPyrLK`` keyword arguments.
            fb_threshold: largest forward-backward distance (pixels).
            inside: ``uv -> bool``, far enough inside the image.

        Returns:
            ``(found (R,) indices into proj, uv (R, 2) float32, tried (P,) bool)``: the points
            found and which points were tried (the others are left to :meth:`match`).
        """
        ids, uv_pred, _ = proj
        seen = np.full(ids.size, -1, dtype=np.int64)
        known = ids < self.last_kf.size
        seen[known] = self.last_kf[ids[known]]
        tried = np.isin(seen, list(self._grays))
        found = np.zeros(ids.size, dtype=bool)
        uv_out = np.zeros((ids.size, 2), dtype=np.float32)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        for k in np.unique(seen[tried]):
            sel = np.flatnonzero(seen == k)
            p0 = self.last_uv[ids[sel]].reshape(-1, 1, 2)
            guess = uv_pred[sel].astype(np.float32).reshape(-1, 1, 2)
            old = self._grays[int(k)]
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(old, gray, p0, guess, flags=flags, **lk)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, old, p1, p0.copy(), flags=flags, **lk)
            p1 = p1.reshape(-1, 2)
            fb = np.linalg.norm(back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
            ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb < fb_threshold)
            ok &= inside(p1) & (np.linalg.norm(p1 - uv_pred[sel], axis=1) < radius)
            found[sel[ok]] = True
            uv_out[sel] = p1
        idx = np.flatnonzero(found)
        return idx, uv_out[idx], tried

    def match(
        self,
        proj: Projected,
        cand: np.ndarray,
        desc: np.ndarray,
        has: np.ndarray,
        *,
        radius: float,
        max_distance: int,
        ratio: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(indices into proj (R,), indices into cand (R,))``: the projected points matched by
        descriptor to the candidates ``cand`` ``(C, 2)`` (descriptors ``desc`` ``(C, 32)``
        where ``has``) within ``radius`` pixels."""
        cidx = np.flatnonzero(has)
        mp, mc = ft.match_in_radius(
            proj[1],
            self.desc[proj[0]],
            cand[cidx],
            desc[cidx],
            radius=radius,
            max_distance=max_distance,
            ratio=ratio,
        )
        return mp, cidx[mc]
