"""DPC and MPC pose-graph terms (eqs. 3.14-3.18, appendix C): exact Jacobians, structure."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.ba.normal_equations import assemble
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.factors.pose_graph_dpc import (
    DPCFactor,
    dpc_residuals,
    relative_pose,
    relative_pose_information,
)
from slam_bridge.factors.pose_graph_mpc import MPCDegenerateError, MPCFactor, epipolar_residuals
from slam_bridge.geometry import lie

K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])


def _state(seed: int = 0, C: int = 5, rot: float = 0.3) -> BAState:
    rng = np.random.default_rng(seed)
    R = lie.so3_exp(rng.normal(scale=rot, size=(C, 3)))
    t = np.cumsum(rng.normal(size=(C, 3)) + [1.0, 0.2, 0.0], axis=0)
    fixed = np.zeros(C, dtype=bool)
    fixed[0] = True
    return BAState(R, t, np.zeros((0, 3)), camera_fixed=fixed)


def _numeric_check(factor, state: BAState, h: float = 1e-6, rtol: float = 1e-6) -> None:
    """Central differences on the manifold vs the block's camera Jacobians."""
    blk = factor.evaluate(state)
    M, k = blk.residuals.shape
    cmap = state.camera_index_map
    Cf = state.free_cameras.size
    scale = max(1.0, float(np.abs(blk.J_cameras).max()))
    for c in range(Cf):
        for d in range(6):
            dc = np.zeros((Cf, 6))
            dc[c, d] = h
            rp = factor.evaluate(state.retract(dc, np.zeros((0, 3)))).residuals
            rm = factor.evaluate(state.retract(-dc, np.zeros((0, 3)))).residuals
            num = (rp - rm) / (2 * h)
            ana = np.zeros((M, k))
            for s in range(blk.cameras.shape[1]):
                hit = cmap[blk.cameras[:, s]] == c
                ana[hit] += blk.J_cameras[hit, s, :, d]
            np.testing.assert_allclose(ana, num, atol=rtol * scale, rtol=rtol)


def _perturbed(state: BAState, seed: int, scale: float) -> BAState:
    rng = np.random.default_rng(seed)
    Cf = state.free_cameras.size
    return state.retract(rng.normal(scale=scale, size=(Cf, 6)), np.zeros((0, 3)))


# ------------------------------------------------------------------------------------------ DPC
@pytest.mark.parametrize("scale", [1e-3, 0.05, 0.8])
def test_dpc_jacobian_exact(scale: float) -> None:
    state = _state()
    pairs = np.array([[0, 1], [1, 2], [2, 3], [3, 4]])
    f = DPCFactor.from_state(state, pairs, D=np.array([1.0, 2.0, 3.0, 0.5, 4.0, 1.5]))
    moved = _perturbed(state, 1, scale)  # away from S_hat: q != 0
    _numeric_check(f, moved, rtol=1e-6)


def _spd(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    A = rng.normal(size=(n, k, k))
    return A @ np.swapaxes(A, 1, 2) + 0.5 * np.eye(k)


@pytest.mark.parametrize("scale", [1e-3, 0.3])
def test_dpc_per_pair_weight_jacobian_exact(scale: float) -> None:
    state = _state()
    pairs = np.array([[0, 1], [1, 2], [2, 3], [3, 4]])
    D = _spd(np.random.default_rng(3), 4, 6)
    f = DPCFactor.from_state(state, pairs, D=D)
    moved = _perturbed(state, 1, scale)
    _numeric_check(f, moved, rtol=1e-6)
    # xi = q^T D_i q per pair
    R_ij, t_ij = relative_pose(
        moved.R_wc[pairs[:, 0]],
        moved.t_wc[pairs[:, 0]],
        moved.R_wc[pairs[:, 1]],
        moved.t_wc[pairs[:, 1]],
    )
    Ri, ti = lie.se3_inverse(f.R_hat_ij, f.t_hat_ij)
    q = lie.se3_log(*lie.se3_compose(Ri, ti, R_ij, t_ij))
    assert f.cost(moved) == pytest.approx(float(np.einsum("ma,mab,mb->", q, D, q)), rel=1e-10)
    with pytest.raises(GeosegError):
        DPCFactor.from_state(state, pairs, D=D[:3])  # one weight per pair


def test_relative_pose_information_matches_numeric_propagation() -> None:
    """Sigma_q = J Sigma J^T with J from central differences of q (at S_hat = S)."""
    state = _state(seed=2, C=3)
    rng = np.random.default_rng(5)
    cov = _spd(rng, 2, 12) * 1e-4
    i, j = np.array([0, 1]), np.array([1, 2])
    args = (state.R_wc[i], state.t_wc[i], state.R_wc[j], state.t_wc[j])
    info = relative_pose_information(*args, cov, min_sigma=(1e-9, 1e-9))
    R_h, t_h = relative_pose(*args)
    h = 1e-6
    for m in range(2):
        J = np.zeros((6, 12))
        for c, cam in enumerate((i[m], j[m])):
            for d in range(6):
                dc = np.zeros((3, 6))
                dc[cam, d] = h
                qs = []
                for sgn in (1, -1):
                    st = BAState(state.R_wc, state.t_wc, state.X_w).retract(
                        sgn * dc, np.zeros((0, 3))
                    )
                    qs.append(
                        dpc_residuals(
                            st.R_wc[i[m] : i[m] + 1],
                            st.t_wc[i[m] : i[m] + 1],
                            st.R_wc[j[m] : j[m] + 1],
                            st.t_wc[j[m] : j[m] + 1],
                            R_h[m : m + 1],
                            t_h[m : m + 1],
                            with_jacobians=False,
                        )[0][0]
                    )
                J[:, 6 * c + d] = (qs[0] - qs[1]) / (2 * h)
        expected = np.linalg.inv(J @ cov[m] @ J.T)
        np.testing.assert_allclose(info[m], expected, rtol=1e-5)


def test_relative_pose_information_floors_a_fixed_pair() -> None:
    """Both cameras fixed (zero covariance): the weight is capped by the sigma floors."""
    state = _state(C=2)
    a = (state.R_wc[:1], state.t_wc[:1], state.R_wc[1:], state.t_wc[1:])
    info = relative_pose_information(*a, np.zeros((1, 12, 12)), min_sigma=(1e-3, 1e-2))
    np.testing.assert_allclose(info[0], np.diag([1e6] * 3 + [1e4] * 3), rtol=1e-9)
    with pytest.raises(GeosegError):
        relative_pose_information(*a, np.zeros((1, 6, 6)))


def test_dpc_zero_at_s_hat_and_value() -> None:
    state = _state()
    pairs = np.array([[0, 1], [1, 2]])
    f = DPCFactor.from_state(state, pairs)
    assert f.cost(state) == pytest.approx(0.0, abs=1e-20)
    moved = _perturbed(state, 2, 0.1)
    R_ij, t_ij = relative_pose(moved.R_wc[:2], moved.t_wc[:2], moved.R_wc[1:3], moved.t_wc[1:3])
    R_h, t_h = relative_pose(state.R_wc[:2], state.t_wc[:2], state.R_wc[1:3], state.t_wc[1:3])
    Ri, ti = lie.se3_inverse(R_h, t_h)
    q = lie.se3_log(*lie.se3_compose(Ri, ti, R_ij, t_ij))
    assert f.cost(moved) == pytest.approx(float(np.sum(q * q)), rel=1e-12)
    # a global rigid motion of every camera leaves the relative poses unchanged
    Rg = lie.so3_exp(np.array([0.1, -0.2, 0.3]))
    rigid = BAState(Rg @ state.R_wc, state.t_wc @ Rg.T + 2.0, state.X_w)
    r, _, _ = dpc_residuals(
        rigid.R_wc[:2], rigid.t_wc[:2], rigid.R_wc[1:3], rigid.t_wc[1:3], f.R_hat_ij, f.t_hat_ij
    )
    np.testing.assert_allclose(r, 0.0, atol=1e-12)


def test_se3_right_jacobian_inv_matches_log() -> None:
    """The DPC Jacobian relies on it at any angle below pi."""
    rng = np.random.default_rng(4)
    for angle in (0.01, 0.3, 2.5):  # below pi: log(exp(xi)) = xi
        xi = rng.normal(size=6)
        xi[:3] *= angle / np.linalg.norm(xi[:3])
        d = rng.normal(scale=1e-7, size=6)
        R, t = lie.se3_compose(*lie.se3_exp(xi), *lie.se3_exp(d))
        np.testing.assert_allclose(
            lie.se3_log(R, t) - xi, lie.se3_right_jacobian_inv(xi) @ d, atol=1e-13
        )


def test_dpc_bad_weight() -> None:
    with pytest.raises(GeosegError):
        DPCFactor.from_state(_state(), [[0, 1]], D=-np.ones(6))


# ------------------------------------------------------------------------------------------ MPC
def _mpc(state: BAState, seed: int = 0, per_pair: int = 6, compress: bool = False) -> MPCFactor:
    """Correspondences of true 3D points between successive cameras."""
    rng = np.random.default_rng(seed)
    ci, cj, ui, uj = [], [], [], []
    for i in range(state.num_cameras - 1):
        Xc = np.stack(
            [
                rng.uniform(-3, 3, per_pair),
                rng.uniform(-2, 2, per_pair),
                rng.uniform(5, 15, per_pair),
            ],
            axis=1,
        )
        Xw = Xc @ state.R_wc[i].T + state.t_wc[i]
        for c, store in ((i, ui), (i + 1, uj)):
            Xcc = (Xw - state.t_wc[c]) @ state.R_wc[c]
            x = Xcc @ K.T
            store.append(x[:, :2] / x[:, 2:] + rng.normal(scale=0.5, size=(per_pair, 2)))
        ci.append(np.full(per_pair, i))
        cj.append(np.full(per_pair, i + 1))
    return MPCFactor(
        K,
        np.concatenate(ci),
        np.concatenate(cj),
        np.concatenate(ui),
        np.concatenate(uj),
        compress=compress,
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_mpc_jacobian_exact(seed: int) -> None:
    state = _state(seed, rot=0.05)
    f = _mpc(state, seed)
    _numeric_check(f, _perturbed(state, 5, 0.02), rtol=1e-6)


def test_mpc_is_point_to_epipolar_line_distance() -> None:
    state = _state(rot=0.05)
    f = _mpc(state)
    blk = f.evaluate(state)
    m = 3
    i, j = f.cameras_i[m], f.cameras_j[m]
    R = state.R_wc[i].T @ state.R_wc[j]
    L = state.R_wc[i].T @ (state.t_wc[j] - state.t_wc[i])
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ lie.so3_hat(L) @ R @ Kinv
    line = F @ np.append(f.uv_j[m], 1.0)
    d = np.append(f.uv_i[m], 1.0) @ line / np.hypot(line[0], line[1])
    assert blk.residuals[m, 0] == pytest.approx(d, rel=1e-10)
    # noise-free correspondences have zero epipolar distance
    psi, valid, _, _ = epipolar_residuals(
        state.R_wc[[0]],
        state.t_wc[[0]],
        state.R_wc[[1]],
        state.t_wc[[1]],
        np.linalg.inv(K),
        np.linalg.inv(K),
        *_project_pair(state, np.array([[1.0, 0.5, 8.0]])),
    )
    assert valid.all() and abs(psi[0]) < 1e-9


def _project_pair(state: BAState, Xc0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xw = Xc0 @ state.R_wc[0].T + state.t_wc[0]
    out = []
    for c in (0, 1):
        x = ((Xw - state.t_wc[c]) @ state.R_wc[c]) @ K.T
        out.append(x[:, :2] / x[:, 2:])
    return out[0], out[1]


def test_mpc_compressed_rows_are_exact() -> None:
    """One 13-row per pair gives the same cost and normal equations as one row per match."""
    state = _state(C=6, rot=0.05)
    moved = _perturbed(state, 7, 0.01)
    rows = _mpc(state, 3, per_pair=25, compress=False)
    comp = _mpc(state, 3, per_pair=25, compress=True)
    b_rows, b_comp = rows.evaluate(moved), comp.evaluate(moved)
    assert b_rows.num_rows == 125 and b_comp.num_rows == 5
    assert b_comp.cost() == pytest.approx(b_rows.cost(), rel=1e-12)
    assert comp.cost(moved) == pytest.approx(rows.cost(moved), rel=1e-12)
    H1, g1 = assemble([rows], moved).dense()
    H2, g2 = assemble([comp], moved).dense()
    np.testing.assert_allclose(H2, H1, rtol=1e-9, atol=1e-9 * np.abs(H1).max())
    np.testing.assert_allclose(g2, g1, rtol=1e-9, atol=1e-9 * np.abs(g1).max())


@pytest.mark.parametrize("compress", [False, True])
def test_mpc_relative_to_is_at_rest_with_the_same_jacobian(compress: bool) -> None:
    """``relative_to(X0)``: xi(X0) = 0 with zero gradient; elsewhere rows = psi - psi(X0)."""
    state = _state(C=5, rot=0.05)
    f = _mpc(state, 4, per_pair=12, compress=compress)
    moved = _perturbed(state, 8, 0.01)
    rel = f.relative_to(moved)
    assert rel.cost(moved) < 1e-20
    _, g = assemble([rel], moved).dense()
    assert np.abs(g).max() < 1e-9
    # same Jacobian as the plain factor (a constant offset), exact against finite differences
    H_rel, _ = assemble([rel], state).dense()
    H, _ = assemble([f], state).dense()
    np.testing.assert_allclose(H_rel, H, rtol=1e-9, atol=1e-9 * np.abs(H).max())
    if not compress:  # per-correspondence rows: exact Jacobian, rows shifted by psi(X0)
        _numeric_check(rel, _perturbed(state, 5, 0.02), rtol=1e-6)
        r = rel.evaluate(state).residuals[:, 0]
        r0 = f.evaluate(moved).residuals[:, 0]
        np.testing.assert_allclose(r, f.evaluate(state).residuals[:, 0] - r0, atol=1e-12)
    with pytest.raises(SlamError, match="offset"):
        MPCFactor(K, [0], [1], [[1.0, 1.0]], [[2.0, 1.0]], offset=np.zeros(2))


def test_mpc_coincident_centres_raise() -> None:
    state = _state(rot=0.05)
    state.t_wc[2] = state.t_wc[1]
    f = _mpc(_state(rot=0.05))
    with pytest.raises(MPCDegenerateError, match="optical"):
        f.evaluate(state)


def test_mpc_bad_pixels() -> None:
    with pytest.raises(GeosegError):
        MPCFactor(K, [0], [1], [[np.nan, 1.0]], [[1.0, 1.0]])


# --------------------------------------------------------------------------------- structure
def test_pose_graph_terms_fill_only_successive_offdiagonal_blocks() -> None:
    """Fig. 3.3: each DPC/MPC row couples only cameras i and i + 1."""
    state = _state(C=6, rot=0.05)
    moved = _perturbed(state, 3, 0.01)
    pairs = np.stack([np.arange(5), np.arange(1, 6)], axis=1)
    for f in (DPCFactor.from_state(state, pairs), _mpc(state)):
        ne = assemble([f], moved)
        cmap = state.camera_index_map
        # pair (0, 1) involves the fixed camera 0: no off-diagonal block for it
        expected = {(int(cmap[i]), int(cmap[i + 1])) for i in range(1, 5)}
        assert {tuple(p) for p in ne.pairs.tolist()} == expected
        assert ne.W.shape[0] == 0
        H, _ = ne.dense()
        for a in range(5):
            for b in range(5):
                blk = H[6 * a : 6 * a + 6, 6 * b : 6 * b + 6]
                if abs(a - b) > 1:
                    assert np.all(blk == 0)
                elif abs(a - b) == 1:
                    assert np.any(blk != 0)
