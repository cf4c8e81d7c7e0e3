"""Simulated landmark tracks as an observation source (the chapter-3 experiment, thesis §3.7).

The thesis's synthetic sequence gives the SLAM the 2D tracks of scene points; here they are
prepared for the whole sequence beforehand (:mod:`slam_bridge.experiments.landmarks` samples and
projects the points of the synthetic city) and handed out one keyframe at a time.
"""

from __future__ import annotations

import numpy as np

from geoseg.errors import check_finite, check_shape
from slam_bridge.errors import SlamError
from slam_bridge.frontend.base import KeyframeObservations

__all__ = ["SimulatedTracks"]


class SimulatedTracks:
    """Precomputed keyframe observations, served in keyframe order.

    Args:
        K: ``(3, 3)`` intrinsics.
        image_size: ``(W, H)``.
        timestamps: ``(C,)`` keyframe times, seconds, increasing.
        keyframe: ``(M,)`` keyframe index of each observation, sorted.
        point: ``(M,)`` point id of each observation.
        uv: ``(M, 2)`` measured pixels.
    """

    def __init__(
        self,
        K: np.ndarray,
        image_size: tuple[int, int],
        timestamps: np.ndarray,
        keyframe: np.ndarray,
        point: np.ndarray,
        uv: np.ndarray,
    ) -> None:
        self.K = np.asarray(K, dtype=np.float64)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        self.keyframe = np.asarray(keyframe, dtype=np.int64).reshape(-1)
        self.point = np.asarray(point, dtype=np.int64).reshape(-1)
        self.uv = np.asarray(uv, dtype=np.float64)
        check_shape("K", self.K, (3, 3))
        check_shape("point", self.point, (self.keyframe.size,))
        check_shape("uv", self.uv, (self.keyframe.size, 2))
        check_finite("uv", self.uv)
        check_finite("timestamps", self.timestamps)
        if np.any(np.diff(self.keyframe) < 0):
            raise SlamError("observations: expected to be sorted by keyframe")
        if self.keyframe.size and (
            self.keyframe[0] < 0 or self.keyframe[-1] >= self.timestamps.size
        ):
            raise SlamError("observations: keyframe index outside the timestamps")
        self._starts = np.searchsorted(self.keyframe, np.arange(self.timestamps.size + 1))
        self._next = 0

    def __len__(self) -> int:
        return int(self.timestamps.size)

    def next_keyframe(self, slam_map=None) -> KeyframeObservations | None:
        """The next keyframe's observations, None after the last one."""
        k = self._next
        if k >= self.timestamps.size:
            return None
        self._next += 1
        sl = slice(self._starts[k], self._starts[k + 1])
        return KeyframeObservations(
            timestamp=float(self.timestamps[k]),
            point_ids=self.point[sl],
            uv=self.uv[sl],
            frame_index=k,
        )
