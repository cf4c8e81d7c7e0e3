"""A run's consistency checks: a heading failure and a scale drift are detected and reported."""

from __future__ import annotations

import types

import numpy as np

from slam_bridge.slam.fusion import GpsConstraints
from slam_bridge.slam.health import assess_run, flagged_ranges
from slam_bridge.slam.initialization import OdometryDistance


def yaw_rotation(psi):
    """Camera-to-world rotation of a level camera whose optical axis has heading ``psi``."""
    f = np.array([np.cos(psi), np.sin(psi), 0.0])  # optical axis (z)
    x = np.array([np.sin(psi), -np.cos(psi), 0.0])  # right
    return np.column_stack([x, [0.0, 0.0, -1.0], f])


def straight_run(n=60, step=1.5, yaw_error_deg=0.0, from_k=30, step_scale=1.0):
    t = 0.1 * np.arange(n)
    pos = np.column_stack([np.zeros(n), step * np.arange(n), np.full(n, 1.5)])
    truth = pos.copy()
    if step_scale != 1.0:
        steps = np.full(n - 1, step)
        steps[from_k:] *= step_scale
        pos[1:, 1] = np.cumsum(steps)
    R = np.stack([yaw_rotation(np.pi / 2) for _ in range(n)])
    R[from_k:] = yaw_rotation(np.pi / 2 + np.radians(yaw_error_deg))
    m = types.SimpleNamespace(
        timestamps=t, R_wc=R, t_wc=pos, num_keyframes=n, segment=np.zeros(n, int)
    )
    result = types.SimpleNamespace(
        map=m, records=[], in_world=np.ones(n, bool), placed=np.ones(n, bool)
    )
    gps = GpsConstraints(t, truth[:, :2], tolerance_s=0.01)
    odometry = OdometryDistance(t, np.full(n, step / 0.1))
    return result, gps, odometry


def test_a_consistent_run_is_ok():
    result, gps, odometry = straight_run()
    health = assess_run(result, gps=gps, odometry=odometry)
    assert health.status == "ok" and health.reasons == []
    assert health.figures["heading_camera_deviation_max_deg"] < 0.1


def test_a_heading_failure_is_detected_with_its_keyframes():
    result, gps, odometry = straight_run(yaw_error_deg=11.5)
    health = assess_run(result, gps=gps, odometry=odometry)
    assert health.status in ("degraded", "failed")
    (reason,) = [r for r in health.reasons if r["check"] == "heading"]
    first, last = reason["keyframes"][0]
    assert 15 <= first <= 31 and last >= 35  # the chords whose middle camera turned
    assert not [r for r in health.reasons if r["check"] == "odometry"]


def test_a_scale_drift_is_detected_against_the_odometry():
    result, gps, odometry = straight_run(step_scale=1.2)
    health = assess_run(result, gps=gps, odometry=odometry)
    (reason,) = [r for r in health.reasons if r["check"] == "odometry"]
    assert reason["keyframes"][0][0] == 31 and health.figures["odometry_flagged_share"] > 0.4
    assert health.status in ("degraded", "failed")


def test_a_map_never_georeferenced_with_a_gps_has_failed():
    result, gps, _ = straight_run()
    result.in_world = np.zeros_like(result.in_world)
    assert assess_run(result, gps=gps).status == "failed"


def test_flagged_ranges_keep_runs_of_the_minimum_length():
    flagged = np.array([0, 1, 0, 1, 1, 1, 0, 1, 1], bool)
    ids = np.arange(10, 19)
    assert flagged_ranges(ids, flagged, 2) == [[13, 15], [17, 18]]
    assert flagged_ranges(ids, flagged, 1) == [[11, 11], [13, 15], [17, 18]]
