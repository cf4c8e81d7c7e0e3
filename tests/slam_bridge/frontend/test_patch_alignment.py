"""Patch alignment against a reference keyframe on images warped by a known affine map."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slam_bridge.frontend.patch_alignment import align_patches, reference_patches

SIZE = (320, 240)


def _texture(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random(SIZE[::-1]).astype(np.float32) * 255, (0, 0), 2.0)
    return cv2.normalize(noise, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _warped(ref: np.ndarray, M: np.ndarray, gain: float = 1.0, bias: float = 0.0) -> np.ndarray:
    cur = cv2.warpAffine(ref, M, SIZE, flags=cv2.INTER_LINEAR).astype(np.float64)
    return np.clip(gain * cur + bias, 0, 255).astype(np.uint8)


@pytest.fixture
def scene():
    """A reference image, the current one scaled by 1.2 about the centre and shifted, darker,
    and 100 reference pixels with their true positions in the current image."""
    ref = _texture()
    s, c, t = 1.2, np.array([160.0, 120.0]), np.array([3.3, -1.7])
    M = np.array([[s, 0, (1 - s) * c[0] + t[0]], [0, s, (1 - s) * c[1] + t[1]]])
    rng = np.random.default_rng(1)
    ref_uv = np.column_stack([rng.uniform(70, 250, 100), rng.uniform(60, 180, 100)])
    true = ref_uv @ M[:, :2].T + M[:, 2]
    return ref, _warped(ref, M, gain=0.8, bias=20.0), M, ref_uv, true, rng


def test_alignment_removes_the_drift(scene):
    ref, cur, M, ref_uv, true, rng = scene
    start = true + rng.normal(0.0, 0.7, true.shape)  # drifted tracks
    T, warp_ok = reference_patches(ref, ref_uv, np.broadcast_to(M[:, :2], (100, 2, 2)), 4)
    res = align_patches(T, cur, start)
    assert warp_ok.all() and T.shape == (100, 81)
    assert res.ok.mean() >= 0.9 and res.uv.dtype == np.float32
    err = np.linalg.norm(res.uv[res.ok] - true[res.ok], axis=1)
    assert np.median(err) < 0.05 and err.max() < 0.3
    assert (res.zncc[res.ok] > 0.99).all()  # the change of brightness is modelled
    moved = np.linalg.norm(res.uv - start, axis=1)
    np.testing.assert_allclose(res.shift[res.ok], moved[res.ok], atol=1e-4)
    assert (moved[~res.ok] < 1e-4).all()  # the others stay where they were


def test_the_warp_matters(scene):
    """Without the change of scale (identity warp) the patches match worse and land farther."""
    ref, cur, M, ref_uv, true, rng = scene
    start = true + rng.normal(0.0, 0.7, true.shape)
    T, _ = reference_patches(ref, ref_uv, np.broadcast_to(M[:, :2], (100, 2, 2)), 4)
    T_id, _ = reference_patches(ref, ref_uv, np.broadcast_to(np.eye(2), (100, 2, 2)), 4)
    good, plain = align_patches(T, cur, start), align_patches(T_id, cur, start, min_zncc=-1.0)
    both = good.ok & plain.ok
    assert np.median(plain.zncc) < np.median(good.zncc)
    err = [np.median(np.linalg.norm(r.uv[both] - true[both], axis=1)) for r in (good, plain)]
    assert err[1] > 3 * err[0]


def test_alignments_it_cannot_trust_leave_the_tracks(scene):
    ref, cur, M, ref_uv, true, _ = scene
    A = np.broadcast_to(M[:, :2], (100, 2, 2))
    T, _ = reference_patches(ref, ref_uv, A, 4)
    far = align_patches(T, cur, true + [4.0, 0.0], max_shift=2.0)  # beyond max_shift
    assert not far.ok.any()
    np.testing.assert_array_equal(far.uv, (true + [4.0, 0.0]).astype(np.float32))
    flat = align_patches(T, np.full(SIZE[::-1], 128, np.uint8), true)  # nothing to match
    assert not flat.ok.any() and (flat.zncc == 0).all()
    other = align_patches(T, _texture(seed=5), true)  # another image: no correlation
    assert other.ok.mean() < 0.1


def test_singular_warps_are_flagged_and_empty_input():
    ref = _texture()
    A = np.zeros((2, 2, 2))
    A[0] = np.eye(2)
    _, ok = reference_patches(ref, np.array([[50.0, 50.0], [60.0, 60.0]]), A, 3)
    assert ok.tolist() == [True, False]
    res = align_patches(np.zeros((0, 49)), ref, np.zeros((0, 2)))
    assert res.uv.shape == (0, 2) and res.ok.shape == (0,)
