"""What an observation source gives the SLAM loop, one keyframe at a time.

A source turns a sensor stream into keyframe observations: the pixels at which the keyframe sees
points, each point named by an id that stays the same across keyframes (a *track*). The loop
(:mod:`slam_bridge.slam.loop`) pulls keyframes with :meth:`ObservationSource.next_keyframe`,
appends them to its map (:class:`slam_bridge.slam.map.Map`), estimates the pose, triangulates
and optimises, then asks for the next one. Two sources exist:

* :class:`slam_bridge.experiments.simulated_tracks.SimulatedTracks`: projections of landmarks
  sampled on the synthetic city (the chapter-3 experiment, thesis §3.7);
* :mod:`slam_bridge.frontend.image_tracks`: corners tracked in images (the visual front end).

Contract:

* point ids are non-negative integers, never reused for another physical point; a source may
  re-observe a point the map knows (projection-guided matching) by giving its id again;
* the source may *read* the map (poses, points, which observations the loop rejected; what
  :class:`MapView` names) to predict where points should appear, never write it;
* ``next_keyframe`` returns None when the stream ends.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["KeyframeObservations", "MapView", "ObservationSource"]


class MapView(Protocol):
    """What a source may read of the loop's map (:class:`slam_bridge.slam.map.Map` is one): the
    front end depends on this interface, not on the map's module.

    Attributes:
        num_keyframes: ``C``.
        timestamps: ``(C,)`` seconds.
        num_points: ``P``, one more than the largest point id seen.
        X_w: ``(P, 3)`` point positions, NaN where never triangulated.
        triangulated: ``(P,)`` bool, the point has a usable position.
        obs_point: ``(M,)`` point id of each observation.
        obs_active: ``(M,)`` bool, the observation is used (False once the loop rejected it).
    """

    @property
    def num_keyframes(self) -> int: ...

    @property
    def timestamps(self) -> np.ndarray: ...

    @property
    def num_points(self) -> int: ...

    @property
    def X_w(self) -> np.ndarray: ...

    @property
    def triangulated(self) -> np.ndarray: ...

    @property
    def obs_point(self) -> np.ndarray: ...

    @property
    def obs_active(self) -> np.ndarray: ...

    def keyframe_observations(self, k: int) -> np.ndarray:
        """``(N_k,)`` indices of keyframe ``k``'s observations."""
        ...

    def triangulated_points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (T,), X_w (T, 3))`` of the triangulated points."""
        ...

    def predict_pose(self, timestamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The camera pose ``(R_wc (3, 3), t_wc (3,))`` predicted at ``timestamp``, or None."""
        ...


@dataclass
class KeyframeObservations:
    """One keyframe as a source gives it.

    Attributes:
        timestamp: seconds, increasing from keyframe to keyframe.
        point_ids: ``(N,)`` int64 track ids, unique within the keyframe.
        uv: ``(N, 2)`` float64 pixels (OpenCV convention: x right, y down, pixel centres at
            integers).
        frame_index: index of the source frame (image) that became this keyframe.
        image: ``(H, W, 3)`` uint8 RGB of the keyframe when the source has images (the network
            bridge labels its pixels), else None.
    """

    timestamp: float
    point_ids: np.ndarray
    uv: np.ndarray
    frame_index: int
    image: np.ndarray | None = None


class ObservationSource(Protocol):
    """Anything that yields keyframe observations (module docstring).

    Attributes:
        K: ``(3, 3)`` intrinsics of the images the pixels refer to.
        image_size: ``(W, H)``.
    """

    K: np.ndarray
    image_size: tuple[int, int]

    def next_keyframe(self, slam_map: MapView) -> KeyframeObservations | None:
        """The next keyframe's observations, or None at the end of the stream."""
        ...
