"""Metrics, tables and plots of the chapter-3 experiment on hand-made trajectories."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slam_bridge.errors import SlamError
from slam_bridge.evaluation import metrics as ev
from slam_bridge.evaluation import tables_ch3
from slam_bridge.geometry.lie import so3_exp


def test_rotation_and_translation_errors():
    rng = np.random.default_rng(0)
    R_gt = so3_exp(rng.normal(size=(5, 3)))
    angles = np.array([0.0, 0.01, 0.1, 0.5, 3.0])
    axes = rng.normal(size=(5, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R_est = R_gt @ so3_exp(axes * angles[:, None])
    np.testing.assert_allclose(ev.rotation_errors(R_est, R_gt), angles, atol=1e-9)
    t_gt = rng.normal(size=(5, 3))
    t_est = t_gt + np.array([[3.0, 4.0, 0.0]] * 5)
    np.testing.assert_allclose(ev.translation_errors(t_est, t_gt), 5.0)


def test_error_stats_and_nan_guard():
    s = ev.error_stats(np.array([1.0, 2.0, 3.0, 10.0]))
    assert s["mean"] == pytest.approx(4.0)
    assert s["median"] == pytest.approx(2.5)
    assert s["std"] == pytest.approx(np.std([1, 2, 3, 10]))
    with pytest.raises(SlamError, match="non-finite"):
        ev.error_stats(np.array([1.0, np.nan]))
    with pytest.raises(SlamError):
        ev.error_stats(np.zeros(0))


def test_align_similarity_recovers_transform():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3)) * 10
    R = so3_exp(np.array([0.1, -0.2, 0.3]))
    dst = 2.5 * src @ R.T + np.array([1.0, 2.0, 3.0])
    s, R_hat, t_hat = ev.align_similarity(src, dst)
    assert s == pytest.approx(2.5)
    np.testing.assert_allclose(R_hat, R, atol=1e-9)
    np.testing.assert_allclose(t_hat, [1.0, 2.0, 3.0], atol=1e-9)


def _two_view_scene():
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    t = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    X = np.array([[0.5, 0.2, 10.0], [1.0, -0.3, 8.0], [1.5, 0.1, 12.0]])
    kf = np.repeat(np.arange(3), 3)
    pt = np.tile(np.arange(3), 3)
    uv = np.empty((9, 2))
    for m in range(9):
        x = K @ (R[kf[m]].T @ (X[pt[m]] - t[kf[m]]))
        uv[m] = x[:2] / x[2]
    return K, R, t, X, kf, pt, uv


def test_count_inliers_all_errors_below_threshold():
    K, R, t, X, kf, pt, uv = _two_view_scene()
    assert ev.count_inliers(K, R, t, X, kf, pt, uv) == 3
    bad = uv.copy()
    bad[4] += [3.0, 0.0]  # point 1 in camera 1 off by 3 px
    assert ev.count_inliers(K, R, t, X, kf, pt, bad) == 2
    used = np.ones(9, bool)
    used[4] = False  # the bad observation was rejected: point 1 counts again
    assert ev.count_inliers(K, R, t, X, kf, pt, bad, used=used) == 3
    # a stale stored point fails; re-triangulation from the poses recovers it
    stale = X.copy()
    stale[2] += [0.3, 0.0, 0.0]
    assert ev.count_inliers(K, R, t, stale, kf, pt, uv) == 2
    assert ev.count_inliers(K, R, t, stale, kf, pt, uv, retriangulate=True) == 3
    # a point never triangulated is not counted
    tri = np.array([True, True, False])
    assert ev.count_inliers(K, R, t, X, kf, pt, uv, triangulated=tri) == 2


def test_inlier_loss():
    assert ev.inlier_loss(990, 1000) == pytest.approx(0.01)
    assert ev.inlier_loss(1010, 1000) == 0.0
    with pytest.raises(SlamError):
        ev.inlier_loss(1, 0)


def test_inlier_churn_counts_the_flips_both_ways():
    ref = np.array([True, True, True, False, False, True])
    met = np.array([True, False, False, True, False, True])
    assert ev.inlier_churn(ref, met) == (2, 1)
    assert ev.inlier_churn(ref, None) is None
    with pytest.raises(SlamError, match="not the same points"):
        ev.inlier_churn(ref, met[:4])


def _run(method, setting, t_mean, inliers, sec, its, mem):
    stats = {"mean": t_mean, "std": 0.1, "median": t_mean, "max": 2 * t_mean}
    return tables_ch3.RunSummary(
        method=method,
        setting=setting,
        rotation={"mean": 0.01, "std": 0.0, "median": 0.01, "max": 0.02},
        translation=stats,
        horizontal=stats,
        vertical=stats,
        inliers=inliers,
        inliers_raw=inliers,
        inliers_truth=inliers,
        points=2000,
        rejected_observations=10,
        fusion_iterations=its,
        fusion_seconds=sec,
        seconds_per_iteration=sec / its,
        fusion_seconds_full=sec,
        fusion_iterations_full=its,
        hessian_bytes_mean=mem,
        hessian_bytes_full_mean=mem,
        ba_seconds=1.0,
        seconds=10.0,
        keyframes=100,
        gps_fused=99,
    )


def test_summary_tables_and_files(tmp_path):
    settings = ["sigma=0.75", "bias"]
    runs = []
    for s in settings:
        runs.append(_run("ba", s, 0.5, 1000, 10.0, 100, 3e6))
        runs.append(_run("dpc", s, 0.4, 990, 4.0, 100, 1e6))
        runs.append(_run("mpc", s, 0.6, 995, 6.0, 100, 1e6))
    # the bias runs carry their inlier masks: n = 0 1000 inliers, MPC loses 30 and gains 25
    mask = np.zeros(1100, bool)
    mask[:1000] = True
    mpc_mask = mask.copy()
    mpc_mask[:30], mpc_mask[1000:1025] = False, True
    runs[3].inlier_points, runs[5].inlier_points = mask, mpc_mask
    summ = tables_ch3.build_summary(runs, ["ba", "dpc", "mpc"], settings)
    assert (summ["mpc_bias_inliers_lost"], summ["mpc_bias_inliers_gained"]) == (30, 25)
    assert summ["mpc_bias_inlier_loss_noise"] == pytest.approx(np.sqrt(55) / 1000)
    assert "mpc_sigma0.75_inliers_lost" not in summ  # no masks: no churn
    assert all("inlier_points" not in r for r in summ["runs"])
    assert summ["dpc_time_ratio"] == pytest.approx(0.4)
    assert summ["mpc_time_ratio"] == pytest.approx(0.6)
    assert summ["memory_ratio"] == pytest.approx(3.0)
    assert summ["inlier_loss_max"] == pytest.approx(0.01)
    assert summ["dpc_sigma0.75_t_mean"] == pytest.approx(0.4)
    md = tables_ch3.markdown_tables(summ)
    assert "Table 3.1" in md and "0.63" in md  # the thesis's DPC mu_T at sigma_b = 0.75
    assert "| 30 / 25 | 0.74 |" in md  # the churn and its chance sd (%)
    tables_ch3.write_markdown(summ, tmp_path / "t.md")
    tables_ch3.write_json(summ, tmp_path / "t.json")
    assert json.loads((tmp_path / "t.json").read_text())["memory_ratio"] == pytest.approx(3.0)
    t = np.cumsum(np.ones((10, 3)), axis=0)
    p = tables_ch3.plot_trajectories(tmp_path / "traj.png", t, {"ba": t + 0.1}, t[:, :2] + 0.2)
    q = tables_ch3.plot_memory(
        tmp_path / "mem.png", {"ba": np.arange(10) * 1e4, "dpc": np.ones(10)}
    )
    assert p.stat().st_size > 1000 and q.stat().st_size > 1000
