"""Mapping stages: culling degenerate points, refitting points; window and fusion settings."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.errors import SlamError
from slam_bridge.experiments.fusion_ch3 import gps_for_setting, run_method
from slam_bridge.slam.fusion import FusionConfig, GpsConstraints
from slam_bridge.slam.mapping import MappingConfig, cull_degenerate_points, refine_points
from slam_bridge.slam.tracking import TrackingConfig
from slam_bridge.slam.windows import WindowConfig


def test_cull_degenerate_points():
    """Points whose rays meet at < min parallax, or behind a camera, are untriangulated;
    well-conditioned points and points seen once stay."""
    t_cams = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])  # two cameras 1 m apart, along +z
    X_w = np.array(
        [
            [0.5, 0.0, 10.0],  # parallax ~5.7 deg: kept
            [0.5, 0.0, 1e5],  # slid far along its rays: ~0 deg, culled
            [0.5, 0.0, -10.0],  # behind both cameras: culled
            [0.5, 0.0, 1e5],  # a single active view: kept
            [0.5, 0.0, 1e5],  # degenerate but not triangulated: untouched
        ]
    )
    points = np.array([0, 0, 1, 1, 2, 2, 3, 4, 4])
    cams = np.array([0, 1, 0, 1, 0, 1, 0, 0, 1])
    tri_ok = np.array([True, True, True, True, False])
    R = np.repeat(np.eye(3)[None], points.size, axis=0)
    n = cull_degenerate_points(points, R, t_cams[cams], X_w, tri_ok, 1.0)
    assert n == 2
    assert tri_ok.tolist() == [True, False, False, True, False]


def test_refine_points_only_takes_better_fits(noiseless):
    """Displaced points are re-triangulated from their observations; a point whose refit would
    not lower its worst error is left alone."""
    cfg, seq = noiseless
    res = run_method(cfg, seq, "ba", gps_for_setting(cfg, seq, "sigma=0"))
    m = res.map
    m.R_wc[:] = seq.R_wc_true
    m.t_wc[:] = seq.t_wc_true
    counts = np.bincount(m.obs_point, minlength=m.num_points)
    pts = np.flatnonzero(m.triangulated & (counts >= 3))
    assert pts.size > 20
    reference = m.X_w.copy()
    moved, kept = pts[:10], pts[10:20]
    m.X_w[moved] += np.array([0.5, -0.3, 0.4])
    before = m.X_w.copy()
    assert refine_points(m, np.r_[moved, kept]) >= moved.size
    np.testing.assert_allclose(m.X_w[moved], reference[moved], atol=5e-3)
    # noiseless points already fit to rounding: any refit is no better by more than rounding
    np.testing.assert_allclose(m.X_w[kept], before[kept], atol=1e-6)
    assert refine_points(m, moved, end_observation=0) == 0  # no observation in range


def test_gps_constraints_pick_the_fix_of_the_keyframe():
    gps = GpsConstraints(np.array([0.0, 1.0, 2.0]), np.array([[0, 0], [1, 1], [np.nan, 2]]))
    np.testing.assert_array_equal(gps.fix_at(1.0005), [1, 1])
    assert gps.fix_at(1.5) is None  # no fix near
    assert gps.fix_at(2.0) is None  # dropout
    assert gps.fix_at(-5.0) is None and gps.fix_at(9.0) is None
    wide = GpsConstraints(np.array([0.0, 1.0]), np.zeros((2, 2)), tolerance_s=0.6)
    assert wide.fix_at(0.55) is not None
    with pytest.raises(SlamError, match="increase"):
        GpsConstraints(np.array([1.0, 0.0]), np.zeros((2, 2)))
    with pytest.raises(SlamError, match="finite or NaN"):
        GpsConstraints(np.array([0.0]), np.array([[np.inf, 0.0]]))
    with pytest.raises(GeosegError, match="xy"):
        GpsConstraints(np.array([0.0]), np.zeros((2, 2)))


def test_settings_are_checked():
    with pytest.raises(SlamError):
        WindowConfig(l=8, n=6)  # fewer than 3 BA-window cameras
    with pytest.raises(SlamError, match="consistency_share"):
        WindowConfig(consistency_share=1.5)
    with pytest.raises(SlamError, match="consistency_iterations"):
        WindowConfig(consistency_iterations=0)
    with pytest.raises(GeosegError, match="consistency_px"):
        WindowConfig(consistency_px=0.0)
    with pytest.raises(GeosegError, match="dpc_info_scale"):
        WindowConfig(dpc_info_scale=0.0)
    with pytest.raises(SlamError, match="pose_graph_share"):
        WindowConfig(pose_graph_share=0.0)
    with pytest.raises(SlamError, match="min_tracked"):
        TrackingConfig(min_tracked=3)
    with pytest.raises(GeosegError, match="window_gate_px"):
        MappingConfig(window_gate_px=-1.0)
    with pytest.raises(SlamError, match="t_ratio"):
        FusionConfig(t_ratio=1.0)
    WindowConfig(consistency_share=None, mpc_length_sigma_m=None)


def test_gps_constraints_interpolate_between_close_fixes():
    t = np.array([0.0, 1.0, 2.0, 5.0])
    xy = np.array([[0.0, 0.0], [10.0, 2.0], [np.nan, np.nan], [30.0, 0.0]])
    gps = GpsConstraints(t, xy, tolerance_s=0.01, interpolate_gap_s=1.5)
    np.testing.assert_allclose(gps.fix_at(0.25), [2.5, 0.5])
    np.testing.assert_array_equal(gps.fix_at(1.0), [10.0, 2.0])
    assert gps.fix_at(1.5) is None  # the next fix is a dropout
    assert gps.fix_at(4.0) is None  # fixes 3 s apart: too far to interpolate
    assert gps.fix_at(-0.5) is None and gps.fix_at(5.5) is None  # outside the log
