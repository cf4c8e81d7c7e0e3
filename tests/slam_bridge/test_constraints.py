"""GPS, DEM, odometry and building constraints (appendix B.3): Jacobians, sparsity, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.ba.normal_equations import assemble
from slam_bridge.ba.robust import GemanMcClureKernel
from slam_bridge.ba.state import BAState
from slam_bridge.factors.building import BuildingFactor, WeightedKernel
from slam_bridge.factors.dem import DEMFactor, DemSegments
from slam_bridge.factors.gps import GPSFactor, GPSFixError
from slam_bridge.factors.odometry import OdometryFactor, dead_reckon
from slam_bridge.geometry.lie import so3_exp


def _state(seed: int = 0, C: int = 5, P: int = 8) -> BAState:
    rng = np.random.default_rng(seed)
    R = so3_exp(rng.normal(scale=0.3, size=(C, 3)))
    t = np.cumsum(rng.normal(size=(C, 3)) + [1.0, 0.2, 0.0], axis=0)
    X = rng.normal(scale=5.0, size=(P, 3))
    fixed = np.zeros(C, dtype=bool)
    fixed[0] = True
    return BAState(R, t, X, camera_fixed=fixed)


def _numeric_check(factor, state: BAState, h: float = 1e-6, atol: float = 1e-7) -> None:
    """Central differences on the manifold (``BAState.retract``) vs the block's Jacobians."""
    blk = factor.evaluate(state)
    M, k = blk.residuals.shape
    cmap, pmap = state.camera_index_map, state.point_index_map
    Cf, Pf = state.free_cameras.size, state.free_points.size
    for c in range(Cf):
        for d in range(6):
            dc = np.zeros((Cf, 6))
            dc[c, d] = h
            rp = factor.evaluate(state.retract(dc, np.zeros((Pf, 3)))).residuals
            rm = factor.evaluate(state.retract(-dc, np.zeros((Pf, 3)))).residuals
            num = (rp - rm) / (2 * h)
            ana = np.zeros((M, k))
            for s in range(blk.cameras.shape[1]):
                hit = cmap[blk.cameras[:, s]] == c
                ana[hit] += blk.J_cameras[hit, s, :, d]
            np.testing.assert_allclose(ana, num, atol=atol, rtol=1e-6)
    if blk.points is not None:
        for p in range(Pf):
            for d in range(3):
                dp = np.zeros((Pf, 3))
                dp[p, d] = h
                rp = factor.evaluate(state.retract(np.zeros((Cf, 6)), dp)).residuals
                rm = factor.evaluate(state.retract(np.zeros((Cf, 6)), -dp)).residuals
                num = (rp - rm) / (2 * h)
                ana = np.zeros((M, k))
                hit = pmap[blk.points] == p
                ana[hit] = blk.J_points[hit, :, d]
                np.testing.assert_allclose(ana, num, atol=atol, rtol=1e-6)


def _no_dense(factor, state: BAState) -> None:
    """The constraint's Hessian has no camera-camera off-diagonal and no camera-point block."""
    ne = assemble([factor], state)
    assert ne.pairs.shape[0] == 0
    assert ne.W.shape[0] == 0


# ------------------------------------------------------------------------------------------ GPS
def test_gps_jacobian_and_structure() -> None:
    state = _state()
    f = GPSFactor([1, 2, 4], [[1.0, 2.0], [3.0, 1.0], [5.0, 5.0]], [1.0, 4.0, 0.5])
    _numeric_check(f, state)
    _no_dense(f, state)
    ne = assemble([f], state)
    # only the translation x, y diagonal entries of the constrained cameras (eq. B.12)
    H, _ = ne.dense()
    nz = np.flatnonzero(np.abs(H).sum(axis=0))
    cmap = state.camera_index_map
    expected = sorted(6 * cmap[c] + 3 + a for c in (1, 2, 4) for a in (0, 1))
    assert nz.tolist() == expected


def test_gps_cost_value() -> None:
    state = _state()
    xy = state.t_wc[4, :2] + [3.0, -4.0]
    f = GPSFactor.most_recent(state, xy, weight=2.0)
    assert f.cameras.tolist() == [4]
    assert f.cost(state) == pytest.approx(2.0 * 25.0)
    assert f.evaluate(state).cost() == pytest.approx(f.cost(state))


def test_gps_missing_fix_skipped_or_raised() -> None:
    state = _state()
    xy = np.array([[1.0, 2.0], [np.nan, np.nan], [5.0, 5.0]])
    f = GPSFactor([1, 2, 4], xy)
    assert f.cameras.tolist() == [1, 4]
    assert np.isfinite(f.cost(state))
    with pytest.raises(GPSFixError, match="missing"):
        GPSFactor([1, 2, 4], xy, skip_missing=False)
    with pytest.raises(GeosegError):
        GPSFactor([1], [[np.inf, 0.0]])
    with pytest.raises(GeosegError):
        GPSFactor([1], [[0.0, 0.0]], [-1.0])


# ------------------------------------------------------------------------------------------ DEM
def _dem() -> DemSegments:
    xy0 = np.array([[-10.0, -10.0], [0.0, 5.0], [20.0, 0.0]])
    xy1 = np.array([[30.0, 10.0], [10.0, 30.0], [20.0, 40.0]])
    return DemSegments(xy0, xy1, np.array([1.0, 2.0, 0.0]), np.array([3.0, -1.0, 4.0]))


def test_dem_segments_altitude_and_gradient() -> None:
    dem = _dem()
    # on the first segment, half way: altitude 2
    assert dem.altitude_at(np.array([[10.0, 0.0]]))[0] == pytest.approx(2.0)
    rng = np.random.default_rng(3)
    xy = rng.uniform(-5, 25, size=(20, 2))
    g = dem.gradient_at(xy)
    h = 1e-6
    num = np.stack(
        [
            (dem.altitude_at(xy + [h, 0]) - dem.altitude_at(xy - [h, 0])) / (2 * h),
            (dem.altitude_at(xy + [0, h]) - dem.altitude_at(xy - [0, h])) / (2 * h),
        ],
        axis=1,
    )
    np.testing.assert_allclose(g, num, atol=1e-6)


def test_dem_jacobian_and_structure() -> None:
    state = _state()
    f = DEMFactor([1, 2, 3, 4], _dem(), camera_height=1.5, weights=[1.0, 2.0, 3.0, 4.0])
    _numeric_check(f, state)
    _no_dense(f, state)
    r = f.evaluate(state).residuals[:, 0]
    z = state.t_wc[[1, 2, 3, 4], 2] - _dem().altitude_at(state.t_wc[[1, 2, 3, 4], :2]) - 1.5
    np.testing.assert_allclose(r, np.sqrt([1.0, 2.0, 3.0, 4.0]) * z)


def test_dem_bad_input() -> None:
    with pytest.raises(GeosegError):
        DemSegments(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    with pytest.raises(GeosegError):
        DemSegments(np.zeros((1, 2)), np.ones((1, 2)), np.array([np.nan]), np.zeros(1))

    class NaNTerrain:
        def altitude_at(self, xy):
            return np.full(len(xy), np.nan)

        def gradient_at(self, xy):
            return np.zeros((len(xy), 2))

    with pytest.raises(GeosegError, match="non-finite"):
        DEMFactor([1], NaNTerrain(), 1.5).evaluate(_state())


# ------------------------------------------------------------------------------------- odometry
def test_dead_reckon() -> None:
    pos = dead_reckon(np.zeros(3), np.array([[1.0, 0, 0], [0, 2.0, 0]]), np.array([2.0, 0.5]))
    np.testing.assert_allclose(pos, [[2.0, 0, 0], [2.0, 1.0, 0]])
    pos2 = dead_reckon(
        np.zeros(2),
        np.array([1.0, 1.0]),
        np.array([1.0, 1.0]),
        heading_rad=np.array([0.0, np.pi / 2]),
    )
    np.testing.assert_allclose(pos2, [[1.0, 0.0], [1.0, 1.0]], atol=1e-12)
    with pytest.raises(GeosegError):
        dead_reckon(np.zeros(3), np.array([[np.nan, 0, 0]]), np.array([1.0]))


@pytest.mark.parametrize("dim", [2, 3])
def test_odometry_jacobian_and_structure(dim: int) -> None:
    state = _state()
    target = state.t_wc[[2, 3, 4], :dim] + 0.7
    f = OdometryFactor([2, 3, 4], target, [1.0, 2.0, 0.5])
    _numeric_check(f, state)
    _no_dense(f, state)
    with pytest.raises(GeosegError):
        OdometryFactor([1], np.array([[np.nan, 0.0]]))


# ------------------------------------------------------------------------------------- building
def test_building_jacobian_weights_and_structure() -> None:
    state = _state(P=10)
    rng = np.random.default_rng(7)
    n = rng.normal(size=(6, 3))
    c = rng.normal(size=6)
    W = rng.uniform(0.2, 2.0, size=6)
    f = BuildingFactor([0, 2, 3, 5, 7, 9], n, c, W, sigma=0.8)
    _numeric_check(f, state)
    ne = assemble([f], state)
    assert ne.pairs.shape[0] == 0 and ne.W.shape[0] == 0
    assert np.all(ne.U == 0)  # point-only terms
    # cost = sum W rho_GM(d^2)
    nn = n / np.linalg.norm(n, axis=1, keepdims=True)
    d = np.einsum("ma,ma->m", state.X_w[[0, 2, 3, 5, 7, 9]], nn) - c / np.linalg.norm(n, axis=1)
    expected = np.sum(W * 0.64 * d**2 / (0.64 + d**2))
    assert f.cost(state) == pytest.approx(expected)
    assert ne.cost == pytest.approx(expected)


def test_weighted_kernel_gradient() -> None:
    k = WeightedKernel(GemanMcClureKernel(0.5), np.array([1.0, 3.0]))
    s = np.array([0.3, 2.0])
    h = 1e-7
    np.testing.assert_allclose(k.weight(s), (k.rho(s + h) - k.rho(s - h)) / (2 * h), rtol=1e-6)


def test_building_bad_input() -> None:
    with pytest.raises(GeosegError):
        BuildingFactor([0], np.zeros((1, 3)), [0.0])
    with pytest.raises(GeosegError):
        BuildingFactor([0], np.ones((1, 3)), [np.nan])
    with pytest.raises(GeosegError):
        BuildingFactor([0], np.ones((1, 3)), [0.0], [-1.0])


def test_dem_any_terrain_model() -> None:
    """A callable terrain (sloped plane) through the TerrainModel protocol."""

    class Plane:
        def altitude_at(self, xy):
            return 0.1 * xy[:, 0] - 0.05 * xy[:, 1] + 2.0

        def gradient_at(self, xy):
            return np.tile([0.1, -0.05], (len(xy), 1))

    state = _state()
    f = DEMFactor([1, 3, 4], Plane(), np.array([1.5, 1.4, 1.6]))
    _numeric_check(f, state)
    t = state.t_wc[[1, 3, 4]]
    expected = t[:, 2] - (0.1 * t[:, 0] - 0.05 * t[:, 1] + 2.0) - [1.5, 1.4, 1.6]
    np.testing.assert_allclose(f.evaluate(state).residuals[:, 0], expected)


def test_dem_segments_from_synth_model() -> None:
    from geoseg.synth.dem import DemModel

    p0 = np.array([[0.0, 0.0], [10.0, 0.0]])
    p1 = np.array([[10.0, 0.0], [10.0, 10.0]])
    z0, z1 = np.array([1.0, 2.0]), np.array([2.0, 4.0])
    model = DemModel(p0, p1, z0, z1, np.zeros(2, dtype=int), z0, z1)
    dem = DemSegments.from_model(model)
    xy = np.array([[3.0, 0.5], [10.5, 7.0], [-2.0, 1.0]])
    np.testing.assert_allclose(dem.altitude_at(xy), model.altitude_at(xy))
    with pytest.raises(GeosegError):
        DemSegments.from_model(object())
