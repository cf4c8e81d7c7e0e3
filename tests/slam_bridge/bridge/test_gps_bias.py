"""The GPS bias estimated from the building model (:mod:`slam_bridge.bridge.gps_bias`): a
known constant bias is recovered from the facades, an unbiased GPS keeps its fixes and weight,
and in the loop of a tiny drive the estimate brings a biased GPS's keyframes back."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from slam_bridge.bridge.association import Association
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.bridge.facades import Facades
from slam_bridge.bridge.gps_bias import BuildingGpsBias, GpsBiasConfig, solve_bias
from slam_bridge.errors import SlamError
from slam_bridge.slam.fusion import GpsConstraints


def _crossing() -> Facades:
    """Four facades around a crossing at the origin: two along x (normals -y, +y), two along
    y (normals -x, +x), each 20 m long and 10 m high, 6 m from the centre line."""
    p0 = np.array([[-10.0, 6.0], [10.0, -6.0], [6.0, 10.0], [-6.0, -10.0]])
    p1 = np.array([[10.0, 6.0], [-10.0, -6.0], [6.0, -10.0], [-6.0, 10.0]])
    normal = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    d = np.einsum("fi,fi->f", normal[:, :2], p0)
    return Facades(p0, p1, np.zeros(4), np.full(4, 10.0), normal, d, np.full(4, -1))


def _window(facades: Facades, shift: np.ndarray, per_facade: int = 8, seed: int = 0):
    """``(association, problem)``: ``per_facade`` points on each facade (2 cm noise), the whole
    map shifted by ``shift`` ``(2,)``, as a map that follows fixes biased by ``shift``."""
    rng = np.random.default_rng(seed)
    pts, fac = [], []
    for f in range(len(facades)):
        s = rng.uniform(0.1, 0.9, per_facade)
        xy = facades.p0[f] + s[:, None] * (facades.p1[f] - facades.p0[f])
        z = rng.uniform(1.0, 9.0, per_facade)
        pts.append(np.column_stack([xy, z]))
        fac.append(np.full(per_facade, f))
    X = (
        np.concatenate(pts)
        + np.r_[shift, 0.0]
        + rng.normal(0.0, 0.02, (len(facades) * per_facade, 3))
    )
    facade = np.concatenate(fac)
    assoc = Association(facade, np.ones(facade.size), "bayes")
    # three cameras along the street, at the truth shifted like the map
    t_wc = np.array([[-2.0, 0.0, 1.5], [0.0, 0.0, 1.5], [2.0, 0.0, 1.5]]) + np.r_[shift, 0.0]
    state = SimpleNamespace(
        X_w=X, t_wc=t_wc, R_wc=np.tile(np.eye(3), (3, 1, 1)), free_cameras=np.arange(3)
    )
    problem = SimpleNamespace(
        point_ids=np.arange(facade.size), state=state, camera_ids=np.arange(3)
    )
    return assoc, problem


def _fixes(bias: np.ndarray):
    """Fixes of the three cameras of :func:`_window` (keyframes 0-2 at times 0-2 s): the
    truth + ``bias``."""
    truth = np.array([[-2.0, 0.0], [0.0, 0.0], [2.0, 0.0]])
    return lambda t, R_wc: truth[int(round(t))] + bias if t < 3 else None


def test_solve_bias_is_the_weighted_least_squares_with_its_prior():
    n = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    b, cov, p = solve_bias(n, np.array([2.0, 1.0, -1.0]), np.array([1.0, 1.0, 1.0]), 1e3)
    np.testing.assert_allclose(b, [2.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(cov, np.diag([1.0, 0.5]), atol=1e-5)
    assert p == 1.0  # no unbiased component
    # one facade: the other axis keeps the prior (no correction, its spread)
    b, cov, _ = solve_bias(n[:1], np.array([2.0]), np.array([1.0]), 1.0)
    np.testing.assert_allclose(b, [1.0, 0.0])
    np.testing.assert_allclose(cov, np.diag([0.5, 1.0]))


def test_the_mixture_detects_a_bias_and_leaves_model_errors_alone():
    """Ten facades a side whose offsets scatter by a metre (the GIS model's errors): offsets
    of 2 m on average are a bias, taken whole; of 0.2 m, the model's errors, left alone."""
    rng = np.random.default_rng(0)
    n = np.repeat([[1.0, 0.0], [0.0, 1.0]], 10, axis=0)
    w = np.full(20, 1.0 / 1.2**2)
    noise = rng.normal(0.0, 1.0, (2, 10))
    noise = (noise - noise.mean(axis=1, keepdims=True)).ravel()  # no mean on either axis
    biased, _, p1 = solve_bias(n, 2.0 + noise, w, 1.5, 0.3, 0.5)
    unbiased, _, p0 = solve_bias(n, 0.2 + noise, w, 1.5, 0.3, 0.5)
    assert p1 > 0.99 and np.all(biased > 1.8)
    assert p0 < 0.2 and np.all(np.abs(unbiased) < 0.1)
    # no facade: the prior's mixture, no correction
    b, cov, p = solve_bias(np.zeros((0, 2)), np.zeros(0), np.zeros(0), 1.5, 0.3, 0.25)
    np.testing.assert_allclose(b, 0.0)
    np.testing.assert_allclose(cov, np.eye(2) * (0.25 * 1.5**2 + 0.75 * 0.3**2))
    assert p == pytest.approx(0.25)


@pytest.mark.parametrize("map_error", [(1.7, -1.1), (0.0, 0.0), (-0.6, 0.9)])
def test_a_constant_bias_is_recovered_from_exact_facades(map_error):
    """Whatever the map's own error (following the biased fixes, on the truth, or off both),
    facades + fixes give the bias."""
    facades = _crossing()
    bias = np.array([1.7, -1.1])
    assoc, problem = _window(facades, np.array(map_error))
    cfg = GpsBiasConfig(enabled=True, facade_sigma_m=0.05)  # an exact model
    est = BuildingGpsBias(BuildingConstraints(facades, association=assoc), _fixes(bias), cfg)
    slam_map = SimpleNamespace(timestamps=np.arange(10.0))
    b, cov = est.estimate(slam_map, problem, 2)
    np.testing.assert_allclose(b, bias, atol=0.03)
    assert np.all(np.linalg.eigvalsh(cov) < 0.01)
    # the same facades seen again: still one look each, the same estimate
    b2, cov2 = est.estimate(slam_map, problem, 2)
    np.testing.assert_allclose(b2, b)
    np.testing.assert_allclose(cov2, cov)


def test_the_corrected_fix_enters_the_fusion():
    facades = _crossing()
    bias = np.array([1.2, 0.8])
    assoc, problem = _window(facades, bias)
    est = BuildingGpsBias(
        BuildingConstraints(facades, association=assoc), _fixes(bias),
        GpsBiasConfig(enabled=True, facade_sigma_m=0.05, inflate=False),
    )  # fmt: skip
    truth = np.array([[-2.0, 0.0], [0.0, 0.0], [2.0, 0.0]])
    gps = GpsConstraints(np.arange(3.0), truth + bias, weight=2.0, bias=est)
    (f,) = gps.factors(SimpleNamespace(timestamps=np.arange(3.0)), problem, 2)
    np.testing.assert_allclose(f.xy_gps[0], truth[2], atol=0.03)
    assert f.sqrt_weights[0] ** 2 == pytest.approx(2.0)


def test_one_street_corrects_only_across_it():
    facades = _crossing()
    bias = np.array([1.0, 2.0])
    assoc, problem = _window(facades, bias)
    keep = assoc.facade <= 1  # the two facades along x: they see y only
    assoc = Association(np.where(keep, assoc.facade, -1), keep.astype(float), "bayes")
    est = BuildingGpsBias(
        BuildingConstraints(facades, association=assoc), _fixes(bias),
        GpsBiasConfig(enabled=True, facade_sigma_m=0.05, prior_sigma_m=1.5),
    )  # fmt: skip
    b, cov = est.estimate(SimpleNamespace(timestamps=np.arange(5.0)), problem, 2)
    np.testing.assert_allclose(b, [0.0, 2.0], atol=0.03)
    assert cov[0, 0] == pytest.approx(1.5**2, rel=0.01) and cov[1, 1] < 0.01


def test_unbiased_gps_keeps_its_fixes_and_weight():
    """Fixes on the truth, a map 0.5 m off it: no correction; the weight is lowered only by
    what the GIS model's errors leave unknown (``inflate``), and not at all without it."""
    facades = _crossing()
    assoc, problem = _window(facades, np.array([0.5, -0.3]), per_facade=12)
    truth = np.array([[-2.0, 0.0], [0.0, 0.0], [2.0, 0.0]])
    for inflate, lowest in ((True, 0.6), (False, 1.0)):
        est = BuildingGpsBias(
            BuildingConstraints(facades, association=assoc), _fixes(np.zeros(2)),
            GpsBiasConfig(enabled=True, inflate=inflate),
        )  # fmt: skip
        gps = GpsConstraints(np.arange(3.0), truth, weight=1.0, bias=est)
        (f,) = gps.factors(SimpleNamespace(timestamps=np.arange(3.0)), problem, 2)
        np.testing.assert_allclose(f.xy_gps[0], truth[2], atol=0.05)
        assert lowest <= f.sqrt_weights[0] ** 2 <= 1.0
        assert np.linalg.norm(est.history[-1][2]) < 0.05


def test_far_offsets_and_thin_facades_are_not_evidence():
    facades = _crossing()
    assoc, problem = _window(facades, np.array([5.0, 5.0]))  # beyond max_offset_m
    est = BuildingGpsBias(
        BuildingConstraints(facades, association=assoc), _fixes(np.zeros(2)),
        GpsBiasConfig(enabled=True),
    )  # fmt: skip
    b, cov = est.estimate(SimpleNamespace(timestamps=np.arange(3.0)), problem, 2)
    np.testing.assert_allclose(b, 0.0)
    est = BuildingGpsBias(
        BuildingConstraints(facades, association=assoc), _fixes(np.zeros(2)),
        GpsBiasConfig(enabled=True, min_points=20, max_offset_m=10.0),
    )  # fmt: skip
    b, _ = est.estimate(SimpleNamespace(timestamps=np.arange(3.0)), problem, 2)
    np.testing.assert_allclose(b, 0.0)  # 8 points per facade: too few
    est = BuildingGpsBias(  # no fix in the window (a dropout): nothing to compare with
        BuildingConstraints(facades, association=assoc), lambda t, R: None,
        GpsBiasConfig(enabled=True, max_offset_m=10.0),
    )  # fmt: skip
    b, _ = est.estimate(SimpleNamespace(timestamps=np.arange(3.0)), problem, 2)
    np.testing.assert_allclose(b, 0.0)


def test_old_facades_fade():
    facades = _crossing()
    assoc, problem = _window(facades, np.array([1.0, 1.0]))
    cfg = GpsBiasConfig(enabled=True, facade_sigma_m=0.1, memory_s=2.0)
    est = BuildingGpsBias(
        BuildingConstraints(facades, association=assoc), _fixes(np.array([1.0, 1.0])), cfg
    )
    b0, _ = est.estimate(SimpleNamespace(timestamps=np.array([0.0, 1.0, 2.0, 100.0])), problem, 2)
    est.constraints.association = None  # no facade since
    b1, cov1 = est.estimate(
        SimpleNamespace(timestamps=np.array([0.0, 1.0, 2.0, 100.0])), problem, 3
    )
    assert np.linalg.norm(b0) > 1.3 and np.allclose(b1, 0.0)
    share = cfg.biased_share
    spread = share * cfg.prior_sigma_m**2 + (1 - share) * cfg.unbiased_sigma_m**2
    np.testing.assert_allclose(cov1, np.eye(2) * spread)


@pytest.mark.parametrize(
    "field",
    [
        "prior_sigma_m",
        "facade_sigma_m",
        "memory_s",
        "min_points",
        "biased_share",
        "unbiased_sigma_m",
    ],
)
def test_bad_settings(field):
    with pytest.raises(SlamError, match=field):
        GpsBiasConfig(**{field: 0})


def test_in_the_loop_a_biased_gps_is_caught(noisy):
    """A tiny drive (known start poses, exact facades with the oracle's association) with every
    keyframe's fix off by a constant 1.5 m: GPS fusion alone follows it; with the bias
    estimated from the facades the keyframes come back (measured: 0.81 -> 0.04 m mean error,
    the last estimate within 0.15 m of the bias)."""
    from geoseg.synth import build_world
    from geoseg.synth.world import SurfaceKind
    from slam_bridge.bridge.association import nearest_facades
    from slam_bridge.experiments.landmarks import sample_landmarks
    from slam_bridge.slam.loop import KnownStartPoses, run_slam

    cfg, seq = noisy
    world = build_world(cfg.world)
    lm = sample_landmarks(world, seq.trajectory.t_wc[:, :2], cfg.landmarks, seed=cfg.seed)
    table = world.facades()
    facades = Facades(
        table.p0, table.p1, table.z_min, table.z_max, table.normal,
        np.einsum("fi,fi->f", table.normal[:, :2], table.p0), table.facade_id,
    )  # fmt: skip
    facade, _ = nearest_facades(facades, lm.X_w, radius_m=0.2)
    facade[lm.kind != SurfaceKind.FACADE] = -1
    oracle = Association(facade, (facade >= 0).astype(float), "oracle")
    bias = np.array([1.2, -0.9])
    fixes = seq.t_wc_true[:, :2] + bias

    def run(estimate: bool):
        gps = GpsConstraints(seq.timestamps, fixes)
        buildings = BuildingConstraints(facades, window_weight=0.4, association=oracle)
        if estimate:
            cfg_bias = GpsBiasConfig(enabled=True, facade_sigma_m=0.2)
            gps.bias = BuildingGpsBias(buildings, gps.camera_fix_at, cfg_bias)
        start = KnownStartPoses(
            seq.R_wc_true, seq.t_wc_true, cfg.slam.tracking.outlier_gate_px,
            cfg.start_keyframes, cfg.slam.mapping,
        )  # fmt: skip
        res = run_slam(seq.source(), "ba", start, [gps, buildings], cfg.slam)
        return res, gps.bias

    def error(res):
        return np.linalg.norm(res.map.t_wc[:, :2] - seq.t_wc_true[:, :2], axis=1).mean()

    plain, _ = run(False)
    caught, est = run(True)
    assert np.linalg.norm(est.history[-1][2] - bias) < 0.2
    assert error(caught) < 0.25 * error(plain)
