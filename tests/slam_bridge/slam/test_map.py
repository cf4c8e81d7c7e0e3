"""The SLAM map: growth, views, attributes, segments, pose prediction, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.errors import SlamError
from slam_bridge.geometry.lie import so3_exp
from slam_bridge.slam.map import Map


def test_keyframes_points_and_observations_grow_in_order():
    m = Map(np.eye(3), (640, 480))
    assert m.num_keyframes == m.num_points == m.num_observations == 0
    k0 = m.add_keyframe(0.0, [3, 1], np.array([[1.0, 2.0], [3.0, 4.0]]))
    label = m.add_attribute("label", (), np.int8, -1)
    assert label.shape == (4,) and np.all(label == -1)
    k1 = m.add_keyframe(0.5, np.arange(40), np.zeros((40, 2)))
    assert (k0, k1) == (0, 1)
    assert m.num_points == 40 and m.attribute("label").shape == (40,)
    assert np.all(np.isnan(m.X_w)) and not m.triangulated.any()
    np.testing.assert_array_equal(m.starts, [0, 2, 42])
    np.testing.assert_array_equal(m.obs_keyframe, [0, 0] + [1] * 40)
    np.testing.assert_array_equal(m.keyframe_observations(0), [0, 1])
    np.testing.assert_array_equal(m.obs_point[:2], [3, 1])
    assert m.obs_active.all()
    # the views write through, and survive growth once re-read
    m.X_w[5] = [1.0, 2.0, 3.0]
    m.triangulated[5] = True
    for i in range(30):  # several doublings
        m.add_keyframe(1.0 + i, [100 + i], np.ones((1, 2)))
    np.testing.assert_array_equal(m.X_w[5], [1.0, 2.0, 3.0])
    ids, X = m.triangulated_points()
    np.testing.assert_array_equal(ids, [5])
    assert m.num_points == 130 and m.attribute("label").shape == (130,)
    np.testing.assert_array_equal(m.R_wc[-1], np.eye(3))


def test_pose_prediction_and_segments():
    m = Map(np.eye(3), (64, 48))
    assert m.predict_pose(1.0) is None
    m.add_keyframe(0.0, [0], np.zeros((1, 2)))
    m.add_keyframe(1.0, [0], np.zeros((1, 2)))
    R1 = so3_exp(np.array([0.0, 0.1, 0.0]))
    m.set_pose(1, R1, np.array([1.0, 0.0, 2.0]))
    R, t = m.predict_pose(2.0)  # constant velocity: one more step of the same motion
    np.testing.assert_allclose(R, R1 @ R1, atol=1e-12)
    np.testing.assert_allclose(t, [2.0, 0.0, 4.0])
    m.add_keyframe(2.0, [1], np.zeros((1, 2)))
    assert m.start_segment(2) == 1
    np.testing.assert_array_equal(m.segment, [0, 0, 1])
    m.add_keyframe(3.0, [1], np.zeros((1, 2)))
    assert m.segment[-1] == 1
    assert m.predict_pose(4.0) is not None  # keyframes 2 and 3 share the segment
    m.add_keyframe(4.0, [1], np.zeros((1, 2)))
    m.start_segment(4)
    assert m.predict_pose(5.0) is None  # the newest keyframe opened a segment alone


def test_bad_input():
    with pytest.raises(GeosegError, match="K"):
        Map(np.full((3, 3), np.nan), (64, 48))
    m = Map(np.eye(3), (64, 48))
    m.add_keyframe(1.0, [0], np.zeros((1, 2)))
    with pytest.raises(SlamError, match="later"):
        m.add_keyframe(1.0, [0], np.zeros((1, 2)))
    with pytest.raises(SlamError, match="twice"):
        m.add_keyframe(2.0, [0, 0], np.zeros((2, 2)))
    with pytest.raises(SlamError, match="non-negative"):
        m.add_keyframe(2.0, [-1], np.zeros((1, 2)))
    with pytest.raises(GeosegError, match="uv"):
        m.add_keyframe(2.0, [1], np.full((1, 2), np.nan))
    with pytest.raises(GeosegError, match="uv"):
        m.add_keyframe(2.0, [1, 2], np.zeros((3, 2)))
    with pytest.raises(SlamError, match="finite"):
        m.add_keyframe(float("nan"), [1], np.zeros((1, 2)))
    m.add_attribute("w", (), float, 0.0)
    with pytest.raises(SlamError, match="exists"):
        m.add_attribute("w", (), float, 0.0)
    with pytest.raises(SlamError, match="not registered"):
        m.attribute("normal")
    assert m.num_keyframes == 1 and m.num_observations == 1  # refused keyframes left nothing


def test_the_core_does_not_import_the_synthetic_world():
    """Only ``slam_bridge.experiments`` builds synthetic sequences: the SLAM core, its sources
    and its evaluation import neither ``geoseg.synth`` nor torch."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import slam_bridge.slam.loop, slam_bridge.slam.config, slam_bridge.evaluation.tables_ch3\n"
        "import slam_bridge.experiments.simulated_tracks\n"
        "bad = [m for m in sys.modules if m.startswith('geoseg.synth') or m == 'torch']\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
