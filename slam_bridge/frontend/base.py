"""What an observation source gives the SLAM loop, one keyframe at a time.

A source turns a sensor stream into keyframe observations: the pixels at which the keyframe sees
points, each point named by an id that stays the same across keyframes (a *track*). The loop
(:mod:`slam_bridge.slam.loop`) pulls keyframes with :meth:`ObservationSource.next_keyframe`,
appends them to its :class:`slam_bridge.slam.map.Map`, estimates the pose, triangulates and
optimises, then asks for the next one. Two sources exist:

* :class:`slam_bridge.experiments.simulated_tracks.SimulatedTracks`: projections of landmarks
  sampled on the synthetic city (the chapter-3 experiment, thesis §3.7);
* :mod:`slam_bridge.frontend.image_tracks`: corners tracked in images (the visual front end).

Contract:

* point ids are non-negative integers, never reused for another physical point; a source may
  re-observe a point the map knows (projection-guided matching) by giving its id again;
* the source may *read* the map (poses, points, which observations the loop rejected) to
  predict where points should appear, never write it;
* ``next_keyframe`` returns None when the stream ends.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from slam_bridge.slam.map import Map

__all__ = ["KeyframeObservations", "ObservationSource"]


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

    def next_keyframe(self, slam_map: Map) -> KeyframeObservations | None:
        """The next keyframe's observations, or None at the end of the stream."""
        ...
