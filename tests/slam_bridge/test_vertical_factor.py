"""The measured-vertical factor: residual, Jacobian, robust cost, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from slam_bridge.ba.factor import Factor
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.factors.vertical import VerticalFactor
from slam_bridge.geometry.lie import so3_exp

DOWN_W = np.array([0.0, 0.0, -1.0])


def _measured(R_wc: np.ndarray, err_rad: np.ndarray, sigma_rad=(0.004, 0.01)):
    """``(basis (M, 2, 3), covariance (M, 2, 2))`` of verticals measured with small errors."""
    basis, cov = [], []
    for R, e in zip(R_wc, err_rad, strict=True):
        d = so3_exp(e) @ (R.T @ DOWN_W)
        a = np.cross(d, [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        basis.append(np.stack([a, np.cross(d, a)]))
        cov.append(np.diag(np.square(sigma_rad)))
    return np.stack(basis), np.stack(cov)


def _state(C=3, seed=0) -> BAState:
    rng = np.random.default_rng(seed)
    return BAState(
        so3_exp(rng.normal(scale=0.3, size=(C, 3))), rng.normal(size=(C, 3)), np.zeros((1, 3))
    )


def test_residual_is_zero_at_the_measured_vertical_and_whitened_by_its_covariance():
    st = _state()
    basis, cov = _measured(st.R_wc, np.zeros((3, 3)))
    f = VerticalFactor(np.arange(3), basis, cov, kernel=None)
    assert isinstance(f, Factor) and f.num_residuals == 6
    np.testing.assert_allclose(f.evaluate(st).residuals, 0.0, atol=1e-12)
    # tilt camera 1 by 0.01 rad about its first basis direction's perpendicular: one sigma of
    # the second axis is 0.01 rad, so the residual's norm is ~1
    R = st.R_wc.copy()
    axis = st.R_wc[1] @ basis[1, 0]  # rotating about basis row 0 moves d along row 1
    R[1] = so3_exp(0.01 * axis) @ R[1]
    r = f.evaluate(BAState(R, st.t_wc, st.X_w)).residuals
    assert np.linalg.norm(r[1]) == pytest.approx(1.0, rel=1e-3)
    np.testing.assert_allclose(r[[0, 2]], 0.0, atol=1e-12)


def test_jacobian_matches_finite_differences_and_heading_is_free():
    st = _state()
    basis, cov = _measured(
        st.R_wc, np.radians([[0.5, -0.3, 0.2], [1.0, 0.0, 0.0], [0.0, 0.4, -0.6]])
    )
    f = VerticalFactor(np.arange(3), basis, cov, kernel=None)
    blk = f.evaluate(st)
    h = 1e-7
    for c in range(3):
        for j in range(6):
            dw, dt = np.zeros(3), np.zeros(3)
            (dw if j < 3 else dt)[j % 3] = h
            R, t = st.R_wc.copy(), st.t_wc.copy()
            R[c], t[c] = so3_exp(dw) @ R[c], t[c] + dt
            num = (f.evaluate(BAState(R, t, st.X_w)).residuals[c] - blk.residuals[c]) / h
            np.testing.assert_allclose(blk.J_cameras[c, 0, :, j], num, atol=1e-5)
    # a rotation about the world's vertical (heading) changes nothing
    np.testing.assert_allclose(blk.J_cameras[:, 0] @ np.array([0, 0, 1.0, 0, 0, 0]), 0, atol=1e-12)


def test_robust_cost_matches_the_block_and_bad_input_is_refused():
    st = _state()
    basis, cov = _measured(st.R_wc, np.radians([[5.0, 0, 0], [0, 0, 0], [0, 0.1, 0]]))
    f = VerticalFactor(np.arange(3), basis, cov)  # Huber: the 5-degree outlier grows linearly
    assert f.cost(st) == pytest.approx(f.evaluate(st).cost(), rel=1e-12)
    assert f.cost(st) < VerticalFactor(np.arange(3), basis, cov, kernel=None).cost(st)
    with pytest.raises(SlamError, match="positive definite"):
        VerticalFactor([0], basis[:1], -cov[:1])
    with pytest.raises(Exception, match="basis"):
        VerticalFactor([0, 1], basis[:1], cov[:1])
    with pytest.raises(SlamError, match="out of range"):
        VerticalFactor([5], basis[:1], cov[:1]).cost(st)
