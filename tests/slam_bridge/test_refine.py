"""The run's map file and the global constrained bundle adjustment (``geoseg slam refine``)
on a small synthetic street whose truth is known."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.bridge.association import Association
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError
from slam_bridge.factors.dem import DemSegments
from slam_bridge.slam.fusion import GpsConstraints
from slam_bridge.slam.initialization import VehicleRig
from slam_bridge.slam.map import Map
from slam_bridge.system.base_fixes import BaseConstraints, adjust_on_fixes
from slam_bridge.system.map_file import MAP_FILE, SavedMap, load_map, save_map, saved_map
from slam_bridge.system.reference import Trajectory, compare_trajectories
from slam_bridge.system.refine import RefineConfig, refine_map
from slam_bridge.testing.scenes import perturb, street_scene


@pytest.fixture(scope="module")
def scene():
    """12 cameras 1 m apart, 1 px noise; facades at y = +-6 m, ground at z = 0."""
    return street_scene(12, points_per_camera=25, noise_px=1.0, seed=3)


def scene_map(scene, R, t, X) -> Map:
    """A run's map of the scene at the poses and points given (every point triangulated)."""
    m = Map(scene.K, (scene.width, scene.height))
    for c in range(scene.R_wc.shape[0]):
        sel = scene.obs_cameras == c
        k = m.add_keyframe(0.1 * c, scene.obs_points[sel], scene.uv[sel])
        m.set_pose(k, R[c], t[c])
    m.X_w[:] = X
    m.triangulated[:] = True
    m.down_c[:] = np.einsum("cba,b->ca", scene.R_wc, [0.0, 0.0, -1.0])  # measured verticals
    return m


def run_of(m: Map, rig: VehicleRig | None = None):
    """``(result, inputs)`` of a run whose map is ``m`` (every keyframe in the world frame)."""
    C = m.num_keyframes
    result = SimpleNamespace(
        map=m, in_world=np.ones(C, bool),
        records=[SimpleNamespace(keyframe=k, tracking="tracked") for k in range(C)],
    )  # fmt: skip
    inputs = SimpleNamespace(
        frames=SimpleNamespace(timestamps=np.arange(2 * C) * 0.05), rig=rig or VehicleRig(),
        georef=None, dem=None, odometry=None,
    )  # fmt: skip
    return result, inputs


def saved_of(m: Map, tmp_path, association=None, gps=None) -> SavedMap:
    """``m`` through the map file (as ``geoseg slam run`` writes it)."""
    result, inputs = run_of(m)
    bridge = None
    if association is not None:
        bridge = SimpleNamespace(constraints=SimpleNamespace(association=association))
    return load_map(save_map(tmp_path / MAP_FILE, result, inputs, bridge, gps))


def street_facades() -> Facades:
    """The scene's two facades, facing the street."""
    return Facades(
        p0=np.array([[-20.0, 6.0], [80.0, -6.0]]), p1=np.array([[80.0, 6.0], [-20.0, -6.0]]),
        z_min=np.array([-1.0, -1.0]), z_max=np.array([30.0, 30.0]),
        normal=np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]]), d=np.array([-6.0, -6.0]),
        true_facade_id=np.array([-1, -1]),
    )  # fmt: skip


def test_the_map_file_round_trips(scene, tmp_path):
    m = scene_map(scene, scene.R_wc, scene.t_wc, scene.X_w)
    m.obs_active[::7] = False
    facade = np.where(np.abs(scene.X_w[:, 1]) > 5.9, 0, -1)
    a = Association(facade, (facade >= 0) * 0.7, "bayes")
    s = saved_of(m, tmp_path, a)
    for name in ("R_wc", "t_wc", "X_w", "obs_keyframe", "obs_point", "obs_uv", "obs_active"):
        np.testing.assert_array_equal(getattr(s, name), getattr(m, name), err_msg=name)
    np.testing.assert_array_equal(s.K, scene.K)
    assert s.image_size == (scene.width, scene.height)
    assert s.association == "bayes" and s.facade_weight.max() == 0.7
    np.testing.assert_array_equal(s.facade, facade)
    np.testing.assert_array_equal(s.frame, np.arange(m.num_keyframes) * 2)
    assert list(s.tracking) == ["tracked"] * m.num_keyframes and s.georef is None
    assert saved_of(m, tmp_path).facade is None  # a run without buildings has no association


def test_the_map_in_memory_is_the_map_file_read_back(scene, tmp_path):
    m = scene_map(scene, scene.R_wc, scene.t_wc, scene.X_w)
    result, inputs = run_of(m)
    memory = saved_map(result, inputs)
    filed = load_map(save_map(tmp_path / MAP_FILE, result, inputs))
    for name in SavedMap.__dataclass_fields__:
        a, b = getattr(memory, name), getattr(filed, name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a == b, name
    memory.t_wc[0] += 1.0  # a copy: adjusting it leaves the run's map alone
    assert m.t_wc[0, 0] == scene.t_wc[0, 0]
    assert filed.base_xy is None  # a run without an image base
    base = base_fixes_of(scene, m)
    with_base = load_map(save_map(tmp_path / MAP_FILE, result, inputs, base=base))
    np.testing.assert_array_equal(with_base.base_xy, base.xy)
    np.testing.assert_array_equal(with_base.base_weight, base.weights)
    np.testing.assert_array_equal(with_base.base_timestamps, base.timestamps)


def test_the_runs_gps_bias_estimate_is_kept_and_removed_from_the_fixes(scene, tmp_path):
    """A run that estimated its GPS's bias saves it; refine corrects the fixes by it."""
    m = scene_map(scene, scene.R_wc, scene.t_wc, scene.X_w)
    bias_m = np.array([2.0, -1.0])
    t = m.timestamps.copy()
    gps = GpsConstraints(t, scene.t_wc[:, :2] + bias_m)  # every fix off by the bias
    # the estimate made at the start (memory_s 0: known from then on), and its covariance
    history = [(0, 0.0, bias_m, np.eye(2) * 0.01, 4, 0.9)]
    gps.bias = SimpleNamespace(
        history=history, config=SimpleNamespace(memory_s=0.0),
        at=lambda ts: np.where((np.asarray(ts) >= 0.0)[..., None], bias_m, 0.0),
    )  # fmt: skip
    s = saved_of(m, tmp_path, gps=gps)
    np.testing.assert_array_equal(s.gps_bias_timestamps, t)
    np.testing.assert_allclose(s.gps_bias_xy, np.tile(bias_m, (12, 1)))
    np.testing.assert_allclose(s.gps_bias_var, 0.01)
    facades = street_facades()
    raw = GpsConstraints(t, gps.xy)
    r = refine_map(s, facades=facades, gps=raw)
    assert r.figures["gps_bias_removed"]
    kept = refine_map(s, RefineConfig(gps_bias=False), facades=facades, gps=raw)
    assert not kept.figures["gps_bias_removed"]
    # measured: 0.016 m with the bias removed, 2.23 m without (the fixes' bias is 2.24 m)
    assert truth_errors(scene, r.map)["translation_error_m"] < 0.1
    assert truth_errors(scene, kept.map)["translation_error_m"] > 2.0


def test_bad_map_files_are_refused_with_what_was_expected(scene, tmp_path):
    with pytest.raises(SlamError, match="no map.npz in this folder"):
        load_map(tmp_path)
    with pytest.raises(SlamError, match="no such map file"):
        load_map(tmp_path / "nothing.npz")
    (tmp_path / "bad.npz").write_text("not an archive")
    with pytest.raises(SlamError, match="not a map file"):
        load_map(tmp_path / "bad.npz")
    np.savez(tmp_path / "other.npz", K=np.eye(3))
    with pytest.raises(SlamError, match="missing"):
        load_map(tmp_path / "other.npz")
    path = save_map(
        tmp_path / MAP_FILE,
        SimpleNamespace(
            map=scene_map(scene, scene.R_wc, scene.t_wc, scene.X_w),
            in_world=np.ones(12, bool), records=[],
        ),
        SimpleNamespace(frames=SimpleNamespace(timestamps=np.arange(12) * 0.1),
                        rig=VehicleRig(), georef=None),
    )  # fmt: skip
    with np.load(path) as z:
        data = dict(z)
    np.savez(tmp_path / "v9.npz", **{**data, "format_version": np.int64(9)})
    with pytest.raises(SlamError, match="version 9"):
        load_map(tmp_path / "v9.npz")
    np.savez(tmp_path / "short.npz", **{**data, "t_wc": data["t_wc"][:3]})
    with pytest.raises(SlamError, match=r"t_wc: expected shape \(12, 3\)"):
        load_map(tmp_path / "short.npz")
    np.savez(tmp_path / "half.npz", **{**data, "base_xy": np.zeros((3, 2))})
    with pytest.raises(SlamError, match="base_timestamps, base_xy, base_weight: all or none"):
        load_map(tmp_path / "half.npz")


def truth_errors(scene, s: SavedMap) -> dict:
    est = Trajectory(s.timestamps, s.R_wc, s.t_wc)
    return compare_trajectories(est, Trajectory(s.timestamps, scene.R_wc, scene.t_wc))


@pytest.mark.parametrize("association", ["nearest", "saved"])
def test_refine_pulls_perturbed_poses_back_to_the_truth(scene, tmp_path, association):
    """Poses 0.3 m and 1 deg off, points 0.2 m off: GPS fixes at the true positions, a flat DEM,
    the facades and the verticals pull the whole street back."""
    R, t, X = perturb(
        scene.R_wc, scene.t_wc, scene.X_w, rot_sigma=0.02, trans_sigma=0.3, point_sigma=0.2
    )
    facade = np.where(scene.X_w[:, 1] > 5.9, 0, np.where(scene.X_w[:, 1] < -5.9, 1, -1))
    saved = saved_of(scene_map(scene, R, t, X), tmp_path, Association(facade, facade >= 0.0, "x"))
    before = truth_errors(scene, saved)
    assert before["translation_error_3d_m"] > 0.3
    gps = GpsConstraints(saved.timestamps, scene.t_wc[:, :2])
    flat = DemSegments([[-20.0, 0.0]], [[80.0, 0.0]], [0.0], [0.0])
    cfg = RefineConfig(association=association)
    r = refine_map(saved, cfg, facades=street_facades(), dem=flat, gps=gps)
    after = truth_errors(scene, r.map)
    # measured (both associations): 0.016 m horizontal, 0.019 m 3D, 0.07 deg, from 0.31 m,
    # 0.38 m and 1.6 deg
    assert after["translation_error_m"] < 0.05 and after["translation_error_3d_m"] < 0.05
    assert after["rotation_error_deg"] < 0.2
    f = r.figures
    assert f["gps_rows"] == f["dem_rows"] == f["vertical_rows"] == f["keyframes"] == 12
    assert f["association"] == association and f["building_rows"] > 50
    assert f["reprojection_rms_px"] < 1.5 < f["reprojection_rms_px_before"]
    assert r.refined.all()


def test_refine_refuses_what_it_cannot_solve(scene, tmp_path):
    saved = saved_of(scene_map(scene, scene.R_wc, scene.t_wc, scene.X_w), tmp_path)
    flat = DemSegments([[-20.0, 0.0]], [[80.0, 0.0]], [0.0], [0.0])
    with pytest.raises(SlamError, match="nothing holds the map horizontally"):
        refine_map(saved, dem=flat)
    with pytest.raises(SlamError, match="no building association"):
        refine_map(saved, RefineConfig(association="saved"), facades=street_facades())
    saved.in_world[1:] = False
    with pytest.raises(SlamError, match="1 keyframe"):
        refine_map(saved, facades=street_facades())
    with pytest.raises(SlamError, match="method"):
        RefineConfig(method="global")
    with pytest.raises(SlamError, match="min_views"):
        RefineConfig(min_views=1)


def base_fixes_of(scene, m: Map, outlier_m: float = 0.0) -> BaseConstraints:
    """Fixes of the true camera positions at every keyframe's time (weight 100: 0.1 m), the
    sixth ``outlier_m`` off across the street (a fix on a repeated facade)."""
    xy = scene.t_wc[:, :2].copy()
    xy[5, 1] += outlier_m
    return BaseConstraints(m.timestamps.copy(), xy, np.full(xy.shape[0], 100.0), tolerance_s=0.02)


def test_base_fixes_hold_the_camera_and_huber_cuts_a_wrong_one(scene, tmp_path):
    """The base's fixes are the camera's own position (a GPS antenna 1 m aside does not move
    them), and a fix 3 m off costs linearly beyond 3 sigmas instead of bending the street."""
    R, t, X = perturb(
        scene.R_wc, scene.t_wc, scene.X_w, rot_sigma=0.02, trans_sigma=0.3, point_sigma=0.2
    )
    m = scene_map(scene, R, t, X)
    result, inputs = run_of(m, VehicleRig(antenna_c=(1.0, 0.0, 0.0)))
    saved = saved_map(result, inputs)
    assert np.abs(saved.antenna_c).max() == 1.0
    flat = DemSegments([[-20.0, 0.0]], [[80.0, 0.0]], [0.0], [0.0])
    good = refine_map(saved, dem=flat, base=base_fixes_of(scene, m))
    assert good.figures["base_rows"] == 12 and "gps_rows" not in good.figures
    # measured: 0.014 m, from 0.31
    assert truth_errors(scene, good.map)["translation_error_m"] < 0.05
    wrong = base_fixes_of(scene, m, outlier_m=3.0)
    robust = refine_map(saved, dem=flat, base=wrong)
    plain = refine_map(saved, RefineConfig(base_huber=None), dem=flat, base=wrong)

    def error_at_the_wrong_fix(r):
        return np.linalg.norm(r.map.t_wc[5, :2] - scene.t_wc[5, :2])

    # measured: 0.026 m with Huber, 0.27 m without
    assert error_at_the_wrong_fix(robust) < 0.5 * error_at_the_wrong_fix(plain)
    with pytest.raises(GeosegError, match="base_huber"):
        RefineConfig(base_huber=0.0)


def test_a_run_is_adjusted_on_its_base_fixes_and_keeps_its_online_poses(scene):
    R, t, X = perturb(
        scene.R_wc, scene.t_wc, scene.X_w, rot_sigma=0.02, trans_sigma=0.3, point_sigma=0.2
    )
    m = scene_map(scene, R, t, X)
    for k in range(m.num_keyframes):
        m.mark_online(k)
    result, inputs = run_of(m)
    figures = adjust_on_fixes(result, inputs, base_fixes_of(scene, m))
    assert figures["base_rows"] == 12 and figures["keyframe_shift_m_mean"] > 0.1
    error = np.linalg.norm(m.t_wc[:, :2] - scene.t_wc[:, :2], axis=1)
    assert error.mean() < 0.05  # measured 0.014, from 0.31
    np.testing.assert_array_equal(m.t_wc_online, t)
    np.testing.assert_array_equal(result.loop_t_wc, t)
    # fixes at no keyframe's time: nothing holds the map, and the run stays as it was
    far = BaseConstraints(m.timestamps + 100.0, scene.t_wc[:, :2], np.ones(12), tolerance_s=0.02)
    before = m.t_wc.copy()
    failed = adjust_on_fixes(result, inputs, far)
    assert "nothing holds the map" in failed["error"]
    np.testing.assert_array_equal(m.t_wc, before)


def test_slam_refine_uses_the_fixes_a_base_run_saved(scene, tmp_path):
    """``geoseg slam refine`` of a run from an image base needs no GPS: the fixes the run
    saved in its map hold it."""
    import json

    from slam_bridge.system.refine import refine_run

    R, t, X = perturb(
        scene.R_wc, scene.t_wc, scene.X_w, rot_sigma=0.02, trans_sigma=0.3, point_sigma=0.2
    )
    m = scene_map(scene, R, t, X)
    result, inputs = run_of(m)
    run = tmp_path / "run"
    run.mkdir()
    save_map(run / MAP_FILE, result, inputs, base=base_fixes_of(scene, m))
    refine_run(run, tmp_path / "refined")
    summary = json.loads((tmp_path / "refined" / "summary.json").read_text())
    assert summary["base_rows"] == 12 and summary["keyframe_shift_m_mean"] > 0.1
    save_map(run / MAP_FILE, result, inputs)  # the same run without its fixes
    with pytest.raises(SlamError, match="nothing holds the map"):
        refine_run(run, tmp_path / "again")
