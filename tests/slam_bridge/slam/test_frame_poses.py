"""A pose for every frame: keyframes kept, frames between interpolated, the tail extrapolated."""

from __future__ import annotations

import types

import numpy as np

from slam_bridge.geometry.lie import so3_exp
from slam_bridge.slam.frame_poses import frame_poses


def test_frames_between_keyframes_are_interpolated_and_marked():
    kt = np.array([0.0, 0.2, 0.4])
    R = np.stack([so3_exp(np.array([0.0, 0.1 * i, 0.0])) for i in range(3)])
    T = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    m = types.SimpleNamespace(timestamps=kt, R_wc=R, t_wc=T, segment=np.zeros(3, int))
    result = types.SimpleNamespace(map=m, placed=np.ones(3, bool), in_world=np.ones(3, bool))
    poses = frame_poses(result, 0.1 * np.arange(7))
    assert (
        list(poses.source) == ["keyframe", "interpolated"] * 2 + ["keyframe"] + ["extrapolated"] * 2
    )
    np.testing.assert_allclose(poses.t_wc[1], [0.5, 0, 0])
    np.testing.assert_allclose(poses.R_wc[3], so3_exp(np.array([0.0, 0.15, 0.0])), atol=1e-12)
    np.testing.assert_allclose(poses.t_wc[6], [3.0, 0, 0])
    assert poses.has_pose.all() and poses.in_world.all()
    m.segment = np.array([0, 1, 1])  # a new segment: nothing interpolated across it
    poses = frame_poses(result, 0.1 * np.arange(5))
    assert poses.source[1] == "none" and np.isnan(poses.t_wc[1]).all()
    assert poses.source[3] == "interpolated"
