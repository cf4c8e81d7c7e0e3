"""Network outputs accumulated on map points (the bridge's 2D -> 3D step) on a toy map."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.dirichlet import MaxProbabilityFilter
from slam_bridge.bridge.evidence import PointEvidence
from slam_bridge.errors import SlamError
from slam_bridge.slam.map import Map

K_CLASSES = 3
SIZE = (8, 6)  # (W, H)


def _map() -> Map:
    """Two keyframes: points 0 and 1 seen in both, point 2 in the second only; the second
    camera is turned 90 degrees about the world z axis."""
    m = Map(np.array([[10.0, 0, 3.5], [0, 10.0, 2.5], [0, 0, 1]]), SIZE)
    m.add_keyframe(0.0, np.array([0, 1]), np.array([[1.0, 1.0], [6.2, 4.4]]))
    m.add_keyframe(1.0, np.array([0, 1, 2]), np.array([[1.4, 0.6], [6.0, 1.0], [3.0, 3.0]]))
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    m.set_pose(1, Rz, np.zeros(3))
    return m


def _probs(building_left: bool, size=SIZE) -> np.ndarray:
    """``(H, W, 3)``: class 0 on the left half and class 1 on the right, or the reverse."""
    W, H = size
    p = np.zeros((H, W, K_CLASSES))
    left, right = (0, 1) if building_left else (1, 0)
    p[:, : W // 2, left] = 0.7
    p[:, : W // 2, 2] = 0.3
    p[:, W // 2 :, right] = 0.6
    p[:, W // 2 :, 2] = 0.4
    return p


def test_mean_vote_and_normals():
    m = _map()
    ev = PointEvidence(m, K_CLASSES)
    W, H = SIZE
    n0 = np.zeros((H, W, 3))
    n0[..., 2] = -1.0  # every pixel faces the camera
    n0[:, W // 2 :] = 0.0  # no normal on the right half
    assert ev.add_keyframe(0, _probs(True), n0) == 2
    n1 = np.zeros((H, W, 3))
    n1[..., 0] = 1.0  # camera +x
    assert ev.add_keyframe(1, _probs(False), n1) == 3

    mean = ev.mean_probs()
    np.testing.assert_allclose(mean[0], [0.35, 0.35, 0.3])  # (0.7, 0, 0.3) and (0, 0.7, 0.3)
    np.testing.assert_allclose(mean[1], [0.3, 0.3, 0.4])  # (0, .6, .4) then (.6, 0, .4)
    np.testing.assert_allclose(mean[2], [0.0, 0.7, 0.3])  # pixel (3, 3): column 3 is left
    np.testing.assert_array_equal(ev.samples, [2, 2, 1])
    np.testing.assert_array_equal(ev.labels(), [0, 0, 1])  # ties go to the lower id
    n = ev.normals()
    # keyframe 0 (identity): camera -z is world -z; keyframe 1: camera +x is world +y
    np.testing.assert_allclose(n[0], np.array([0.0, 1.0, -1.0]) / np.sqrt(2))
    np.testing.assert_allclose(n[1], [0.0, 1.0, 0.0])  # keyframe 0 gave no normal there
    np.testing.assert_allclose(n[2], [0.0, 1.0, 0.0])


def test_maps_at_half_the_image_size():
    """A network run on a downsized image: its maps are sampled where the pixels fall."""
    full, half = PointEvidence(_map(), K_CLASSES), PointEvidence(_map(), K_CLASSES)
    for k, left in ((0, True), (1, False)):
        full.add_keyframe(k, _probs(left))
        half.add_keyframe(k, _probs(left, size=(4, 3)))
    np.testing.assert_array_equal(half.mean_probs(), full.mean_probs())
    with pytest.raises(SlamError, match="aspect ratio"):
        PointEvidence(_map(), K_CLASSES).add_keyframe(0, _probs(True, size=(4, 6)))


def test_points_added_later_and_smoothing():
    m = _map()
    calls = []

    def first_class(probs, rows, cols):  # a sampler that sees the map and the pixels
        calls.append((probs.shape, rows.size))
        return np.eye(K_CLASSES)[np.zeros(rows.size, np.int64)]

    ev = PointEvidence(m, K_CLASSES, smooth_at=first_class)
    ev.add_keyframe(1, _probs(True))
    assert calls == [((SIZE[1], SIZE[0], K_CLASSES), 3)]
    np.testing.assert_array_equal(ev.labels()[:3], [0, 0, 0])
    m.add_keyframe(2.0, np.array([5]), np.array([[0.0, 0.0]]))  # the map grows
    ev.add_keyframe(2, _probs(True))
    np.testing.assert_array_equal(ev.samples, [1, 1, 1, 0, 0, 1])
    assert np.isnan(ev.mean_probs()[3]).all() and ev.labels()[3] == -1
    assert np.isnan(ev.normals()).all()  # no normal map given


def test_a_keyframe_without_a_pose_gives_no_normals():
    m = _map()
    m.set_pose(1, np.full((3, 3), np.nan), np.full(3, np.nan))  # lost, not placed
    ev = PointEvidence(m, K_CLASSES)
    W, H = SIZE
    normals = np.zeros((H, W, 3))
    normals[..., 2] = -1.0
    ev.add_keyframe(1, _probs(True), normals)
    ev.add_keyframe(0, _probs(True), normals)
    np.testing.assert_array_equal(ev.samples, [2, 2, 1])  # probabilities from both
    np.testing.assert_allclose(ev.normals()[0], [0, 0, -1])  # normals from keyframe 0 only
    assert np.isnan(ev.normals()[2]).all()


def test_rejected_observations_are_not_sampled():
    m = _map()
    m.obs_active[m.keyframe_observations(1)[0]] = False  # point 0 in keyframe 1
    ev = PointEvidence(m, K_CLASSES)
    assert ev.add_keyframe(1, _probs(True)) == 2
    assert ev.samples[0] == 0


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda p: p[:-1], "probs"),
        (lambda p: p[..., :2], "probs"),
        (lambda p: p * 2, "sum to 1"),
        (lambda p: np.where(p > 0.5, np.nan, p), "NaN"),
    ],
)
@pytest.mark.parametrize("window", [None, 3])
def test_bad_probability_maps(change, message, window):
    """The same errors with the pixels' own vectors and with a filter's box means."""
    smooth_at = (
        None
        if window is None
        else MaxProbabilityFilter(num_classes=K_CLASSES, building_class=1, window=window).smooth_at
    )
    ev = PointEvidence(_map(), K_CLASSES, smooth_at=smooth_at)
    with pytest.raises(SlamError, match=message):
        ev.add_keyframe(0, change(_probs(True)))


def test_bad_calls():
    m = _map()
    ev = PointEvidence(m, K_CLASSES)
    with pytest.raises(SlamError, match="keyframe 5"):
        ev.add_keyframe(5, _probs(True))
    ev.add_keyframe(0, _probs(True))
    with pytest.raises(SlamError, match="added already"):
        ev.add_keyframe(0, _probs(True))
    with pytest.raises(SlamError, match="normals"):
        ev.add_keyframe(1, _probs(True), np.zeros((2, 2, 3)))
    with pytest.raises(SlamError, match="exists already"):
        PointEvidence(m, K_CLASSES)  # one accumulator per map
    with pytest.raises(SlamError, match="num_classes"):
        PointEvidence(Map(np.eye(3), SIZE), 1)
