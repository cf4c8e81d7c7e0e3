"""The chapter-4 pictures' geometry: facade outlines clipped at the camera's near plane."""

from __future__ import annotations

import numpy as np

from slam_bridge.experiments.buildings_ch4_plots import clip_near


def test_clip_near_keeps_a_polygon_in_front_and_drops_one_behind():
    front = np.array([[0, 0, 2.0], [1, 0, 2.0], [1, 1, 3.0], [0, 1, 3.0]])
    np.testing.assert_allclose(clip_near(front, near=1.0), front)
    assert clip_near(-front, near=1.0).shape == (0, 3)


def test_clip_near_cuts_a_facade_beside_the_camera_at_the_plane():
    # a wall 2 m to the right running from 1 m behind the camera to 3 m ahead, 0-4 m high
    wall = np.array([[2, 0, -1.0], [2, 0, 3.0], [2, -4, 3.0], [2, -4, -1.0]])
    clipped = clip_near(wall, near=1.0)
    expected = [[2, 0, 1.0], [2, 0, 3.0], [2, -4, 3.0], [2, -4, 1.0]]
    assert sorted(map(tuple, clipped.tolist())) == sorted(map(tuple, expected))
    assert np.all(clipped[:, 2] >= 1.0 - 1e-12)


def test_no_reprojection_picture_when_the_runs_share_no_placed_keyframe(tmp_path):
    from slam_bridge.experiments.buildings_ch4_plots import _reprojections

    def run(timestamps, in_world):
        n = len(timestamps)
        return {
            "timestamps": np.asarray(timestamps, float),
            "in_world": np.asarray(in_world, bool),
            "t_wc": np.zeros((n, 3)),
            "R_wc": np.tile(np.eye(3), (n, 1, 1)),
            "K": np.eye(3),
        }

    runs = {"nobuild": run([0.0, 0.2, 0.4], [1, 1, 0]), "bayes": run([0.1, 0.4], [1, 1])}
    assert _reprojections(tmp_path, "exact", runs, tmp_path, None, np.arange(5) * 0.1) is None
    assert not list(tmp_path.iterdir())
