"""The compiled (numba) and pure-NumPy paths of the k-BA give the same normal equations and steps.

CI runs whichever path is installed; this test pins the other one against it, so the NumPy
fallback (``SLAM_BRIDGE_NUMBA=0`` or no numba) stays correct.
"""

from __future__ import annotations

import numpy as np
import pytest

import slam_bridge.ba.compiled as switch
from slam_bridge.ba.normal_equations import assemble
from slam_bridge.ba.solvers.schur import SchurFactorization

pytest.importorskip("numba")


def _solve_both_paths(monkeypatch, state, factor):
    results = []
    for compiled in (True, False):
        monkeypatch.setattr(switch, "USE_NUMBA", compiled)
        neq = assemble([factor], state)
        rhs_c = -neq.g_c
        rhs_p = -neq.g_p
        dc, dp = SchurFactorization(neq, damping=1e-3, mode="marquardt").solve(rhs_c, rhs_p)
        results.append((neq, dc, dp))
    return results


@pytest.mark.parametrize("kernel", [None, "huber"])
def test_compiled_and_numpy_paths_agree(monkeypatch, make_street, ba_problem, kernel) -> None:
    scene = make_street(12, points_per_camera=25, noise_px=1.0, seed=3)
    state, factor = ba_problem(scene, kernel=kernel)
    (neq_a, dc_a, dp_a), (neq_b, dc_b, dp_b) = _solve_both_paths(monkeypatch, state, factor)
    assert neq_a.cost == pytest.approx(neq_b.cost, rel=1e-12)
    for name in ("U", "V", "W", "g_c", "g_p", "U_pairs"):
        a, b = getattr(neq_a, name), getattr(neq_b, name)
        np.testing.assert_allclose(
            a, b, rtol=1e-10, atol=1e-10 * max(1.0, np.abs(b).max(initial=0.0))
        )
    np.testing.assert_allclose(dc_a, dc_b, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(dp_a, dp_b, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("scale", [1e-7, 1e-3, 0.05, 0.5, 3.0])
def test_dpc_compiled_and_numpy_paths_agree(monkeypatch, scale: float) -> None:
    """The compiled DPC residuals and Jacobians equal the :mod:`slam_bridge.geometry.lie` ones, below
    and above the series threshold and past pi/2 (so3_log's near-pi branch), with one and
    with per-pair weights."""
    from slam_bridge.factors.pose_graph_dpc import dpc_residuals, dpc_whitener
    from slam_bridge.geometry import lie

    rng = np.random.default_rng(7)
    M = 25
    R_i, R_j = lie.so3_exp(rng.normal(size=(M, 3))), lie.so3_exp(rng.normal(size=(M, 3)))
    t_i, t_j = rng.normal(size=(M, 3)), rng.normal(size=(M, 3))
    R_ij, t_ij = lie.se3_compose(*lie.se3_inverse(R_i, t_i), R_j, t_j)
    R_hat = R_ij @ lie.so3_exp(scale * rng.normal(size=(M, 3)) / np.sqrt(3.0))
    t_hat = t_ij + scale * rng.normal(size=(M, 3))
    A = rng.normal(size=(M, 6, 6))
    for W in (
        dpc_whitener(np.arange(1.0, 7.0)),
        dpc_whitener(A @ A.transpose(0, 2, 1) + 6 * np.eye(6)),
    ):
        out = []
        for compiled in (True, False):
            monkeypatch.setattr(switch, "USE_NUMBA", compiled)
            out.append(dpc_residuals(R_i, t_i, R_j, t_j, R_hat, t_hat, W))
            r_only, no_i, no_j = dpc_residuals(
                R_i, t_i, R_j, t_j, R_hat, t_hat, W, with_jacobians=False
            )
            np.testing.assert_array_equal(r_only, out[-1][0])
            assert no_i is None and no_j is None
        for a, b in zip(*out):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-13 * max(1.0, np.abs(b).max()))


def _pose_graph_families(scene, kernel):
    """MPC rows between successive cameras of ``scene`` (their shared points' pixels) and the
    first four successive camera pairs (for DPC links)."""
    from slam_bridge.factors.pose_graph_mpc import MPCFactor

    cams, pts, uv = scene.obs_cameras, scene.obs_points, scene.uv
    ci, cj, uvi, uvj = [], [], [], []
    for i in range(scene.R_wc.shape[0] - 1):
        a, b = np.flatnonzero(cams == i), np.flatnonzero(cams == i + 1)
        common, ia, ib = np.intersect1d(pts[a], pts[b], return_indices=True)
        ci += [i] * common.size
        cj += [i + 1] * common.size
        uvi.append(uv[a[ia]])
        uvj.append(uv[b[ib]])
    mpc = MPCFactor(scene.K, ci, cj, np.concatenate(uvi), np.concatenate(uvj), kernel=kernel)
    pairs = np.stack([np.arange(4), np.arange(1, 5)], axis=1)
    return mpc, pairs


@pytest.mark.parametrize("kernel", [None, "huber"])
def test_pair_families_compiled_and_numpy_paths_agree(
    monkeypatch, make_street, ba_problem, kernel
) -> None:
    """MPC (compressed rows on the NumPy path when least squares), DPC, GPS and the baseline
    lengths: the compiled shortcuts give the generic path's normal equations, with a fixed
    camera in the pairs."""
    from slam_bridge.factors.baseline_length import BaselineLengthFactor
    from slam_bridge.factors.gps import GPSFactor
    from slam_bridge.factors.pose_graph_dpc import DPCFactor

    scene = make_street(8, points_per_camera=15, noise_px=1.0, seed=4)
    state, _ = ba_problem(scene, n_fixed=1)  # perturbed poses: non-zero residuals
    mpc, pairs = _pose_graph_families(scene, kernel)
    truth = type(state)(scene.R_wc, scene.t_wc, scene.X_w)
    Ks = np.repeat(scene.K[None], 8, axis=0)
    Ks[:, 0, 0] *= np.linspace(0.9, 1.1, 8)  # one calibration per camera
    per_camera = type(mpc)(Ks, mpc.cameras_i, mpc.cameras_j, mpc.uv_i, mpc.uv_j, kernel=kernel)
    families = [
        mpc,
        mpc.relative_to(truth),
        per_camera,
        DPCFactor.from_state(truth, pairs, np.arange(1.0, 7.0), kernel=kernel),
        GPSFactor(np.array([5, 7]), scene.t_wc[[5, 7], :2] + 0.3, kernel=kernel),
        BaselineLengthFactor.from_state(truth, pairs, np.linspace(0.002, 0.01, len(pairs))),
    ]
    for family in families:
        out = []
        for compiled in (True, False):
            monkeypatch.setattr(switch, "USE_NUMBA", compiled)
            neq = assemble([family], state)
            if hasattr(family, "cost_and_invalid"):
                cost = family.cost_and_invalid(state)
            else:
                cost = (family.cost(state), 0)
            out.append((neq, *neq.dense(), cost))
        (neq_a, H_a, g_a, c_a), (neq_b, H_b, g_b, c_b) = out
        assert neq_a.cost == pytest.approx(neq_b.cost, rel=1e-10)
        assert c_a[0] == pytest.approx(c_b[0], rel=1e-10) and c_a[1] == c_b[1]
        assert neq_a.cost == pytest.approx(c_a[0], rel=1e-10)
        np.testing.assert_allclose(H_a, H_b, rtol=1e-9, atol=1e-9 * np.abs(H_b).max())
        np.testing.assert_allclose(g_a, g_b, rtol=1e-9, atol=1e-9 * np.abs(g_b).max())
        assert neq_a.pairs.shape == neq_b.pairs.shape


@pytest.mark.parametrize("scale", [1e-7, 0.05, 0.2, 2.5])
def test_retract_compiled_and_numpy_paths_agree(monkeypatch, scale: float) -> None:
    """The compiled camera update equals ``so3_exp(dw) @ R`` below and above the series
    threshold (0.1 rad); fixed cameras and points stay bit-identical on both paths."""
    from slam_bridge.ba.state import BAState
    from slam_bridge.geometry import lie

    rng = np.random.default_rng(11)
    C, P = 7, 9
    fixed_c = np.zeros(C, dtype=bool)
    fixed_c[[0, 4]] = True
    fixed_p = np.zeros(P, dtype=bool)
    fixed_p[2] = True
    state = BAState(
        lie.so3_exp(rng.normal(size=(C, 3))), rng.normal(size=(C, 3)), rng.normal(size=(P, 3)),
        camera_fixed=fixed_c, point_fixed=fixed_p,
    )  # fmt: skip
    dc = rng.normal(size=(C - 2, 6)) * scale
    dp = rng.normal(size=(P - 1, 3)) * scale
    out = []
    for compiled in (True, False):
        monkeypatch.setattr(switch, "USE_NUMBA", compiled)
        out.append(state.retract(dc, dp))
    a, b = out
    np.testing.assert_allclose(a.R_wc, b.R_wc, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(a.t_wc, b.t_wc)
    np.testing.assert_array_equal(a.X_w, b.X_w)
    np.testing.assert_array_equal(a.R_wc[fixed_c], state.R_wc[fixed_c])
    free = np.flatnonzero(~fixed_c)
    np.testing.assert_allclose(a.R_wc[free], lie.so3_exp(dc[:, :3]) @ state.R_wc[free], atol=1e-14)
