"""Barrier-term fusion (eq. 2.3, appendix B): derivatives, Sherman-Morrison, feasibility."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from slam_bridge.ba.solvers.barrier import (
    BarrierConfig,
    BarrierSolver,
    barrier_objective,
    barrier_system,
    sherman_morrison_solve,
    solve_barrier,
    vision_cost,
)
from slam_bridge.ba.solvers.lm import BAObjective, levenberg_marquardt
from slam_bridge.ba.solvers.schur import SchurFactorization
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.factors.building import BuildingFactor
from slam_bridge.factors.dem import DEMFactor, DemSegments
from slam_bridge.factors.gps import GPSFactor
from slam_bridge.factors.odometry import OdometryFactor
from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.geometry.lie import so3_exp


def _optimum(scene, n_fixed: int = 2) -> tuple[BAState, ReprojectionFactor]:
    """``X*``: the unconstrained k-BA optimum of a scene (first cameras fixed)."""
    fixed = np.zeros(scene.R_wc.shape[0], dtype=bool)
    fixed[:n_fixed] = True
    state = BAState(scene.R_wc, scene.t_wc, scene.X_w, camera_fixed=fixed)
    rep = ReprojectionFactor(scene.K, scene.obs_cameras, scene.obs_points, scene.uv)
    res = levenberg_marquardt(BAObjective([rep]), state)
    return res.state, rep


@pytest.fixture(scope="module")
def small_optimum():
    from slam_bridge.testing.scenes import street_scene

    scene = street_scene(5, points_per_camera=4, noise_px=1.0, seed=3)
    return _optimum(scene)


@pytest.fixture(scope="module")
def street_optimum():
    from slam_bridge.testing.scenes import street_scene

    scene = street_scene(8, points_per_camera=20, noise_px=1.0, seed=0)
    return _optimum(scene)


def _all_constraints(state: BAState) -> list:
    C = state.num_cameras
    dem = DemSegments(np.array([[-50.0, 0.0]]), np.array([[50.0, 0.0]]), [-1.0], [1.0])
    return [
        GPSFactor.most_recent(state, state.t_wc[-1, :2] + [0.3, 0.8]),
        DEMFactor(np.arange(2, C), dem, 1.5, weights=np.full(C - 2, 0.5)),
        OdometryFactor([C - 2], state.t_wc[[C - 2]] + [0.1, -0.1, 0.05]),
        BuildingFactor(np.arange(4), np.tile([0.0, 1.0, 0.0], (4, 1)), state.X_w[:4, 1] + 0.2),
    ]


# -------------------------------------------------------------------------------- derivatives
def test_barrier_gradient_central_differences(small_optimum) -> None:
    state, rep = small_optimum
    cons = _all_constraints(state)
    zeta, _ = vision_cost([rep], state)
    t, gamma = 1.05 * zeta, 0.3
    # evaluate away from X* so that grad zeta != 0
    rng = np.random.default_rng(0)
    Cf, Pf = state.free_cameras.size, state.free_points.size
    x = state.retract(rng.normal(scale=1e-4, size=(Cf, 6)), rng.normal(scale=1e-4, size=(Pf, 3)))
    assert vision_cost([rep], x)[0] < t
    sysm = barrier_system([rep], cons, x, t, gamma)
    g = np.concatenate([sysm.H_tilde.g_c.ravel(), sysm.H_tilde.g_p.ravel()])
    h = 1e-7
    num = np.zeros_like(g)
    for k in range(g.size):
        d = np.zeros(g.size)
        d[k] = h
        dp_ = (d[: 6 * Cf].reshape(Cf, 6), d[6 * Cf :].reshape(Pf, 3))
        dm_ = (-dp_[0], -dp_[1])
        fp = barrier_objective([rep], cons, x.retract(*dp_), t, gamma)
        fm = barrier_objective([rep], cons, x.retract(*dm_), t, gamma)
        num[k] = (fp - fm) / (2 * h)
    # the assembled g_f is half the gradient of f (core convention)
    np.testing.assert_allclose(2 * g, num, rtol=2e-5, atol=1e-6 * np.abs(num).max())


def test_barrier_hessian_exact_for_linear_residuals() -> None:
    """With residuals linear in the translations, H_f = 2 (H~ + u u^T) exactly (eq. B.4)."""
    rng = np.random.default_rng(1)
    C = 4
    state = BAState(so3_exp(rng.normal(size=(C, 3))), rng.normal(size=(C, 3)), np.zeros((0, 3)))
    vision = [OdometryFactor(np.arange(C), state.t_wc + rng.normal(scale=0.1, size=(C, 3)))]
    cons = [GPSFactor([1, 3], state.t_wc[[1, 3], :2] + 0.5, [2.0, 1.0])]
    zeta, _ = vision_cost(vision, state)
    t, gamma = 2.0 * zeta, 0.7
    sysm = barrier_system(vision, cons, state, t, gamma)
    H, _ = sysm.H_tilde.dense()
    u = sysm.u_c.ravel()
    model = 2 * (H + np.outer(u, u))
    idx = np.concatenate([np.arange(6 * c + 3, 6 * c + 6) for c in range(C)])

    def f(d: np.ndarray) -> float:
        dc = np.zeros((C, 6))
        dc[:, 3:] = d.reshape(C, 3)
        return barrier_objective(vision, cons, state.retract(dc, np.zeros((0, 3))), t, gamma)

    h = 1e-4
    n = idx.size
    num = np.zeros((n, n))
    for a in range(n):
        for b in range(n):
            ea, eb = np.eye(n)[a] * h, np.eye(n)[b] * h
            num[a, b] = (f(ea + eb) - f(ea - eb) - f(-ea + eb) + f(-ea - eb)) / (4 * h * h)
    np.testing.assert_allclose(
        model[np.ix_(idx, idx)], num, rtol=1e-5, atol=1e-6 * np.abs(num).max()
    )


def test_constraints_keep_the_dense_part_rank_one(street_optimum) -> None:
    """The constraints only add diagonal camera/point blocks to H~ (appendix B.3-B.4), so the
    barrier Hessian is sparse BA structure + the rank-1 u u^T, nothing else."""
    state, rep = street_optimum
    cons = _all_constraints(state)
    zeta, _ = vision_cost([rep], state)
    t = 1.05 * zeta
    with_c = barrier_system([rep], cons, state, t, 1.0)
    without = barrier_system([rep], [], state, t, 1.0)
    assert with_c.H_tilde.pairs.shape[0] == 0  # no camera-camera block at all
    H1, _ = with_c.H_tilde.dense()
    H0, _ = without.H_tilde.dense()
    diff = H1 - H0
    Cf = state.free_cameras.size
    sizes = [6] * Cf + [3] * state.free_points.size
    mask = np.zeros_like(diff, dtype=bool)
    o = 0
    for s_ in sizes:
        mask[o : o + s_, o : o + s_] = True
        o += s_
    assert np.abs(diff[~mask]).max() == 0.0
    assert np.abs(diff[mask]).max() > 0.0
    np.testing.assert_array_equal(with_c.u_c, without.u_c)  # u comes from zeta only


# --------------------------------------------------------------------------- Sherman-Morrison
@pytest.mark.parametrize("lam", [0.0, 1e-3])
def test_sherman_morrison_equals_dense_solve(street_optimum, lam: float) -> None:
    state, rep = street_optimum
    cons = _all_constraints(state)
    rng = np.random.default_rng(2)
    Cf, Pf = state.free_cameras.size, state.free_points.size
    x = state.retract(rng.normal(scale=1e-3, size=(Cf, 6)), rng.normal(scale=1e-3, size=(Pf, 3)))
    sysm = barrier_system([rep], cons, x, vision_cost([rep], x)[0] + 50.0, 2.0)
    fac = SchurFactorization(sysm.H_tilde, lam, "marquardt")
    b_c, b_p = rng.normal(size=(Cf, 6)), rng.normal(size=(Pf, 3))
    x_c, x_p = sherman_morrison_solve(fac, b_c, b_p, sysm.u_c, sysm.u_p)
    H, _ = sysm.H_tilde.dense()
    if lam:
        d = np.maximum(np.diag(H), 1e-12)
        H = H + lam * np.diag(d)
    u = np.concatenate([sysm.u_c.ravel(), sysm.u_p.ravel()])
    dense = np.linalg.solve(H + np.outer(u, u), np.concatenate([b_c.ravel(), b_p.ravel()]))
    got = np.concatenate([x_c.ravel(), x_p.ravel()])
    np.testing.assert_allclose(got, dense, rtol=1e-7, atol=1e-9 * np.abs(dense).max())
    assert np.abs(u).max() > 0  # the rank-1 term is really exercised


# ------------------------------------------------------------------------------- feasibility
class _PlantedSolver(BarrierSolver):
    """Proposes a step ``factor`` times too long on the first ``n_bad`` proposals; counts the
    proposals (one factorisation each)."""

    def __init__(self, *a, n_bad: int = 3, factor: float = 1000.0, **kw) -> None:
        super().__init__(*a, **kw)
        self.n_bad = n_bad
        self.factor = factor
        self.proposals = 0

    def propose_step(self, system, lam):
        dc, dp = super().propose_step(system, lam)
        self.proposals += 1
        if self.n_bad > 0:
            self.n_bad -= 1
            return self.factor * dc, self.factor * dp
        return dc, dp


def test_barrier_never_accepts_infeasible_steps(street_optimum) -> None:
    state, rep = street_optimum
    gps = GPSFactor.most_recent(state, state.t_wc[-1, :2] + [0.0, 3.0])
    solver = _PlantedSolver([rep], [gps], BarrierConfig(max_iterations=15), n_bad=3)
    res = solver.run(state)
    reasons = [h.reason for h in res.history]
    assert reasons[:3] == ["infeasible"] * 3  # the planted steps leave the barrier
    assert all(h.trial_zeta >= res.t for h in res.history if h.reason == "infeasible")
    assert all(h.trial_zeta < res.t for h in res.history if h.accepted)
    assert any(h.accepted for h in res.history)
    assert res.zeta < res.t
    assert vision_cost([rep], res.state)[0] == pytest.approx(res.zeta, rel=1e-12)


def test_infeasible_step_is_shortened_before_damping_rises(street_optimum) -> None:
    """An infeasible trial is retried halved, same direction and damping (no new proposal);
    a step shortened into the barrier is accepted; without backtracks the damping rises."""
    state, rep = street_optimum
    gps = GPSFactor.most_recent(state, state.t_wc[-1, :2] + [0.0, 1.0])
    cfg = BarrierConfig(max_iterations=15, max_backtracks=4)
    solver = _PlantedSolver([rep], [gps], cfg, n_bad=0)
    res = solver.run(state)
    first = [h for h in res.history if h.iteration == 1]
    # from X* the Newton step crosses the barrier (module docstring): shortened, then accepted
    assert first[0].reason == "infeasible" and first[0].step_scale == 1.0
    assert [h.step_scale for h in first] == [0.5**k for k in range(len(first))]
    assert len({h.lam for h in first}) == 1  # one damping, one factorisation
    assert first[-1].accepted and first[-1].step_scale < 1.0
    assert first[-1].step_norm == pytest.approx(first[0].step_norm * first[-1].step_scale)
    assert solver.proposals == len([h for h in res.history if h.step_scale == 1.0])
    assert all(h.trial_zeta >= res.t for h in res.history if h.reason == "infeasible")
    assert all(h.trial_zeta < res.t for h in res.history if h.accepted)
    second = [h for h in res.history if h.iteration == 2]
    assert second[0].lam == first[-1].lam  # a shortened step does not lower the damping
    assert res.zeta < res.t
    plain = solve_barrier([rep], [gps], state, BarrierConfig(max_iterations=15, max_backtracks=0))
    assert all(h.step_scale == 1.0 for h in plain.history)
    assert plain.history[0].reason == "infeasible"
    assert plain.history[1].lam == pytest.approx(10 * plain.history[0].lam)
    assert res.objective < plain.objective  # same budget, further along
    with pytest.raises(SlamError, match="max_backtracks"):
        BarrierConfig(max_backtracks=-1)


def test_gps_fusion_moves_latest_camera_towards_fix(street_optimum) -> None:
    state, rep = street_optimum
    target = state.t_wc[-1, :2] + [0.0, 1.0]
    gps = GPSFactor.most_recent(state, target)
    res = solve_barrier([rep], [gps], state)
    before = np.linalg.norm(state.t_wc[-1, :2] - target)
    after = np.linalg.norm(res.state.t_wc[-1, :2] - target)
    assert after < before - 0.05
    assert res.zeta_star < res.zeta < res.t
    assert res.t == pytest.approx(1.05 * res.zeta_star)
    assert res.constraint_cost < gps.cost(state)
    assert res.iterations == len({h.iteration for h in res.history})
    for a, b in zip(res.history, res.history[1:]):  # f decreases over accepted steps
        if a.accepted:
            assert b.objective <= a.objective


def test_zero_zeta_star_is_handled(caplog) -> None:
    from slam_bridge.testing.scenes import street_scene

    scene = street_scene(6, points_per_camera=10, noise_px=0.0, seed=4)
    fixed = np.zeros(6, dtype=bool)
    fixed[:2] = True
    state = BAState(scene.R_wc, scene.t_wc, scene.X_w, camera_fixed=fixed)
    rep = ReprojectionFactor(scene.K, scene.obs_cameras, scene.obs_points, scene.uv)
    assert rep.cost(state) < 1e-18
    gps = GPSFactor.most_recent(state, state.t_wc[-1, :2] + [0.5, 0.5])
    with caplog.at_level(logging.WARNING, logger="slam_bridge.ba.solvers.barrier"):
        res = solve_barrier([rep], [gps], state)
    assert "no slack" in caplog.text
    assert res.t > 0 and res.zeta < res.t
    assert np.all(np.isfinite(res.state.t_wc)) and np.all(np.isfinite(res.state.X_w))


def test_barrier_bad_config_and_inputs(street_optimum) -> None:
    state, rep = street_optimum
    with pytest.raises(SlamError):
        BarrierConfig(t_ratio=1.0)
    with pytest.raises(SlamError):
        BarrierSolver([], [])
    zeta, _ = vision_cost([rep], state)
    with pytest.raises(SlamError, match="outside the barrier"):
        barrier_system([rep], [], state, 0.5 * zeta, 1.0)
    # a missing GPS fix leaves nothing to fuse: the state stays X*
    gps = GPSFactor([state.num_cameras - 1], [[np.nan, np.nan]])
    res = solve_barrier([rep], [gps], state)
    np.testing.assert_array_equal(res.state.t_wc, state.t_wc)


def test_building_fusion_pulls_points_to_their_plane(street_optimum) -> None:
    """Point-only constraints (W, V blocks) go through the same Sherman-Morrison solve."""
    state, rep = street_optimum
    facade = np.flatnonzero(np.abs(state.X_w[:, 1] - 6.0) < 0.5)[:15]  # the y = +6 facade
    plane_y = 6.3  # the building model is 30 cm off
    f = BuildingFactor(
        facade, np.tile([0.0, 1.0, 0.0], (facade.size, 1)), np.full(facade.size, plane_y), sigma=1.0
    )
    res = solve_barrier([rep], [f], state)
    before = np.abs(state.X_w[facade, 1] - plane_y).mean()
    after = np.abs(res.state.X_w[facade, 1] - plane_y).mean()
    assert after < before
    assert res.zeta < res.t
