"""Levenberg-Marquardt: recovery on a noiseless scene, robust kernels, feasibility, results."""

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.ba.robust import GemanMcClureKernel, HuberKernel, TrivialKernel, get_kernel
from slam_bridge.ba.solvers.lm import BAObjective, LMConfig, LMStep, levenberg_marquardt
from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.geometry.lie import so3_log


@pytest.mark.parametrize("mode", ["marquardt", "additive"])
def test_lm_recovers_noiseless_scene(street_noiseless, ba_problem, mode):
    scene = street_noiseless
    state, f = ba_problem(scene, n_fixed=2)
    seen = []
    res = levenberg_marquardt(
        BAObjective([f], damping_mode=mode),
        state,
        LMConfig(max_iterations=100, damping_mode=mode, rel_cost_tol=1e-15, step_tol=1e-12),
        callback=lambda it, st, c: seen.append(c),
    )
    assert res.converged, res.termination
    assert res.initial_cost > 1e3
    assert res.cost < 1e-12
    rot_err = np.linalg.norm(so3_log(np.swapaxes(scene.R_wc, 1, 2) @ res.state.R_wc), axis=1)
    assert rot_err.max() < 1e-6
    assert np.abs(res.state.t_wc - scene.t_wc).max() < 1e-6
    assert np.abs(res.state.X_w - scene.X_w).max() < 1e-5
    # fixed cameras untouched, history consistent
    np.testing.assert_array_equal(res.state.t_wc[:2], state.t_wc[:2])
    assert res.cost_history[0] == res.initial_cost and res.cost_history[-1] == res.cost
    assert np.all(np.diff(res.cost_history) <= 0)
    assert len(res.iteration_times) == res.iterations and len(seen) == res.accepted
    assert res.time_per_iteration > 0


def test_robust_kernel_downweights_outlier(street, ba_problem):
    scene = street
    uv = scene.uv.copy()
    uv[7] += [60.0, -45.0]  # planted 75 px outlier on point p
    p = scene.obs_points[7]
    err = {}
    for kernel, perturbed in [(None, True), ("huber", True), ("geman_mcclure", False)]:
        f = ReprojectionFactor(
            scene.K, scene.obs_cameras, scene.obs_points, uv, kernel=kernel, kernel_scale=2.0
        )
        state, _ = ba_problem(scene, perturbed=perturbed)
        res = levenberg_marquardt(BAObjective([f]), state, LMConfig(max_iterations=100))
        r, _ = f.residuals(res.state)
        err[kernel] = (np.linalg.norm(res.state.X_w[p] - scene.X_w[p]), np.linalg.norm(r[7]))
    assert err[None][0] > 10.0  # least squares drags the point away (here to infinity)
    for k in ("huber", "geman_mcclure"):
        assert err[k][0] < 1.0
        assert err[k][1] > 60.0  # the outlier keeps its residual


def test_kernels_values():
    s = np.array([0.0, 0.25, 4.0, 100.0])
    np.testing.assert_allclose(TrivialKernel().rho(s), s)
    h = HuberKernel(1.0)
    np.testing.assert_allclose(h.rho(s), [0, 0.25, 3.0, 19.0])
    np.testing.assert_allclose(h.weight(s), [1, 1, 0.5, 0.1])
    g = GemanMcClureKernel(2.0)
    np.testing.assert_allclose(g.rho(s), 4 * s / (4 + s))
    # weight is the derivative of rho
    eps = 1e-6
    for k in (h, g):
        num = (k.rho(s[1:] + eps) - k.rho(s[1:] - eps)) / (2 * eps)
        np.testing.assert_allclose(k.weight(s[1:]), num, rtol=1e-6)
    assert isinstance(get_kernel("gm", 3.0), GemanMcClureKernel)
    with pytest.raises(GeosegError):
        get_kernel("cauchyish")


class _Quadratic:
    """F(x) = |x - 3|^2 on R^2 with an infeasible region x0 > 2.5 (hard constraint)."""

    def __init__(self):
        self.calls = 0

    def cost(self, x):
        return float(np.sum((x - 3.0) ** 2))

    def linearize(self, x):
        obj = self

        class Lin:
            cost = obj.cost(x)

            def solve(self, lam):
                d = -(x - 3.0) / (1.0 + lam)
                pred = -(2 * np.sum((x - 3.0) * d) + np.sum(d * d))
                return LMStep(d, pred, float(np.max(np.abs(d))))

        return Lin()

    def retract(self, x, d):
        return x + d

    def is_feasible(self, x):
        return x[0] < 2.5


def test_generic_objective_never_accepts_infeasible():
    obj = _Quadratic()
    visited = []
    res = levenberg_marquardt(
        obj, np.zeros(2), LMConfig(max_iterations=40), callback=lambda i, x, c: visited.append(x)
    )
    assert all(x[0] < 2.5 for x in visited)
    assert res.state[0] < 2.5
    assert res.cost < obj.cost(np.zeros(2))


def test_bad_config(street, ba_problem):
    state, f = ba_problem(street)
    with pytest.raises(GeosegError):
        levenberg_marquardt(BAObjective([f]), state, LMConfig(damping_mode="nope"))
    with pytest.raises(GeosegError):
        BAObjective([])


def test_point_behind_all_cameras_is_graceful(street_noiseless, ba_problem):
    scene = street_noiseless
    state, f = ba_problem(scene, perturbed=False)
    p = 0
    cams = f.cameras[f.points == p]
    X = state.X_w.copy()
    X[p] = state.t_wc[cams].mean(axis=0) - 50.0 * state.R_wc[cams[0]][:, 2]  # far behind
    state = type(state)(state.R_wc, state.t_wc, X, state.camera_fixed)
    res = levenberg_marquardt(BAObjective([f]), state, LMConfig(max_iterations=10))
    assert np.all(np.isfinite(res.state.X_w)) and np.all(np.isfinite(res.state.t_wc))
    np.testing.assert_allclose(res.state.X_w[p], X[p])  # no information: left where it was
    assert f.cost_and_invalid(res.state)[1] == cams.size


def test_all_cameras_fixed_refines_points_only(street, ba_problem):
    state, f = ba_problem(street, n_fixed=street.R_wc.shape[0])
    res = levenberg_marquardt(BAObjective([f]), state, LMConfig(max_iterations=30))
    assert res.cost < res.initial_cost
    np.testing.assert_array_equal(res.state.R_wc, state.R_wc)
    np.testing.assert_array_equal(res.state.t_wc, state.t_wc)


def test_retract_updates_free_parameters_only(street, ba_problem):
    """``retract`` moves the free cameras and points, keeps the fixed ones, returns masks of its
    own, and refuses an update that overflows to inf (never a silent non-finite state)."""
    state, _ = ba_problem(street, n_fixed=2)
    state.point_fixed[3] = True
    Cf, Pf = state.free_cameras.size, state.free_points.size
    rng = np.random.default_rng(0)
    dc, dp = rng.normal(scale=1e-2, size=(Cf, 6)), rng.normal(size=(Pf, 3))
    new = state.retract(dc, dp)
    fc, fp = state.free_cameras, state.free_points
    np.testing.assert_allclose(so3_log(new.R_wc[fc] @ state.R_wc[fc].transpose(0, 2, 1)), dc[:, :3])
    np.testing.assert_allclose(new.t_wc[fc] - state.t_wc[fc], dc[:, 3:])
    np.testing.assert_allclose(new.X_w[fp] - state.X_w[fp], dp)
    np.testing.assert_array_equal(new.t_wc[:2], state.t_wc[:2])
    np.testing.assert_array_equal(new.X_w[3], state.X_w[3])
    new.camera_fixed[5] = True  # the new state's masks are its own
    assert not state.camera_fixed[5] and state.camera_index_map[5] >= 0
    assert new.camera_index_map[5] == -1
    huge = state.copy()
    huge.X_w[fp[0]] = 1e308
    dp_big = np.zeros((Pf, 3))
    dp_big[0] = 1e308
    with np.errstate(over="ignore"), pytest.raises(GeosegError, match="X_w"):
        huge.retract(np.zeros((Cf, 6)), dp_big)


def test_dead_zone_kernel_is_free_within_its_band_and_quadratic_beyond():
    from slam_bridge.ba.robust import DeadZoneKernel

    k = DeadZoneKernel(2.0)
    r = np.array([0.0, 1.0, 1.99, 2.5, 4.0, 10.0])
    np.testing.assert_allclose(k.rho(r**2), [0, 0, 0, 0.25, 4.0, 64.0])
    s = np.array([0.5, 3.0, 9.0, 30.0])
    eps = 1e-6
    np.testing.assert_allclose(
        k.weight(s), (k.rho(s + eps) - k.rho(s - eps)) / (2 * eps), atol=1e-6
    )
    with pytest.raises(GeosegError):
        DeadZoneKernel(0.0)
