"""Reprojection factor: residuals, Jacobians vs central differences, invalid rows, bad input."""

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.ba.state import BAState
from slam_bridge.factors.reprojection import ReprojectionFactor


def test_residuals_zero_at_truth(street_noiseless, ba_problem):
    state, f = ba_problem(street_noiseless, perturbed=False)
    r, ok = f.residuals(state)
    assert ok.all()
    assert np.abs(r).max() < 1e-9
    assert f.cost(state) < 1e-15


def test_factor_jacobians_central_differences(street, ba_problem):
    state, f = ba_problem(street, n_fixed=0, sigma=0.7)
    blk = f.evaluate(state)
    assert blk.residuals.shape == (f.cameras.size, 2)
    assert blk.J_cameras.shape == (f.cameras.size, 1, 2, 6)
    C, P = state.num_cameras, state.num_points
    h = 1e-6
    cams = [0, 3, C - 1]
    for c in cams:
        rows = f.cameras == c
        for k in range(6):
            dc = np.zeros((C, 6))
            dc[c, k] = h
            rp, _ = f.residuals(state.retract(dc, np.zeros((P, 3))))
            rm, _ = f.residuals(state.retract(-dc, np.zeros((P, 3))))
            num = (rp - rm) / (2 * h)
            np.testing.assert_allclose(
                blk.J_cameras[rows, 0, :, k], num[rows], rtol=1e-5, atol=1e-5
            )
    for p in [0, 5, P - 1]:
        rows = f.points == p
        for k in range(3):
            dp = np.zeros((P, 3))
            dp[p, k] = h
            rp, _ = f.residuals(state.retract(np.zeros((C, 6)), dp))
            rm, _ = f.residuals(state.retract(np.zeros((C, 6)), -dp))
            num = (rp - rm) / (2 * h)
            np.testing.assert_allclose(blk.J_points[rows, :, k], num[rows], rtol=1e-5, atol=1e-5)


def test_point_behind_camera_is_invalid(street, ba_problem):
    state, f = ba_problem(street, perturbed=False)
    X = state.X_w.copy()
    p = f.points[0]
    c = f.cameras[0]
    X[p] = 2 * state.t_wc[c] - X[p]  # mirror through the optical centre: behind
    bad = BAState(state.R_wc, state.t_wc, X, state.camera_fixed)
    blk = f.evaluate(bad)
    assert not blk.valid[0] and blk.n_invalid >= 1
    assert np.all(np.isfinite(blk.residuals)) and np.all(blk.residuals[~blk.valid] == 0)
    assert f.cost_and_invalid(bad)[1] == blk.n_invalid


def test_nan_observations_rejected(street):
    uv = street.uv.copy()
    uv[3, 0] = np.nan
    with pytest.raises(GeosegError, match="uv"):
        ReprojectionFactor(street.K, street.obs_cameras, street.obs_points, uv)
    uv[3, 0] = np.inf
    with pytest.raises(GeosegError, match="uv"):
        ReprojectionFactor(street.K, street.obs_cameras, street.obs_points, uv)


def test_index_out_of_range(street, ba_problem):
    state, _ = ba_problem(street)
    f = ReprojectionFactor(street.K, [state.num_cameras], [0], [[1.0, 2.0]])
    with pytest.raises(GeosegError, match="camera index"):
        f.evaluate(state)
