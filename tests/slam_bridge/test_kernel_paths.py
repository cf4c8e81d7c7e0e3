"""The compiled (numba) and pure-NumPy paths of the k-BA give the same normal equations and steps.

CI runs whichever path is installed; this test pins the other one against it, so the NumPy
fallback (``SLAM_BRIDGE_NUMBA=0`` or no numba) stays correct.
"""

from __future__ import annotations

import numpy as np
import pytest

import slam_bridge.problem as problem
from slam_bridge.problem import assemble
from slam_bridge.solvers.schur import SchurFactorization

pytest.importorskip("numba")


def _solve_both_paths(monkeypatch, state, factor):
    results = []
    for compiled in (True, False):
        monkeypatch.setattr(problem, "USE_NUMBA", compiled)
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
    """The compiled DPC residuals and Jacobians equal the :mod:`slam_bridge.lie` ones, below
    and above the series threshold and past pi/2 (so3_log's near-pi branch), with one and
    with per-pair weights."""
    from slam_bridge import lie
    from slam_bridge.factors.pose_graph_dpc import dpc_residuals, dpc_whitener

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
            monkeypatch.setattr(problem, "USE_NUMBA", compiled)
            out.append(dpc_residuals(R_i, t_i, R_j, t_j, R_hat, t_hat, W))
            r_only, no_i, no_j = dpc_residuals(
                R_i, t_i, R_j, t_j, R_hat, t_hat, W, with_jacobians=False
            )
            np.testing.assert_array_equal(r_only, out[-1][0])
            assert no_i is None and no_j is None
        for a, b in zip(*out):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-13 * max(1.0, np.abs(b).max()))
