"""Triangulation, two-view initialisation and PnP on synthetic views."""

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.geometry.lie import so3_exp, so3_log
from slam_bridge.geometry.multiview import pnp, ray_parallax_deg, triangulate, two_view_init


def test_triangulation_exact_on_noiseless_views(street_noiseless):
    s = street_noiseless
    for it in (0, 3):
        res = triangulate(
            s.K, s.R_wc, s.t_wc, s.obs_cameras, s.obs_points, s.uv, refine_iterations=it
        )
        assert res.valid.mean() > 0.9
        np.testing.assert_allclose(res.X_w, s.X_w, atol=1e-6)
        assert np.nanmax(res.rms_px) < 1e-6
        assert res.num_views.min() >= 3


def test_triangulation_noisy_refinement_helps(street):
    s = street
    dlt = triangulate(s.K, s.R_wc, s.t_wc, s.obs_cameras, s.obs_points, s.uv, refine_iterations=0)
    ref = triangulate(s.K, s.R_wc, s.t_wc, s.obs_cameras, s.obs_points, s.uv, refine_iterations=5)
    ok = dlt.valid & ref.valid
    assert np.nanmean(ref.rms_px[ok]) <= np.nanmean(dlt.rms_px[ok]) + 1e-9
    assert np.nanmean(ref.rms_px[ok]) < 1.5


def test_triangulation_flags_cheirality_and_parallax():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R = np.stack([np.eye(3)] * 2)
    t = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    X = np.array([[0.5, 0.2, 5.0], [0.3, 0.1, 1e4]])
    cams = np.array([0, 1, 0, 1])
    pts = np.array([0, 0, 1, 1])
    uv = np.concatenate(
        [(K @ (X[p] - t[c]))[:2] / (X[p] - t[c])[2] for c, p in zip(cams, pts)]
    ).reshape(-1, 2)
    res = triangulate(K, R, t, cams, pts, uv, min_parallax_deg=1.0)
    assert res.valid.tolist() == [True, False]  # the far point has ~0.006 deg parallax
    assert res.parallax_deg[1] < 0.1
    # the mirrored point (behind both cameras) projects the same for a pure DLT sign flip:
    # simulate by flipping the cameras to look backwards
    Rb = np.stack([so3_exp(np.array([0.0, np.pi, 0.0]))] * 2)
    res_b = triangulate(K, Rb, t, cams[:2], pts[:2], uv[:2])
    assert not res_b.in_front[0] and not res_b.valid[0]


def test_triangulation_bad_input(street):
    s = street
    uv = s.uv.copy()
    uv[0, 1] = np.nan
    with pytest.raises(GeosegError):
        triangulate(s.K, s.R_wc, s.t_wc, s.obs_cameras, s.obs_points, uv)


def _two_views(rng, n=80):
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(6, 15, n)])
    R2 = so3_exp(np.array([0.02, -0.05, 0.01]))
    t2 = np.array([0.8, 0.1, 0.3])
    x1 = X @ K.T
    Xc2 = (X - t2) @ R2  # R2^T (X - t2)
    x2 = Xc2 @ K.T
    return K, X, R2, t2, x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]


def test_two_view_init_recovers_relative_pose():
    rng = np.random.default_rng(0)
    K, X, R2, t2, uv1, uv2 = _two_views(rng)
    res = two_view_init(K, uv1, uv2, threshold_px=0.5)
    assert np.linalg.norm(so3_log(R2.T @ res.R_wc)) < 1e-3
    np.testing.assert_allclose(res.t_wc, t2 / np.linalg.norm(t2), atol=1e-3)
    assert res.inliers.mean() > 0.9
    with pytest.raises(GeosegError):
        two_view_init(K, uv1[:4], uv2[:4])


def test_pnp_recovers_pose_with_outliers():
    rng = np.random.default_rng(1)
    K, X, R2, t2, _, uv2 = _two_views(rng, 100)
    uv = uv2.copy()
    uv[:10] += rng.uniform(30, 60, size=(10, 2))
    res = pnp(K, X, uv)
    assert np.linalg.norm(so3_log(R2.T @ res.R_wc)) < 1e-6
    np.testing.assert_allclose(res.t_wc, t2, atol=1e-6)
    assert not res.inliers[:10].any() and res.inliers[10:].all()
    assert res.rms_px < 1e-6
    with pytest.raises(GeosegError):
        pnp(K, X[:3], uv[:3])


def test_ray_parallax_deg_is_the_widest_angle_to_the_first_view():
    # point 0 seen from x = 0, 1 and -2 at 10 m depth; point 1 seen once
    centres = np.array([[0.0, 0, 0], [1.0, 0, 0], [-2.0, 0, 0], [5.0, 0, 0]])
    X = np.array([[0.0, 0, 10], [0.0, 0, 10], [0.0, 0, 10], [5.0, 0, 3]])
    points = np.array([0, 0, 0, 1])
    par = ray_parallax_deg(centres, X, points, 3)
    assert par[0] == pytest.approx(np.degrees(np.arctan(0.2)), rel=1e-12)
    assert par[1] == 0.0 and par[2] == 0.0  # one view; no view
