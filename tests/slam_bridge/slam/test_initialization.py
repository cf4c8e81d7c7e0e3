"""The image SLAM's start-up without ground truth, on simulated tracks of the tiny drive."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.errors import SlamError
from slam_bridge.experiments.fusion_ch3 import gps_for_setting
from slam_bridge.experiments.simulated_tracks import SimulatedTracks
from slam_bridge.geometry.lie import so3_exp, so3_log
from slam_bridge.slam.fusion import GpsConstraints
from slam_bridge.slam.initialization import (
    InitConfig,
    OdometryDistance,
    TwoViewStart,
    VehicleRig,
    fit_level_similarity,
    fit_similarity,
)
from slam_bridge.slam.loop import run_slam
from slam_bridge.slam.map import Map


def test_fit_similarity_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    R = so3_exp(np.array([0.3, -0.2, 1.1]))
    s, T = 2.5, np.array([10.0, -4.0, 2.0])
    src = rng.normal(size=(30, 3)) * 5
    dst = s * src @ R.T + T + rng.normal(scale=1e-3, size=(30, 3))
    s_hat, R_hat, T_hat = fit_similarity(src, dst)
    assert s_hat == pytest.approx(s, rel=1e-3)
    assert np.degrees(np.linalg.norm(so3_log(R_hat.T @ R))) < 0.05
    np.testing.assert_allclose(T_hat, T, atol=0.02)
    assert fit_similarity(src, dst, fix_scale=True)[0] == 1.0


@pytest.mark.parametrize("level", [False, True])
def test_weighted_fits_follow_the_accurate_pairs(level):
    """Ten pairs to a millimetre and ten a few metres off: weighted by their accuracy, the fit
    is the accurate pairs' own; equal weights give the unweighted fit."""
    rng = np.random.default_rng(1)
    R = so3_exp(np.array([0.0, 0.0, 0.8]))
    T = np.array([3.0, -2.0, 1.0])
    src = np.column_stack([rng.uniform(-30, 30, (20, 2)), rng.uniform(-1, 1, 20)])
    dst = src @ R.T + T
    dst[10:, :2] += rng.normal(scale=3.0, size=(10, 2))
    weights = np.r_[np.full(10, 100.0), np.full(10, 1.0)]

    def fit(w):
        if level:
            return fit_level_similarity(src, dst, up_src=np.array([0, 0, 1.0]), weights=w)
        return fit_similarity(src, dst, weights=w)

    _, R_w, T_w = fit(weights)
    _, R_u, T_u = fit(None)
    assert np.linalg.norm(so3_log(R_w.T @ R)) < 0.1 * np.linalg.norm(so3_log(R_u.T @ R))
    np.testing.assert_allclose(src[:10] @ R_w.T + T_w, dst[:10], atol=0.1)
    for a, b in zip(fit(np.ones(20)), fit(None)):
        np.testing.assert_allclose(a, b, atol=1e-9)
    with pytest.raises(SlamError, match="weights"):
        fit(np.r_[weights[:-1], 0.0])


def test_fit_similarity_up_axis_fixes_the_roll_of_collinear_points():
    """Points along a line leave the rotation about it free; the up-axis pair pins it."""
    R = so3_exp(np.array([0.0, 0.0, 0.7])) @ so3_exp(np.array([0.4, 0.0, 0.0]))
    src = np.column_stack([np.linspace(0, 30, 16), np.zeros(16), np.zeros(16)])
    dst = src @ R.T
    up_src = R.T @ np.array([0.0, 0.0, 1.0])  # the source's direction of the target's +z
    _, R_hat, _ = fit_similarity(src, dst, up_src=up_src, fix_scale=True)
    assert np.degrees(np.linalg.norm(so3_log(R_hat.T @ R))) < 1e-6
    with pytest.raises(SlamError, match="at least 2"):
        fit_similarity(src[:1], dst[:1])
    with pytest.raises(SlamError, match="coincide"):
        fit_similarity(np.zeros((4, 3)), dst[:4])


def test_odometry_distance_and_settings():
    odo = OdometryDistance(np.array([0.0, 1.0, 2.0]), np.array([2.0, 2.0, 4.0]))
    assert odo(0.0, 1.0) == pytest.approx(2.0)
    assert odo(1.0, 2.0) == pytest.approx(3.0)  # trapezoid
    assert odo(2.0, 3.0) == pytest.approx(4.0)  # constant beyond the end
    with pytest.raises(SlamError, match="increasing"):
        OdometryDistance(np.array([0.0, 0.0]), np.array([1.0, 1.0]))
    with pytest.raises(GeosegError, match="speed_mps"):
        OdometryDistance(np.array([0.0, 1.0]), np.array([1.0, np.nan]))
    with pytest.raises(GeosegError, match="camera_height_m"):
        VehicleRig(camera_height_m=0.0)
    with pytest.raises(SlamError, match="min_fixes"):
        InitConfig(min_fixes=1)


def _odometry(seq):
    traj = seq.trajectory
    return OdometryDistance(traj.timestamps, traj.speed)


def test_two_view_start_recovers_the_relative_pose_and_the_scale(noisy):
    cfg, seq = noisy
    start = TwoViewStart(odometry=_odometry(seq), mapping=cfg.slam.mapping)
    m = Map(seq.K, seq.image_size)
    got = start.start(m, seq.source())
    a, b = got.fixed_keyframes
    assert not got.georeferenced and m.triangulated.sum() >= 40
    R_true = seq.R_wc_true[a].T @ seq.R_wc_true[b]
    t_true = seq.R_wc_true[a].T @ (seq.t_wc_true[b] - seq.t_wc_true[a])
    R_est = m.R_wc[a].T @ m.R_wc[b]
    t_est = m.R_wc[a].T @ (m.t_wc[b] - m.t_wc[a])
    assert np.degrees(np.linalg.norm(so3_log(R_est.T @ R_true))) < 0.5
    cos = t_est @ t_true / (np.linalg.norm(t_est) * np.linalg.norm(t_true))
    assert np.degrees(np.arccos(min(cos, 1.0))) < 5.0
    # the odometry's arc length over a ~2 m chord: within a few percent of the true baseline
    assert np.linalg.norm(t_est) == pytest.approx(np.linalg.norm(t_true), rel=0.05)


@pytest.mark.parametrize("bend_m", [0.0, 8.0])
def test_a_map_that_does_not_fit_the_gps_track_is_reported(noisy, bend_m, caplog):
    """GPS fixes that swing up to ``bend_m`` sideways off the driven track (a map the fixes do
    not fit, as after a bad start): the georeferencing logs a warning once; plain GPS noise
    does not."""
    cfg, seq = noisy
    T = seq.t_wc_true
    heading = np.gradient(T[:, :2], axis=0)
    side = np.column_stack([-heading[:, 1], heading[:, 0]])
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    swing = bend_m * np.sin(np.linspace(0.0, 2.0 * np.pi, T.shape[0]))
    gps_xy = gps_for_setting(cfg, seq, "sigma=0.75") + swing[:, None] * side
    gps = GpsConstraints(seq.timestamps, gps_xy)
    start = TwoViewStart(
        InitConfig(min_distance_m=20.0), gps=gps, odometry=_odometry(seq), mapping=cfg.slam.mapping
    )
    with caplog.at_level("WARNING", logger="slam_bridge.slam.initialization"):
        res = run_slam(seq.source(), "ba", start, [gps], cfg.slam)
    assert res.georeferenced
    warned = [r for r in caplog.records if "does not fit the GPS track" in r.getMessage()]
    assert len(warned) == (1 if bend_m else 0)


def test_warn_residual_must_be_positive():
    with pytest.raises(GeosegError, match="warn_residual_m"):
        InitConfig(warn_residual_m=0.0)


@pytest.mark.parametrize("with_odometry", [True, False])
def test_georeferenced_run_without_ground_truth_beats_the_gps(noisy, with_odometry):
    """Simulated tracks, no pose given: two views, scale (odometry, or the GPS fit), then the
    similarity to the GPS fixes; the fused trajectory is closer to the truth than the fixes."""
    cfg, seq = noisy
    gps_xy = gps_for_setting(cfg, seq, "sigma=0.75")
    gps = GpsConstraints(seq.timestamps, gps_xy)
    start = TwoViewStart(
        InitConfig(min_distance_m=20.0),
        gps=gps,
        odometry=_odometry(seq) if with_odometry else None,
        mapping=cfg.slam.mapping,
    )
    res = run_slam(seq.source(), "ba", start, [gps], cfg.slam)
    assert res.georeferenced and res.tracking_failures == 0
    assert res.map.num_keyframes == seq.num_keyframes
    e = np.linalg.norm(res.t_wc[:, :2] - seq.t_wc_true[:, :2], axis=1)
    e_gps = np.linalg.norm(gps_xy - seq.t_wc_true[:, :2], axis=1)
    assert e.mean() < 0.6 * e_gps.mean()


def test_lost_tracking_restarts_a_segment(noisy):
    """Keyframe 20 sees nothing: the run reports it, re-anchors a new segment at the motion
    model's prediction, initialises it by two views and goes on with the GPS."""
    cfg, seq = noisy
    o = seq.observations
    keep = o.keyframe != 20
    source = SimulatedTracks(
        seq.K, seq.image_size, seq.timestamps, o.keyframe[keep], o.point[keep], o.uv[keep]
    )
    gps_xy = gps_for_setting(cfg, seq, "sigma=0.75")
    gps = GpsConstraints(seq.timestamps, gps_xy)
    start = TwoViewStart(
        InitConfig(min_distance_m=20.0), gps=gps, odometry=_odometry(seq), mapping=cfg.slam.mapping
    )
    res = run_slam(source, "ba", start, [gps], cfg.slam)
    states = [r.tracking for r in res.records]
    assert res.tracking_failures == 1 and states[20] == "lost"
    # keyframe 20 (no track left) cannot be a two-view reference: the next one starts it
    seg = res.map.segment
    assert seg[19] == 0 and seg[20] > 0 and np.all(seg[21:] == seg[21])
    assert res.map.num_keyframes == seq.num_keyframes
    assert res.placed.all() and res.in_world[20:].all()  # 20 dead-reckoned, then re-anchored
    e = np.linalg.norm(res.t_wc[:, :2] - seq.t_wc_true[:, :2], axis=1)
    assert e[20] < 1.0 and e[21:].mean() < 2.0


def test_a_keyframe_without_mapped_points_is_bridged_by_two_views(noisy):
    """With no mapped point in view, the tracks shared with the previous keyframe and the
    distance driven place the keyframe (close to the truth) instead of a lost tracking."""
    from slam_bridge.slam.tracking import bridge_two_view

    cfg, seq = noisy
    res = run_slam(seq.source(), "ba", _known_start(seq, cfg), [], cfg.slam, max_keyframes=20)
    m = res.map
    o = seq.observations
    sel = o.keyframe == 20
    k = m.add_keyframe(seq.timestamps[20], o.point[sel], o.uv[sel])
    m.triangulated[o.point[sel]] = False  # the map has nothing in view
    odo = _odometry(seq)
    tracked = bridge_two_view(m, k, distance=odo)
    assert tracked is not None and tracked.weak and tracked.inliers >= 15
    # the motion from keyframe 19 (as the map has it) matches the true motion
    step = tracked.t_wc - m.t_wc[19]
    true_step = seq.t_wc_true[20] - seq.t_wc_true[19]
    assert np.linalg.norm(step - true_step) < 0.1
    turn = m.R_wc[19].T @ tracked.R_wc
    true_turn = seq.R_wc_true[19].T @ seq.R_wc_true[20]
    assert np.degrees(np.linalg.norm(so3_log(turn.T @ true_turn))) < 0.5
    # no scale, or too few shared tracks: no bridge
    m2 = Map(seq.K, seq.image_size)
    m2.add_keyframe(0.0, [], np.zeros((0, 2)))
    m2.add_keyframe(1.0, [], np.zeros((0, 2)))
    assert bridge_two_view(m2, 1, distance=odo) is None


def _known_start(seq, cfg):
    from slam_bridge.slam.loop import KnownStartPoses

    return KnownStartPoses(seq.R_wc_true, seq.t_wc_true, mapping=cfg.slam.mapping)


class _TrueVerticals:
    """A vertical 'measured' in every keyframe (the truth): what the refit may lean on."""

    name, world_frame = "vertical", False

    def __init__(self, R_wc_true: np.ndarray) -> None:
        self.R_wc_true = R_wc_true

    def factors(self, slam_map, problem, k):
        slam_map.down_c[k] = self.R_wc_true[k].T @ np.array([0.0, 0.0, -1.0])
        return []


@pytest.mark.parametrize("measured", [False, True])
def test_measured_verticals_hold_the_tilt_that_a_sloping_dem_error_gives(noisy, measured):
    """A DEM whose error climbs 4 cm per metre along the drive tilts the GPS/DEM similarity fit
    by ~2 degrees; with measured verticals (``Map.down_c``) the fit keeps the true tilt."""
    from slam_bridge.factors.dem import DemSegments
    from slam_bridge.slam.fusion import DemConstraints

    cfg, seq = noisy
    rig = VehicleRig()
    T = seq.t_wc_true
    along = np.linalg.norm(T[:, :2] - T[0, :2], axis=1)
    z = T[:, 2] - rig.camera_height_m + 0.04 * along
    dem = DemSegments(T[:-1, :2], T[1:, :2], z[:-1], z[1:])
    gps = GpsConstraints(seq.timestamps, gps_for_setting(cfg, seq, "sigma=0.75"))
    start = TwoViewStart(
        InitConfig(min_distance_m=20.0), rig, gps=gps, odometry=_odometry(seq), dem=dem,
        mapping=cfg.slam.mapping,
    )  # fmt: skip
    providers = [gps, DemConstraints(dem, rig.camera_height_m)]
    if measured:
        providers.append(_TrueVerticals(seq.R_wc_true))
    res = run_slam(seq.source(), "ba", start, providers, cfg.slam)
    down = np.array([0.0, 0.0, -1.0])
    est = np.einsum("kji,j->ki", res.map.R_wc, down)
    true = np.einsum("kji,j->ki", seq.R_wc_true, down)
    tilt = np.degrees(np.arccos(np.clip(np.einsum("ki,ki->k", est, true), -1, 1)))[res.in_world]
    if measured:
        assert tilt.mean() < 0.5  # (0.36)
    else:
        assert tilt.mean() > 1.5  # the DEM error's slope, 2.3 degrees (2.17)


def test_level_similarity_takes_its_tilt_from_the_up_direction_only():
    from slam_bridge.geometry.lie import so3_exp
    from slam_bridge.slam.initialization import fit_level_similarity

    rng = np.random.default_rng(4)
    # a climbing track (3 % slope) in a map frame turned and tilted against the world
    world = np.column_stack(
        [np.linspace(0, 60, 20), 5 * np.sin(np.linspace(0, 2, 20)), 0.03 * np.linspace(0, 60, 20)]
    )
    R_true = so3_exp(np.array([0.05, -0.03, 0.8]))
    src = (world - [10.0, 2.0, 1.0]) @ R_true / 1.1  # world = 1.1 R_true src + (10, 2, 1)
    up_src = R_true.T @ np.array([0.0, 0.0, 1.0])
    dst = world + np.column_stack([rng.normal(0, 0.05, (20, 2)), np.full(20, 7.0)])  # level z
    s, R, T = fit_level_similarity(src, dst, up_src=up_src)
    np.testing.assert_allclose(R, R_true, atol=0.003)  # the slope is kept, not levelled
    assert s == pytest.approx(1.1, rel=0.003)
    moved = s * src @ R.T + T
    np.testing.assert_allclose(moved[:, :2], world[:, :2], atol=0.1)
    assert moved[:, 2].mean() == pytest.approx(dst[:, 2].mean())
    s1, _, _ = fit_level_similarity(src, dst, up_src=up_src, fix_scale=True)
    assert s1 == 1.0
    with pytest.raises(SlamError, match="zero up"):
        fit_level_similarity(src, dst, up_src=np.zeros(3))


def test_fixes_that_leave_the_trajectory_make_the_segment_georeferenced_again(noisy):
    """After the fits have stopped, the GPS jumps 8 m (a receiver re-acquiring with another
    bias): five keyframes in a row far from their fixes re-georeference the segment, which the
    run records and its status reports."""
    from slam_bridge.slam.health import assess_run

    cfg, seq = noisy
    gps_xy = gps_for_setting(cfg, seq, "sigma=0.75")
    jump = seq.timestamps >= seq.timestamps[seq.num_keyframes // 2]
    gps_xy[jump] += [8.0, 0.0]
    gps = GpsConstraints(seq.timestamps, gps_xy)
    start = TwoViewStart(
        InitConfig(min_distance_m=20.0, refit_distance_m=30.0),
        gps=gps,
        odometry=_odometry(seq),
        mapping=cfg.slam.mapping,
    )
    res = run_slam(seq.source(), "ba", start, [gps], cfg.slam)
    assert res.recoveries, "the jump was not caught"
    k, before, after = res.recoveries[0]
    assert seq.timestamps[k] >= seq.timestamps[jump][0] and after < before
    health = assess_run(res, gps=gps)
    assert any("georeferenced again" in r["detail"] for r in health.reasons)
    assert health.status in ("degraded", "failed")
    quiet = TwoViewStart(
        InitConfig(min_distance_m=20.0, refit_distance_m=30.0),
        gps=GpsConstraints(seq.timestamps, gps_for_setting(cfg, seq, "sigma=0.75")),
        odometry=_odometry(seq),
        mapping=cfg.slam.mapping,
    )
    assert not run_slam(seq.source(), "ba", quiet, [quiet.gps], cfg.slam).recoveries


def test_a_turn_is_georeferenced_on_the_fixes_own_times():
    """A 90 degree turn of radius 15 m at 10 m/s, keyframes every 0.1 s, noise-free 1 Hz fixes:
    a fix interpolated to a keyframe's time lies up to 0.8 m inside the turn, but each fix is
    paired with the map at its own time, so the true shape lands on the truth."""
    t = 0.1 * np.arange(25)
    ang = 10.0 * t / 15.0  # along the arc, radians
    world = np.column_stack([15.0 * np.sin(ang), 15.0 * (1 - np.cos(ang)), np.full(t.size, 1.5)])
    heading = so3_exp(np.array([0.0, 0.0, 0.3]))
    local = (world - world[0]) @ heading  # the map's frame: turned and shifted
    R_wc = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # camera -y = the map's up (+z)
    m = Map(np.diag([500.0, 500.0, 1.0]), (640, 480))
    for k, tk in enumerate(t):
        m.add_keyframe(float(tk), np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
        m.set_pose(k, R_wc, local[k])
    fixes = t[::10]
    gps = GpsConstraints(fixes, world[::10, :2], tolerance_s=0.02, interpolate_gap_s=1.5)
    start = TwoViewStart(
        InitConfig(min_fixes=8, min_distance_m=10.0),
        VehicleRig(camera_height_m=1.5, antenna_c=(0.0, 0.0, 0.0)),
        gps=gps,
        odometry=OdometryDistance(t, np.full(t.size, 10.0)),
    )
    assert start.georeference(m, t.size - 1)
    err = np.linalg.norm(m.t_wc[:, :2] - world[:, :2], axis=1)
    assert err.max() < 0.05  # fixes interpolated to the keyframes: 0.49 m
