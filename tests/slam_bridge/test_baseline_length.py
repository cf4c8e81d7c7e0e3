"""The baseline-length family: Jacobian against central differences, cost."""

from __future__ import annotations

import numpy as np
import pytest

from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.factors.baseline_length import BaselineLengthFactor


def assert_jacobian_matches_central_differences(f, st, rtol=1e-7, atol=1e-6):
    """The pair factor's camera Jacobians against central differences on the manifold."""
    blk = f.evaluate(st)
    eps = 1e-6
    C = st.R_wc.shape[0]
    for cam in range(C):
        for k in range(6):
            d = np.zeros((C, 6))
            d[cam, k] = eps
            rp = f.evaluate(st.retract(d, np.zeros((0, 3)))).residuals
            rm = f.evaluate(st.retract(-d, np.zeros((0, 3)))).residuals
            num = (rp - rm)[:, 0] / (2 * eps)
            ana = np.zeros(num.size)
            for row in range(num.size):
                for slot in range(2):
                    if blk.cameras[row, slot] == cam:
                        ana[row] += blk.J_cameras[row, slot, 0, k]
            np.testing.assert_allclose(ana, num, rtol=rtol, atol=atol)
    return blk


def test_baseline_length_factor_jacobian():
    rng = np.random.default_rng(0)
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    t = rng.normal(size=(3, 3))
    st = BAState(R, t, np.zeros((0, 3)))
    f = BaselineLengthFactor(np.array([[0, 1], [1, 2]]), np.array([1.0, 2.0]), 0.1)
    blk = assert_jacobian_matches_central_differences(f, st)
    assert f.cost(st) == pytest.approx(float(np.sum(blk.residuals**2)))
    with pytest.raises(SlamError, match="sigma"):
        BaselineLengthFactor(np.array([[0, 1]]), np.array([1.0]), 0.0)
    with pytest.raises(SlamError, match="lengths"):
        BaselineLengthFactor(np.array([[0, 1]]), np.array([1.0, 2.0]), 0.1)


def test_yaw_change_factor_jacobian_and_sign():
    from slam_bridge.factors.yaw_change import YawChangeFactor
    from slam_bridge.geometry.lie import so3_exp

    rng = np.random.default_rng(1)
    R = np.stack([so3_exp(rng.normal(scale=0.3, size=3)) for _ in range(3)])
    R[1] = R[0] @ so3_exp(np.array([0.02, -0.1, 0.01]))  # turned 0.1 rad about its -y
    st = BAState(R, rng.normal(size=(3, 3)), np.zeros((0, 3)))
    f = YawChangeFactor(np.array([[0, 1], [1, 2]]), np.array([0.1, 0.05]), 0.01)
    blk = assert_jacobian_matches_central_differences(f, st, rtol=1e-5)
    assert abs(blk.residuals[0, 0]) < 0.5  # a 0.1 rad turn about -y is a +0.1 heading change
    with pytest.raises(SlamError, match="sigma"):
        YawChangeFactor(np.array([[0, 1]]), np.array([0.1]), 0.0)
