"""SO(3)/SE(3): round trips, small-angle and near-pi branches, Jacobians vs finite differences."""

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.geometry import lie


def _rand_w(rng, n, scale=1.0):
    return rng.normal(size=(n, 3)) * scale


@pytest.mark.parametrize("scale", [1e-9, 1e-5, 0.05, 0.5, 2.0])
def test_so3_exp_log_round_trip(scale):
    rng = np.random.default_rng(0)
    w = _rand_w(rng, 50, scale)
    w = w[np.linalg.norm(w, axis=1) < np.pi - 1e-3]
    R = lie.so3_exp(w)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-13
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-13)
    np.testing.assert_allclose(lie.so3_log(R), w, atol=1e-12 * max(1, scale))


def test_so3_log_near_pi():
    rng = np.random.default_rng(1)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for theta in [np.pi - 1e-3, np.pi - 1e-7, np.pi - 1e-10]:
        w = theta * axes
        w2 = lie.so3_log(lie.so3_exp(w))
        np.testing.assert_allclose(w2, w, atol=1e-7)
    # exactly pi: either sign is correct, the rotation must be reproduced
    w = np.pi * axes
    R = lie.so3_exp(w)
    np.testing.assert_allclose(lie.so3_exp(lie.so3_log(R)), R, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(lie.so3_log(R), axis=1), np.pi, atol=1e-12)


def test_so3_log_identity_and_shapes():
    assert np.allclose(lie.so3_log(np.eye(3)), 0.0)
    R = lie.so3_exp(np.zeros((2, 4, 3)))
    assert R.shape == (2, 4, 3, 3)
    assert lie.so3_log(R).shape == (2, 4, 3)
    with pytest.raises(GeosegError):
        lie.so3_exp(np.zeros((4, 2)))


def test_hat_vee_round_trip():
    rng = np.random.default_rng(2)
    w = rng.normal(size=(10, 3))
    v = rng.normal(size=(10, 3))
    np.testing.assert_allclose(lie.so3_vee(lie.so3_hat(w)), w)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", lie.so3_hat(w), v), np.cross(w, v))
    xi = rng.normal(size=(10, 6))
    np.testing.assert_allclose(lie.se3_vee(lie.se3_hat(xi)), xi)


def test_thesis_generators():
    rng = np.random.default_rng(3)
    a = rng.normal(size=3)
    M = np.einsum("i,ijk->jk", a, lie.THESIS_GENERATORS)
    expected = np.array([[0, a[0], -a[1]], [-a[0], 0, a[2]], [a[1], -a[2], 0]])
    np.testing.assert_allclose(M, expected)
    w = lie.from_thesis_coefficients(a)
    np.testing.assert_allclose(lie.so3_hat(w), M)
    np.testing.assert_allclose(lie.thesis_coefficients(w), a)
    # eq. 1.56: d/da_i exp(a_i G_i) M at 0 = G_i M
    Mx = rng.normal(size=(3, 3))
    h = 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        num = (
            lie.so3_exp(lie.from_thesis_coefficients(e)) @ Mx
            - lie.so3_exp(lie.from_thesis_coefficients(-e)) @ Mx
        ) / (2 * h)
        np.testing.assert_allclose(num, lie.THESIS_GENERATORS[i] @ Mx, atol=1e-9)


@pytest.mark.parametrize("scale", [1e-6, 0.03, 0.09, 0.11, 1.0, 2.5])
def test_so3_jacobians_fd(scale):
    rng = np.random.default_rng(4)
    w = rng.normal(size=3)
    w *= scale / np.linalg.norm(w)
    Jl, Jr = lie.so3_left_jacobian(w), lie.so3_right_jacobian(w)
    R = lie.so3_exp(w)
    h = 1e-6
    num_l, num_r = np.zeros((3, 3)), np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        Rp, Rm = lie.so3_exp(w + d), lie.so3_exp(w - d)
        num_l[:, k] = (lie.so3_log(Rp @ R.T) - lie.so3_log(Rm @ R.T)) / (2 * h)
        num_r[:, k] = (lie.so3_log(R.T @ Rp) - lie.so3_log(R.T @ Rm)) / (2 * h)
    np.testing.assert_allclose(Jl, num_l, atol=1e-8)
    np.testing.assert_allclose(Jr, num_r, atol=1e-8)
    np.testing.assert_allclose(lie.so3_left_jacobian_inv(w) @ Jl, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(lie.so3_right_jacobian_inv(w) @ Jr, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("scale", [1e-7, 0.05, 0.2, 1.5])
def test_se3_exp_log_and_jacobians_fd(scale):
    rng = np.random.default_rng(5)
    xi = rng.normal(size=6)
    xi[:3] *= scale / np.linalg.norm(xi[:3])
    R, t = lie.se3_exp(xi)
    np.testing.assert_allclose(lie.se3_log(R, t), xi, atol=1e-12)
    np.testing.assert_allclose(t, lie.so3_left_jacobian(xi[:3]) @ xi[3:])
    T = lie.se3_to_matrix(R, t)
    Tinv = np.linalg.inv(T)
    h = 1e-6
    num_l, num_r = np.zeros((6, 6)), np.zeros((6, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        Tp = lie.se3_to_matrix(*lie.se3_exp(xi + d))
        Tm = lie.se3_to_matrix(*lie.se3_exp(xi - d))
        num_l[:, k] = (
            lie.se3_log(*lie.se3_from_matrix(Tp @ Tinv))
            - lie.se3_log(*lie.se3_from_matrix(Tm @ Tinv))
        ) / (2 * h)
        num_r[:, k] = (
            lie.se3_log(*lie.se3_from_matrix(Tinv @ Tp))
            - lie.se3_log(*lie.se3_from_matrix(Tinv @ Tm))
        ) / (2 * h)
    np.testing.assert_allclose(lie.se3_left_jacobian(xi), num_l, atol=1e-8)
    np.testing.assert_allclose(lie.se3_right_jacobian(xi), num_r, atol=1e-8)
    np.testing.assert_allclose(lie.se3_left_jacobian_inv(xi) @ num_l, np.eye(6), atol=1e-7)
    np.testing.assert_allclose(
        lie.se3_right_jacobian_inv(xi) @ lie.se3_right_jacobian(xi), np.eye(6), atol=1e-12
    )


def test_se3_adjoint_and_group_ops():
    rng = np.random.default_rng(6)
    R, t = lie.se3_exp(rng.normal(size=6))
    xi = rng.normal(size=6) * 0.3
    T = lie.se3_to_matrix(R, t)
    lhs = T @ lie.se3_to_matrix(*lie.se3_exp(xi)) @ np.linalg.inv(T)
    rhs = lie.se3_to_matrix(*lie.se3_exp(lie.se3_adjoint(R, t) @ xi))
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)
    Ri, ti = lie.se3_inverse(R, t)
    Rc, tc = lie.se3_compose(R, t, Ri, ti)
    np.testing.assert_allclose(Rc, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(tc, 0, atol=1e-14)
