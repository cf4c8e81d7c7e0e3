"""Ground-truth evaluation of tracks, on a synthetic depth map where the truth is known."""

from __future__ import annotations

import numpy as np
import pytest

from slam_bridge.errors import SlamError
from slam_bridge.evaluation.tracks import (
    KIND_EDGE,
    KIND_SKY,
    KIND_SURFACE,
    RenderTruth,
    TruthMap,
    evaluate_tracks,
    flatten_tracks,
)
from slam_bridge.frontend.base import KeyframeObservations
from slam_bridge.geometry.camera import project

W, H = 64, 48
K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])


def scene():
    """Three frames moving along x; a wall at z = 10 m on the left half, 5 m on the right half
    of frame 0, sky in the top rows (all frames share one depth map: the evaluation only reads
    the reference frames' maps, frame 0 here)."""
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    t = np.array([[0.0, 0, 0], [0.3, 0, 0], [0.6, 0, 0]])
    depth = np.full((H, W), 10.0, dtype=np.float32)
    depth[:, W // 2 :] = 5.0
    depth[:6] = 0.0
    return R, t, depth


def observe(uv0, z, R, t):
    """Pixels in the three frames of points seen at ``uv0`` with depth ``z`` in frame 0."""
    X = np.column_stack([uv0, np.ones(len(uv0))]) @ np.linalg.inv(K).T * z[:, None]
    return [project(K, R[f], t[f], X)[0] for f in range(3)]


def keyframes(uvs, ids):
    return [KeyframeObservations(0.1 * f, ids, uvs[f], f) for f in range(len(uvs))]


def test_exact_tracks_have_zero_error_and_shifted_ones_are_bad():
    R, t, depth = scene()
    uv0 = np.array([[10.3, 20.6], [20.0, 30.0], [45.2, 30.1]])
    uvs = observe(uv0, np.array([10.0, 10.0, 5.0]), R, t)
    uvs[2] = uvs[2].copy()
    uvs[2][1, 1] += 3.0  # point 1 is 3 px off in frame 2
    ev = evaluate_tracks(keyframes(uvs, np.array([7, 8, 9])), K, R, t, lambda f: depth)
    assert ev.reference.tolist() == [True] * 3 + [False] * 6
    np.testing.assert_allclose(ev.error_px[ev.table.point != 8], 0.0, atol=1e-6)
    assert ev.error_px[-2] == pytest.approx(3.0, abs=1e-6)
    assert ev.summary["bad_share"] == pytest.approx(1 / 6)
    assert ev.summary["keyframes"] == 3 and ev.summary["points"] == 3
    assert ev.summary["tracks_per_keyframe_mean"] == 3 and ev.summary["track_length_max"] == 3
    assert (ev.kind == KIND_SURFACE).all()
    # the best-fitting static point explains a pure shift along the epipolar line (x), not y
    assert ev.summary["bad_share_consistency"] > 0


def test_depth_edges_take_the_side_that_fits_and_sky_is_at_infinity():
    R, t, depth = scene()
    # on the depth edge (columns 31 | 32): a corner of the near wall, a corner of the far wall
    uv0 = np.array([[31.6, 30.0], [31.4, 20.0]])
    near, far = observe(uv0, np.array([5.0, 5.0]), R, t), observe(uv0, np.array([10.0, 10.0]), R, t)
    uvs = [np.vstack([near[f][0], far[f][1]]) for f in range(3)]
    ev = evaluate_tracks(keyframes(uvs, np.array([0, 1])), K, R, t, lambda f: depth)
    assert (ev.kind == KIND_EDGE).all()
    np.testing.assert_allclose(ev.error_px, 0.0, atol=1e-6)
    # sky: a point at infinity moves with the rotation only (none here: it stays put)
    sky = [np.array([[20.0, 2.0]])] * 3
    ev = evaluate_tracks(keyframes(sky, np.array([5])), K, R, t, lambda f: depth)
    assert (ev.kind == KIND_SKY).all()
    assert ev.error_px.max() < 0.01


def test_reobservations_and_active_mask():
    R, t, depth = scene()
    uv0 = np.array([[10.0, 20.0], [20.0, 30.0]])
    uvs = observe(uv0, np.array([10.0, 10.0]), R, t)
    kfs = [
        KeyframeObservations(0.0, np.array([0, 1]), uvs[0], 0),
        KeyframeObservations(0.1, np.array([0]), uvs[1][:1], 1),
        KeyframeObservations(0.2, np.array([0, 1]), uvs[2] + [[0.0, 0.0], [5.0, 0.0]], 2),
    ]
    ev = evaluate_tracks(kfs, K, R, t, lambda f: depth)
    assert ev.reobserved.tolist() == [False, False, False, False, True]
    assert ev.summary["reobservations"] == 1 and ev.summary["bad_share_reobserved"] == 1.0
    active = np.array([True, True, True, True, False])  # the loop rejected it
    assert evaluate_tracks(kfs, K, R, t, lambda f: depth, active=active).summary["bad_share"] == 0


def test_flatten_and_bad_input():
    table = flatten_tracks(
        [KeyframeObservations(0.0, np.array([3, 4]), np.zeros((2, 2)), 5)]
        + [KeyframeObservations(0.1, np.array([4]), np.ones((1, 2)), 7)]
    )
    assert table.keyframe.tolist() == [0, 0, 1] and table.frame.tolist() == [5, 5, 7]
    assert table.point.tolist() == [3, 4, 4]
    R, t, depth = scene()
    with pytest.raises(SlamError, match="refers to frame 7"):
        evaluate_tracks(table, K, R, t, lambda f: depth)
    with pytest.raises(SlamError, match="geoseg render folder"):
        RenderTruth("/nonexistent")


def test_truth_map_positions_and_rejection():
    R, t, depth = scene()
    uv0 = np.array([[10.0, 20.0], [20.0, 30.0], [45.0, 30.0]])
    uvs = observe(uv0, np.array([10.0, 10.0, 5.0]), R, t)
    uvs[1] = uvs[1] + [[0.0, 0.0], [0.0, 0.0], [0.0, 4.0]]
    for points in ("depth", "triangulate"):
        tm = TruthMap(K, (W, H), R, t, lambda f: depth, points=points, reject_px=2.0)
        for kf in keyframes(uvs[:2], np.array([0, 1, 2])):
            tm.add(kf)
        m = tm.map
        assert m.num_keyframes == 2 and m.triangulated[:2].all()
        np.testing.assert_allclose(m.t_wc, t[:2])
        if points == "depth":
            X = np.column_stack([uv0[:2], np.ones(2)]) @ np.linalg.inv(K).T * 10.0
            np.testing.assert_allclose(m.X_w[:2], X, atol=1e-9)
            assert m.obs_active.tolist() == [True] * 5 + [False]  # 4 px off: rejected
