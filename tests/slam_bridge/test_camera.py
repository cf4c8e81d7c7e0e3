"""Pinhole projection: values, analytic Jacobians on the manifold, cheirality, local window."""

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.geometry.camera import PinholeCamera, local_window, project, project_with_jacobians
from slam_bridge.geometry.lie import so3_exp


def _setup(n=20, seed=0):
    rng = np.random.default_rng(seed)
    K = np.array([[480.0, 0.5, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    R = so3_exp(rng.normal(size=(n, 3)) * 0.5)
    t = rng.normal(size=(n, 3))
    X_c = np.column_stack([rng.normal(size=(n, 2)), rng.uniform(2, 10, size=n)])
    X_w = np.einsum("nij,nj->ni", R, X_c) + t
    return K, R, t, X_w, X_c


def test_project_matches_formula():
    K, R, t, X_w, X_c = _setup()
    uv, z, ok = project(K, R, t, X_w)
    h = X_c @ K.T
    np.testing.assert_allclose(uv, h[:, :2] / h[:, 2:], rtol=1e-12)
    np.testing.assert_allclose(z, X_c[:, 2], rtol=1e-12)
    assert ok.all()
    cam = PinholeCamera(K, 640, 480)
    np.testing.assert_allclose(cam.project(R, t, X_w)[0], uv)


def test_projection_jacobians_central_differences():
    K, R, t, X_w, _ = _setup()
    uv, _, ok, Jc, Jp = project_with_jacobians(K, R, t, X_w)
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        Rp, tp = so3_exp(d[:3]) @ R, t + d[3:]
        Rm, tm = so3_exp(-d[:3]) @ R, t - d[3:]
        num = (project(K, Rp, tp, X_w)[0] - project(K, Rm, tm, X_w)[0]) / (2 * h)
        np.testing.assert_allclose(Jc[:, :, k], num, rtol=1e-6, atol=1e-6)
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        num = (project(K, R, t, X_w + d)[0] - project(K, R, t, X_w - d)[0]) / (2 * h)
        np.testing.assert_allclose(Jp[:, :, k], num, rtol=1e-6, atol=1e-6)


def test_per_camera_intrinsics():
    K, R, t, X_w, _ = _setup(5)
    Ks = np.stack([K * np.array([[1 + 0.1 * i], [1], [1]]) for i in range(5)])
    Ks[:, 2] = [0, 0, 1]
    uv, *_ = project(Ks, R, t, X_w)
    for i in range(5):
        np.testing.assert_allclose(uv[i], project(Ks[i], R[i], t[i], X_w[i : i + 1])[0][0])


def test_points_behind_flagged_not_divided():
    K = np.eye(3)
    R, t = np.eye(3), np.zeros(3)
    X = np.array([[0.0, 0.0, 1.0], [1.0, 1.0, -2.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1e-9]])
    with np.errstate(all="raise"):  # no division by zero or overflow allowed
        uv, z, ok, Jc, Jp = project_with_jacobians(K, R, t, X)
    assert ok.tolist() == [True, False, False, False]
    assert np.isnan(uv[~ok]).all() and np.isfinite(uv[ok]).all()
    assert np.all(Jc[~ok] == 0) and np.all(Jp[~ok] == 0)


def test_bad_inputs():
    K, R, t, X_w, _ = _setup(3)
    with pytest.raises(GeosegError):
        project(K, R, t, X_w[:, :2])
    with pytest.raises(GeosegError):
        project(np.ones((3, 3)), R, t, X_w)


def test_local_window():
    # 6 keyframes; point p seen by cameras listed
    obs = {0: [0, 1, 2], 1: [2, 3, 4], 2: [4, 5], 3: [0, 1], 4: [1, 5]}
    cams = np.concatenate([np.array(v) for v in obs.values()])
    pts = np.concatenate([[p] * len(v) for p, v in obs.items()])
    win = local_window(np.arange(6), cams, pts, l=2)
    assert win.free_cameras.tolist() == [4, 5]
    assert win.points.tolist() == [1, 2, 4]
    assert win.fixed_cameras.tolist() == [1, 2, 3]
    assert set(pts[win.observations]) == {1, 2, 4}
    with pytest.raises(GeosegError):
        local_window(np.zeros(0), cams, pts, l=2)
