"""Tests for the essential-matrix relative-pose baseline and its error metrics."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geoseg.errors import GeosegError
from geoseg.models.relpose import relative_pose_labels
from geoseg.reloc.essential_baseline import (
    detect_and_match,
    direction_error_deg,
    estimate_relative_pose,
    relative_pose_from_matches,
    rotation_error_deg,
)

W, H = 640, 480
K = np.array([[500.0, 0.0, W / 2], [0.0, 500.0, H / 2], [0.0, 0.0, 1.0]])
# camera looking north (+y) in a z-up world: x_c = east, y_c = down, z_c = north
R_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def _poses():
    """Two camera-to-world poses with a known, non-trivial relative pose."""
    R_a = _rot("z", 10.0) @ R_NORTH @ _rot("x", 3.0)
    t_a = np.array([2.0, -1.0, 1.5])
    R_b = _rot("z", 2.0) @ R_NORTH @ _rot("x", -2.0) @ _rot("z", 1.5)
    t_b = t_a + np.array([1.2, 0.8, 0.3])
    return R_a, t_a, R_b, t_b


def _project(X_w, R_wc, t_wc):
    X_c = (X_w - t_wc) @ R_wc  # R_wc^T (X_w - t_wc), row-wise
    uv = X_c @ K.T
    return uv[:, :2] / uv[:, 2:3], X_c[:, 2]


@pytest.mark.parametrize("robust", ["magsac", "ransac"])
def test_exact_correspondences_match_relative_pose_labels(robust: str) -> None:
    R_a, t_a, R_b, t_b = _poses()
    rng = np.random.default_rng(0)
    # points 8-30 m in front of camera a, spread over the image
    n = 200
    z = rng.uniform(8.0, 30.0, n)
    uv = rng.uniform([20, 20], [W - 20, H - 20], (n, 2))
    X_c = np.linalg.solve(K, np.c_[uv, np.ones(n)].T).T * z[:, None]
    X_w = X_c @ R_a.T + t_a
    uv_a, z_a = _project(X_w, R_a, t_a)
    uv_b, z_b = _project(X_w, R_b, t_b)
    keep = (z_b > 0) & (uv_b[:, 0] > 0) & (uv_b[:, 0] < W) & (uv_b[:, 1] > 0) & (uv_b[:, 1] < H)
    assert keep.sum() > 100
    est = relative_pose_from_matches(
        uv_a[keep], uv_b[keep], K, ransac_threshold_px=0.5, robust=robust
    )
    assert est.ok, est.reason
    R_gt, t_gt = relative_pose_labels(R_a, t_a, R_b, t_b)
    assert rotation_error_deg(est.R_ab, R_gt) < 0.1
    assert direction_error_deg(est.t_dir_ab, t_gt) < 0.5
    assert est.n_inliers >= 0.9 * keep.sum()
    # the direction points from a towards b: base camera a + ray hits b's centre
    np.testing.assert_allclose(
        R_a @ est.t_dir_ab, (t_b - t_a) / np.linalg.norm(t_b - t_a), atol=1e-2
    )
    # swapping the images gives the inverse relative pose
    inv = relative_pose_from_matches(
        uv_b[keep], uv_a[keep], K, ransac_threshold_px=0.5, robust=robust
    )
    R_gt_ba, t_gt_ba = relative_pose_labels(R_b, t_b, R_a, t_a)
    assert rotation_error_deg(inv.R_ab, R_gt_ba) < 0.1
    assert direction_error_deg(inv.t_dir_ab, t_gt_ba) < 0.5


def test_outliers_are_rejected() -> None:
    R_a, t_a, R_b, t_b = _poses()
    rng = np.random.default_rng(1)
    n = 300
    X_c = np.c_[rng.uniform(-6, 6, n), rng.uniform(-3, 3, n), rng.uniform(8, 30, n)]
    X_w = X_c @ R_a.T + t_a
    uv_a, _ = _project(X_w, R_a, t_a)
    uv_b, _ = _project(X_w, R_b, t_b)
    uv_b = uv_b + rng.normal(0, 0.3, uv_b.shape)
    bad = rng.choice(n, 90, replace=False)
    uv_b[bad] = rng.uniform([0, 0], [W, H], (90, 2))
    est = relative_pose_from_matches(uv_a, uv_b, K)
    assert est.ok
    R_gt, t_gt = relative_pose_labels(R_a, t_a, R_b, t_b)
    assert rotation_error_deg(est.R_ab, R_gt) < 0.5
    assert direction_error_deg(est.t_dir_ab, t_gt) < 3.0
    assert est.inliers[bad].mean() < 0.1


def test_too_few_matches_is_a_failure_not_garbage() -> None:
    rng = np.random.default_rng(0)
    uv = rng.uniform(0, 400, (6, 2))
    est = relative_pose_from_matches(uv, uv + 3.0, K)
    assert not est.ok and "too few matches" in est.reason
    assert np.isnan(est.R_ab).all() and np.isnan(est.t_dir_ab).all()
    est = relative_pose_from_matches(np.zeros((0, 2)), np.zeros((0, 2)), K)
    assert not est.ok and est.n_matches == 0
    # random correspondences: no consistent geometry with enough support
    est = relative_pose_from_matches(
        rng.uniform(0, 600, (40, 2)), rng.uniform(0, 600, (40, 2)), K, min_inliers=30
    )
    assert not est.ok and "inliers" in est.reason


def test_pure_rotation_and_identical_views_fail() -> None:
    rng = np.random.default_rng(2)
    R_a, t_a, _, _ = _poses()
    X_c = np.c_[rng.uniform(-6, 6, 150), rng.uniform(-3, 3, 150), rng.uniform(8, 30, 150)]
    X_w = X_c @ R_a.T + t_a
    uv_a, _ = _project(X_w, R_a, t_a)
    est = relative_pose_from_matches(uv_a, uv_a.copy(), K)
    assert not est.ok and "parallax" in est.reason
    uv_b, _ = _project(X_w, R_a @ _rot("y", 3.0), t_a)  # same centre, rotated camera
    est = relative_pose_from_matches(uv_a, uv_b, K)
    assert not est.ok, est


def test_bad_arguments_raise() -> None:
    uv = np.zeros((20, 2))
    with pytest.raises(GeosegError, match="uv_b"):
        relative_pose_from_matches(uv, np.zeros((19, 2)), K)
    with pytest.raises(GeosegError, match="K"):
        relative_pose_from_matches(uv, uv, np.eye(3) * 0)
    with pytest.raises(GeosegError, match="method"):
        detect_and_match(np.zeros((8, 8), np.uint8), np.zeros((8, 8), np.uint8), method="surf")
    with pytest.raises(GeosegError, match="image_a"):
        detect_and_match(np.zeros((8, 8, 4), np.uint8), np.zeros((8, 8), np.uint8))


# ----------------------------------------------------------------------------- images


def _texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """Corner-rich texture: random grey rectangles and discs over smooth noise."""
    noise = cv2.resize(rng.uniform(0, 255, (16, 16)).astype(np.float32), (size, size))
    tex = noise.astype(np.uint8)
    for _ in range(4000):
        x, y = rng.integers(0, size, 2)
        w, h = rng.integers(4, 24, 2)
        grey = int(rng.integers(0, 256))
        if rng.uniform() < 0.5:
            cv2.rectangle(tex, (int(x), int(y)), (int(x + w), int(y + h)), grey, -1)
        else:
            cv2.circle(tex, (int(x), int(y)), int(w // 2), grey, -1)
    return cv2.GaussianBlur(tex, (3, 3), 0)


# planes n . X = c with an in-plane basis (e1, e2), metres -> texture pixels
_PLANES = [
    (np.array([1.0, 0, 0]), -4.0, np.array([0, 1.0, 0]), np.array([0, 0, 1.0])),  # west wall
    (np.array([1.0, 0, 0]), 4.0, np.array([0, 1.0, 0]), np.array([0, 0, 1.0])),  # east wall
    (np.array([0, 1.0, 0]), 25.0, np.array([1.0, 0, 0]), np.array([0, 0, 1.0])),  # far wall
    (np.array([0, 0, 1.0]), 0.0, np.array([1.0, 0, 0]), np.array([0, 1.0, 0])),  # ground
]


def _render(R_wc, t_wc, textures) -> np.ndarray:
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays_c = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    rays_w = rays_c @ R_wc.T
    best = np.full((H, W), np.inf)
    out = np.zeros((H, W), np.uint8)
    for (n, c, e1, e2), tex in zip(_PLANES, textures):
        denom = rays_w @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (c - t_wc @ n) / denom
        s = np.where(np.isfinite(s), s, -1.0)
        hit = (s > 0) & (s < best)
        X = t_wc + np.maximum(s, 0.0)[..., None] * rays_w
        px = (X @ e1 * 20.0) % tex.shape[1]
        py = (X @ e2 * 20.0) % tex.shape[0]
        img = cv2.remap(
            tex,
            px.astype(np.float32),
            py.astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )
        out[hit] = img[hit]
        best[hit] = s[hit]
    return out


@pytest.mark.parametrize("method", ["orb", "sift"])
def test_images_end_to_end_agree_with_labels(method: str) -> None:
    rng = np.random.default_rng(3)
    textures = [_texture(rng) for _ in _PLANES]
    R_a = R_NORTH @ _rot("x", -8.0)  # pitch down a bit to see the ground
    t_a = np.array([0.0, 0.0, 1.6])
    R_b = _rot("z", 4.0) @ R_a
    t_b = t_a + np.array([1.0, 1.5, 0.1])
    img_a, img_b = _render(R_a, t_a, textures), _render(R_b, t_b, textures)
    uv_a, uv_b = detect_and_match(img_a, img_b, method=method)
    assert len(uv_a) > 50
    est = estimate_relative_pose(img_a, img_b, K, method=method)
    assert est.ok, est.reason
    R_gt, t_gt = relative_pose_labels(R_a, t_a, R_b, t_b)
    assert rotation_error_deg(est.R_ab, R_gt) < 0.5
    assert direction_error_deg(est.t_dir_ab, t_gt) < 2.0


def test_blank_images_fail_cleanly() -> None:
    blank = np.full((H, W, 3), 128, np.uint8)
    est = estimate_relative_pose(blank, blank, K)
    assert not est.ok and est.n_matches == 0 and "too few matches" in est.reason


def test_images_that_do_not_fit_one_K_are_refused() -> None:
    image = np.full((H, W, 3), 128, np.uint8)
    upscaled = np.full((2 * H, 2 * W, 3), 128, np.uint8)
    with pytest.raises(GeosegError, match="one K holds for one image size"):
        estimate_relative_pose(image, upscaled, K)
    small = np.full((H // 4, W // 4, 3), 128, np.uint8)
    with pytest.raises(GeosegError, match="principal point"):
        estimate_relative_pose(small, small, K)


def test_error_metrics() -> None:
    R = _rot("z", 30.0)
    assert rotation_error_deg(R, np.eye(3)) == pytest.approx(30.0)
    assert rotation_error_deg(np.stack([R, R]), np.stack([R, np.eye(3)])) == pytest.approx([0, 30])
    assert direction_error_deg([1, 0, 0], [0, 2, 0]) == pytest.approx(90.0)
    assert direction_error_deg([1, 0, 0], [-1, 0, 0]) == pytest.approx(180.0)
    assert np.isnan(direction_error_deg([np.nan] * 3, [1, 0, 0]))
    with pytest.raises(GeosegError):
        rotation_error_deg(np.eye(3), np.eye(2))
