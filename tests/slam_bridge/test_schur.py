"""Normal equations and the Schur complement against dense linear algebra."""

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.ba.factor import FactorBlock
from slam_bridge.ba.normal_equations import assemble
from slam_bridge.ba.solvers.schur import (
    SchurFactorization,
    _chain_split_point,
    _ChainSplit,
    camera_covariance,
    latest_camera_covariance,
    reduced_camera_matrix,
    schur_solve,
)
from slam_bridge.geometry.lie import so3_log


class RelativeTranslation:
    """Toy two-camera factor ``r = (t_j - t_i - z) + 0.1 log(R_i^T R_j)`` (k = 3, a = 2)."""

    def __init__(self, pairs, z):
        self.pairs, self.z = np.asarray(pairs), np.asarray(z)

    def _r(self, state):
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        rot = so3_log(np.swapaxes(state.R_wc[i], 1, 2) @ state.R_wc[j])
        return state.t_wc[j] - state.t_wc[i] - self.z + 0.1 * rot

    def evaluate(self, state):
        # rotation Jacobians approximated to first order at small relative rotation is not
        # exact; use the translation part only and keep the rotation term constant in tests
        M = self.pairs.shape[0]
        J = np.zeros((M, 2, 3, 6))
        J[:, 0, :, 3:] = -np.eye(3)
        J[:, 1, :, 3:] = np.eye(3)
        J[:, 0, :, :3] = 0.01 * np.eye(3)  # arbitrary but fixed, for the algebra test
        J[:, 1, :, :3] = -0.02 * np.eye(3)
        return FactorBlock(self._r(state), self.pairs, J, kernel="huber", name="rel")

    def cost(self, state):
        return self.evaluate(state).cost()


class PointPrior:
    """Point-only factor (a = 0): ``r = X_p - z``."""

    def __init__(self, points, z):
        self.points, self.z = np.asarray(points), np.asarray(z)

    def evaluate(self, state):
        M = self.points.size
        J = np.broadcast_to(np.eye(3), (M, 3, 3)).copy()
        return FactorBlock(
            state.X_w[self.points] - self.z,
            np.zeros((M, 0), dtype=int),
            np.zeros((M, 0, 3, 6)),
            self.points,
            J,
            name="prior",
        )

    def cost(self, state):
        return self.evaluate(state).cost()


def _dense_from_blocks(blocks, state):
    """Stacked dense J (free columns only), whitened residuals and IRLS weights."""
    cmap, pmap = state.camera_index_map, state.point_index_map
    Cf, Pf = state.free_cameras.size, state.free_points.size
    rows_J, rows_r, rows_w = [], [], []
    for blk in blocks:
        s = blk.squared_norms()
        w = blk.kernel.weight(s)
        if blk.valid is not None:
            w = np.where(blk.valid, w, 0.0)
        M, k = blk.residuals.shape
        J = np.zeros((M, k, 6 * Cf + 3 * Pf))
        for a in range(blk.cameras.shape[1]):
            for m in range(M):
                c = cmap[blk.cameras[m, a]]
                if c >= 0:
                    J[m, :, 6 * c : 6 * c + 6] += blk.J_cameras[m, a]
        if blk.points is not None:
            for m in range(M):
                p = pmap[blk.points[m]]
                if p >= 0:
                    J[m, :, 6 * Cf + 3 * p : 6 * Cf + 3 * p + 3] = blk.J_points[m]
        rows_J.append(J.reshape(M * k, -1))
        rows_r.append(blk.residuals.reshape(-1))
        rows_w.append(np.repeat(w, k))
    return np.concatenate(rows_J), np.concatenate(rows_r), np.concatenate(rows_w)


@pytest.fixture
def tiny(make_street, ba_problem):
    scene = make_street(5, points_per_camera=4, noise_px=1.0, seed=3)
    state, f = ba_problem(scene, n_fixed=1, kernel="huber", kernel_scale=1.5)
    fixed_pt = np.zeros(state.num_points, dtype=bool)
    fixed_pt[[1, 4]] = True
    state.point_fixed[:] = fixed_pt  # in-place mask edits are followed by the index maps
    rng = np.random.default_rng(0)
    rel = RelativeTranslation([[0, 1], [1, 2], [3, 2], [3, 4]], rng.normal(size=(4, 3)))
    prior = PointPrior([0, 2, 1], state.X_w[[0, 2, 1]] + 0.3)
    return state, [f, rel, prior]


def test_assembled_equals_dense(tiny):
    state, factors = tiny
    neq = assemble(factors, state)
    blocks = [f.evaluate(state) for f in factors]
    J, r, w = _dense_from_blocks(blocks, state)
    H, g = neq.dense()
    np.testing.assert_allclose(H, J.T @ (w[:, None] * J), atol=1e-8, rtol=1e-10)
    np.testing.assert_allclose(g, J.T @ (w * r), atol=1e-8, rtol=1e-10)
    assert neq.cost == pytest.approx(sum(b.cost() for b in blocks))
    # off-diagonal camera blocks only from the two-camera factor (fig. 3.3 structure)
    assert {tuple(p) for p in neq.pairs.tolist()} == {(0, 1), (1, 2), (2, 3)}  # camera 0 fixed
    assert set(neq.costs) == {"reprojection", "rel", "prior"}


@pytest.mark.parametrize("mode", ["additive", "marquardt"])
@pytest.mark.parametrize("damping", [0.0, 1e-3, 10.0])
def test_schur_solve_equals_dense(tiny, mode, damping):
    state, factors = tiny
    neq = assemble(factors, state)
    H, _ = neq.dense()
    D = np.eye(H.shape[0]) if mode == "additive" else np.diag(np.maximum(np.diag(H), 1e-12))
    rng = np.random.default_rng(1)
    fac = SchurFactorization(neq, damping, mode)
    for _ in range(2):  # several right-hand sides, one factorisation
        rc = rng.normal(size=neq.g_c.shape)
        rp = rng.normal(size=neq.g_p.shape)
        dc, dp = fac.solve(rc, rp)
        x = np.linalg.solve(H + damping * D, np.concatenate([rc.ravel(), rp.ravel()]))
        np.testing.assert_allclose(
            np.concatenate([dc.ravel(), dp.ravel()]), x, rtol=1e-8, atol=1e-10
        )
    dc2, dp2 = schur_solve(neq, rc, rp, damping, mode)
    np.testing.assert_allclose(dc2, dc)
    np.testing.assert_allclose(dp2, dp)


def test_reduced_matrix_and_covariance(tiny):
    state, factors = tiny
    neq = assemble(factors, state)
    H, _ = neq.dense()
    nc = 6 * neq.num_free_cameras
    A, B, Dm = H[:nc, :nc], H[:nc, nc:], H[nc:, nc:]
    S = A - B @ np.linalg.solve(Dm, B.T)
    np.testing.assert_allclose(reduced_camera_matrix(neq), S, rtol=1e-9, atol=1e-8)
    cov = camera_covariance(neq)
    full = np.linalg.inv(H)[:nc, :nc]
    for i in range(neq.num_free_cameras):
        np.testing.assert_allclose(
            cov[i], full[6 * i : 6 * i + 6, 6 * i : 6 * i + 6], rtol=1e-7, atol=1e-12
        )
    np.testing.assert_allclose(latest_camera_covariance(neq), cov[-1])


def test_street_scene_schur_equals_dense(street, ba_problem):
    state, f = ba_problem(street)
    neq = assemble([f], state)
    H, g = neq.dense()
    dc, dp = schur_solve(neq, -neq.g_c, -neq.g_p, 1e-4, "marquardt")
    D = np.diag(np.maximum(np.diag(H), 1e-12))
    x = np.linalg.solve(H + 1e-4 * D, -g)
    np.testing.assert_allclose(np.concatenate([dc.ravel(), dp.ravel()]), x, rtol=1e-7, atol=1e-9)


def test_rhs_shape_and_singular_errors(tiny):
    state, factors = tiny
    neq = assemble(factors, state)
    fac = SchurFactorization(neq, 1e-3)
    with pytest.raises(GeosegError, match="rhs_c"):
        fac.solve(np.zeros((1, 6)), np.zeros_like(neq.g_p))
    neq.V[0] = 0.0  # a point block with no information
    with pytest.raises(GeosegError, match="positive definite"):
        SchurFactorization(neq, 0.0)
    neq.U[:] = 0.0  # no camera information at all: the reduced system is singular
    neq.W[:] = 0.0
    neq.V[0] = np.eye(3)
    with pytest.raises(GeosegError, match="gauge"):
        SchurFactorization(neq, 0.0)


@pytest.mark.parametrize("skewed", [False, True])
def test_grouped_sums_match_brute_force(skewed):
    from slam_bridge.ba.normal_equations import _gram_sum
    from slam_bridge.geometry.sums import _segment_sum

    rng = np.random.default_rng(4)
    M, n = 300, 7
    idx = rng.integers(-1, n, size=M)
    if skewed:  # one huge group: the padded layout is refused, the fallback is used
        idx[: M - 20] = 2
    X = rng.normal(size=(M, 2, 5))
    got = _gram_sum(idx, X, 3, n)
    seg = _segment_sum(idx, X.reshape(M, -1), n).reshape(n, 2, 5)
    for i in range(n):
        rows = idx == i
        np.testing.assert_allclose(
            got[i], np.einsum("mka,mkb->ab", X[rows, :, :3], X[rows]), atol=1e-12
        )
        np.testing.assert_allclose(seg[i], X[rows].sum(axis=0), atol=1e-12)


def test_schur_without_locality_equals_dense(make_street, ba_problem):
    """Shuffled camera order: chunks touch many cameras, the layout adapts, results unchanged."""
    scene = make_street(12, points_per_camera=6, noise_px=1.0, seed=5)
    perm = np.random.default_rng(0).permutation(12)
    inv = np.argsort(perm)
    scene.R_wc, scene.t_wc = scene.R_wc[perm], scene.t_wc[perm]
    scene.obs_cameras = inv[scene.obs_cameras]
    state, f = ba_problem(scene, n_fixed=2)
    neq = assemble([f], state)
    H, g = neq.dense()
    dc, dp = schur_solve(neq, -neq.g_c, -neq.g_p, 1e-3, "additive")
    x = np.linalg.solve(H + 1e-3 * np.eye(H.shape[0]), -g)
    np.testing.assert_allclose(np.concatenate([dc.ravel(), dp.ravel()]), x, rtol=1e-7, atol=1e-9)


def _chain_then_window(make_street, ba_problem, n_chain: int = 8):
    """A hybrid-like problem (fig. 3.3): cameras ``0 .. n_chain`` linked by DPC terms only,
    the later ones sharing points; camera 0 fixed, points fewer than two of those see fixed."""
    from slam_bridge.factors.pose_graph_dpc import DPCFactor

    scene = make_street(16, points_per_camera=6, noise_px=1.0, seed=2)
    state, f = ba_problem(scene, n_fixed=1)
    keep = scene.obs_cameras >= n_chain
    reproj = type(f)(scene.K, scene.obs_cameras[keep], scene.obs_points[keep], scene.uv[keep])
    views = np.bincount(scene.obs_points[keep], minlength=state.num_points)
    state.point_fixed[:] = views < 2
    pairs = np.stack([np.arange(n_chain + 1), np.arange(1, n_chain + 2)], axis=1)
    dpc = DPCFactor.from_state(state, pairs, np.full(6, 1e4))
    return state, [reproj, dpc]


def test_chain_split_point() -> None:
    """The chain ends where the rest stops reaching back further than ``SPLIT_BAND`` cameras."""
    reach = np.array([0, 0, 1, 2, 3, 4, 5, 6, 6, 6, 7, 8, 9, 9])  # chain 0-7, then a window
    assert _chain_split_point(reach) == (8, 2)
    assert _chain_split_point(np.zeros(12, dtype=np.int64)) == (0, 0)  # everything coupled
    assert _chain_split_point(np.array([0, 0, 1] + [1] * 9)) == (0, 0)  # chain too short
    # a tail that reaches back to the chain's 4th-last camera: the chain shrinks until it fits
    m, r = _chain_split_point(np.array([0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 8, 8, 8, 8]))
    assert (m, r) == (10, 2)


@pytest.mark.parametrize("damping", [0.0, 1e-3])
def test_chain_split_equals_dense(make_street, ba_problem, damping) -> None:
    """The pose-graph chain is factorised apart (banded) and the solve, the covariance and the
    reduced matrix are those of the dense system."""
    state, factors = _chain_then_window(make_street, ba_problem)
    neq = assemble(factors, state)
    fac = SchurFactorization(neq, damping, "marquardt")
    assert fac._split is not None and fac._split.n_A >= 6 * 5
    H, g = neq.dense()
    H = H + damping * np.diag(np.maximum(np.diag(H), 1e-12))
    dc, dp = fac.solve(-neq.g_c, -neq.g_p)
    x = np.linalg.solve(H, -g)
    np.testing.assert_allclose(np.concatenate([dc.ravel(), dp.ravel()]), x, rtol=1e-7, atol=1e-10)
    n_c = 6 * neq.num_free_cameras
    S = H[:n_c, :n_c] - H[:n_c, n_c:] @ np.linalg.solve(H[n_c:, n_c:], H[n_c:, :n_c])
    np.testing.assert_allclose(fac.S, S, rtol=1e-7, atol=1e-8 * np.abs(S).max())
    if damping == 0.0:
        np.testing.assert_allclose(
            fac.camera_covariance_full(), np.linalg.inv(S), rtol=1e-6, atol=1e-12
        )


@pytest.mark.parametrize("r", [0, 1, 2])
def test_chain_split_solves_any_coupling_width(r) -> None:
    """``_ChainSplit`` on a synthetic S: a block-tridiagonal chain of 6 cameras, a dense rest of
    4 coupled to the chain's last ``r`` cameras (none for r = 0), against a dense solve."""
    rng = np.random.default_rng(r)
    m, rest = 6, 4
    n = 6 * (m + rest)
    S = np.zeros((n, n))
    for i in range(m):  # chain: each camera with its successor
        S[6 * i : 6 * i + 12, 6 * i : 6 * i + 12] += 0.3 * rng.normal(size=(12, 12))
    A = rng.normal(size=(6 * rest, 6 * rest))
    S[6 * m :, 6 * m :] += A
    S[6 * (m - r) : 6 * m, 6 * m :] += rng.normal(size=(6 * r, 6 * rest))
    if r == 0:  # the chain's last link into the rest removed
        S[6 * (m - 1) : 6 * m, 6 * m :] = 0.0
        S[6 * m :, 6 * (m - 1) : 6 * m] = 0.0
    S = S @ S.T + n * np.eye(n)  # SPD; squaring widens every coupling by one camera
    b = rng.normal(size=(n, 3))
    split = _ChainSplit(S, m, r + 1 if r else 0)
    np.testing.assert_allclose(split.solve(b), np.linalg.solve(S, b), rtol=1e-9, atol=1e-12)
    assert split.finite
