"""A pose for every frame of a run, not only its keyframes.

The SLAM estimates keyframes; the frames between two keyframes of one segment take the pose
interpolated in time (rotation along the geodesic, position linearly), the frames after the
last keyframe the last motion continued (constant velocity, at most ``max_extrapolation_s``).
Each frame says where its pose came from (:data:`POSE_SOURCES`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_bridge.geometry.lie import so3_exp, so3_log

__all__ = ["POSE_SOURCES", "FramePoses", "frame_poses"]

#: where a frame's pose came from: its keyframe's estimate, interpolated between two keyframes,
#: extrapolated past the last keyframe, or none (before the first keyframe, between segments)
POSE_SOURCES = ("keyframe", "interpolated", "extrapolated", "none")


@dataclass
class FramePoses:
    """Poses of all frames.

    Attributes:
        timestamps: ``(T,)`` frame times.
        R_wc: ``(T, 3, 3)`` (NaN where ``source`` is ``none``).
        t_wc: ``(T, 3)``.
        source: ``(T,)`` one of :data:`POSE_SOURCES` per frame.
        segment: ``(T,)`` the SLAM segment (-1: none).
        in_world: ``(T,)`` the pose is in the world frame (a georeferenced segment).
    """

    timestamps: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    source: np.ndarray
    segment: np.ndarray
    in_world: np.ndarray

    @property
    def has_pose(self) -> np.ndarray:
        """``(T,)`` bool: the frame has a pose."""
        return self.source != "none"


def frame_poses(result, timestamps: np.ndarray, max_extrapolation_s: float = 1.0) -> FramePoses:
    """Every frame's pose from a run's keyframes (module docstring).

    Args:
        result: the :class:`slam_bridge.slam.loop.SlamResult`.
        timestamps: ``(T,)`` the frames' times (increasing; the keyframes' are among them).
        max_extrapolation_s: frames further than this past the last keyframe keep no pose.

    Returns:
        A :class:`FramePoses`.
    """
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    m = result.map
    T = t.size
    R = np.full((T, 3, 3), np.nan)
    P = np.full((T, 3), np.nan)
    source = np.full(T, "none", dtype=object)
    segment = np.full(T, -1, dtype=np.int64)
    in_world = np.zeros(T, dtype=bool)
    placed = np.flatnonzero(result.placed)
    world = result.in_world
    if placed.size == 0:
        return FramePoses(t, R, P, source, segment, in_world)
    kt = m.timestamps[placed]
    frame = np.clip(np.searchsorted(t, kt), 0, T - 1)
    for a, b, fa, fb in zip(placed[:-1], placed[1:], frame[:-1], frame[1:]):
        if m.segment[a] != m.segment[b]:
            continue
        w = (t[fa + 1 : fb] - m.timestamps[a]) / (m.timestamps[b] - m.timestamps[a])
        rel = so3_log(m.R_wc[b] @ m.R_wc[a].T)
        for i, wi in zip(range(fa + 1, fb), w):
            R[i] = so3_exp(wi * rel) @ m.R_wc[a]
            P[i] = (1 - wi) * m.t_wc[a] + wi * m.t_wc[b]
        source[fa + 1 : fb] = "interpolated"
        segment[fa + 1 : fb] = m.segment[a]
        in_world[fa + 1 : fb] = world[a] and world[b]
    R[frame], P[frame] = m.R_wc[placed], m.t_wc[placed]
    source[frame], segment[frame], in_world[frame] = "keyframe", m.segment[placed], world[placed]
    last, fl = placed[-1], frame[-1]
    if placed.size >= 2 and m.segment[placed[-2]] == m.segment[last] and fl + 1 < T:
        prev = placed[-2]
        dt = m.timestamps[last] - m.timestamps[prev]
        omega = so3_log(m.R_wc[last] @ m.R_wc[prev].T) / dt
        velocity = (m.t_wc[last] - m.t_wc[prev]) / dt
        for i in range(fl + 1, T):
            h = t[i] - m.timestamps[last]
            if h > max_extrapolation_s:
                break
            R[i] = so3_exp(h * omega) @ m.R_wc[last]
            P[i] = m.t_wc[last] + h * velocity
            source[i], segment[i], in_world[i] = "extrapolated", m.segment[last], world[last]
    return FramePoses(t, R, P, source, segment, in_world)
