"""The vertical direction from an image's vertical line segments."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geoseg.errors import ConfigError
from slam_bridge.frontend.vertical_lines import (
    VerticalLinesConfig,
    detect_segments,
    vertical_direction,
)
from slam_bridge.geometry.lie import so3_exp

K = np.array([[457.0, 0.0, 320.0], [0.0, 457.0, 240.0], [0.0, 0.0, 1.0]])
DOWN_W = np.array([0.0, 0.0, -1.0])


def _camera(tilt_deg: tuple[float, float]) -> np.ndarray:
    """``R_wc`` of a camera looking along +y (x right, y down), tilted about x and y."""
    level = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # columns: x, y, z
    tilt = so3_exp(np.radians([tilt_deg[0], tilt_deg[1], 0.0]))
    return tilt @ level


def _segments(R_wc, n_vertical=30, n_other=30, noise_px=0.3, seed=0):
    """Pixel segments of vertical edges (facade corners, poles) and of other edges."""
    rng = np.random.default_rng(seed)
    base = np.column_stack([rng.uniform(-12, 12, n_vertical), rng.uniform(8, 30, n_vertical)])
    z0 = rng.uniform(-1.0, 2.0, n_vertical)
    top = np.column_stack([base, z0 + rng.uniform(2.0, 6.0, n_vertical)])
    bottom = np.column_stack([base, z0])
    a = rng.uniform([-12, 8, -1], [12, 30, 6], size=(n_other, 3))
    b = a + rng.normal(size=(n_other, 3)) * [3.0, 3.0, 0.3]  # mostly horizontal edges
    ends = np.vstack([np.hstack([bottom, top]), np.hstack([a, b])]).reshape(-1, 3)
    X_c = ends @ R_wc  # t_wc = 0: X_c = R_wc^T X_w
    uv = X_c @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    return uv.reshape(-1, 4) + rng.normal(scale=noise_px, size=(n_vertical + n_other, 4))


def _angle_deg(a, b):
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def test_a_tilted_cameras_vertical_is_recovered_from_its_segments():
    R_wc = _camera((2.0, -1.5))
    truth = R_wc.T @ DOWN_W
    predicted = so3_exp(np.radians([1.2, -0.8, 0.5])) @ truth  # the SLAM's guess, ~1.5 deg off
    est = vertical_direction(_segments(R_wc), K, predicted)
    assert est is not None and est.num_segments >= 20
    assert _angle_deg(est.down_c, truth) < 0.25  # from 1.3 deg; exact without the pixel noise
    np.testing.assert_allclose(est.basis @ est.down_c, 0.0, atol=1e-12)
    np.testing.assert_allclose(est.basis @ est.basis.T, np.eye(2), atol=1e-12)
    # the error lies within a few standard deviations of the reported covariance
    e = est.basis @ (truth - est.down_c)
    assert e @ np.linalg.solve(est.covariance, e) < 12.0
    assert np.all(np.linalg.eigvalsh(est.covariance) >= np.radians(0.2) ** 2 * 0.999)


def test_no_vertical_without_enough_agreeing_segments():
    R_wc = _camera((0.0, 0.0))
    truth = R_wc.T @ DOWN_W
    assert vertical_direction(np.zeros((0, 4)), K, truth) is None
    assert vertical_direction(_segments(R_wc, n_vertical=5), K, truth) is None
    # a prediction far off: the gate leaves out every vertical edge
    far = so3_exp(np.radians([0.0, 0.0, 10.0])) @ truth  # rolled about the optical axis
    assert vertical_direction(_segments(R_wc), K, far) is None
    short = VerticalLinesConfig(min_length_px=5000.0)
    assert vertical_direction(_segments(R_wc), K, truth, short) is None


def test_detect_segments_finds_the_edges_of_a_drawn_facade():
    img = np.full((240, 320), 40, np.uint8)
    cv2.rectangle(img, (100, 30), (180, 200), 220, -1)  # a bright wall: two vertical edges
    seg = detect_segments(np.dstack([img] * 3))
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    vertical = (np.abs(seg[:, 2] - seg[:, 0]) < 2.0) & (length > 120)
    assert {round(x / 10) for x in seg[vertical, 0]} >= {10, 18}
    assert detect_segments(np.zeros((50, 50), np.uint8)).shape == (0, 4)


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"gate_deg": 0.0}, "gate_deg"),
        ({"inlier_deg": 5.0, "gate_deg": 4.0}, "inlier_deg"),
        ({"min_segments": 1}, "min_segments"),
        ({"floor_deg": -1.0}, "floor_deg"),
    ],
)
def test_bad_settings_are_refused(kw, match):
    with pytest.raises(ConfigError, match=match):
        VerticalLinesConfig(**kw)
