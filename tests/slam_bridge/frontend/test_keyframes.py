"""The keyframe rule on its own."""

from __future__ import annotations

import math

import pytest

from slam_bridge.errors import SlamError
from slam_bridge.frontend.keyframes import KeyframeConfig, KeyframeRule


def test_spacing_with_a_distance_callable():
    rule = KeyframeRule(
        KeyframeConfig(spacing_m=2.0), 640, distance=lambda t0, t1: 11.0 * (t1 - t0)
    )
    assert rule.decide(1, 0.0, 0.1, 1.0, 100.0) is None  # 1.1 m: no, whatever the flow
    assert rule.decide(2, 0.0, 0.2, 1.0, 0.0) == "spacing"  # 2.2 m
    assert rule.decide(1, 0.0, 0.1, 0.5, 0.0) == "tracks"  # too few tracks left
    nan_rule = KeyframeRule(KeyframeConfig(), 640, distance=lambda t0, t1: math.nan)
    assert nan_rule.decide(1, 0.0, 0.1, 1.0, 30.0) == "parallax"  # no odometry: image rule


def test_parallax_scales_with_the_image_width():
    rule = KeyframeRule(KeyframeConfig(parallax_px=24.0, reference_width=640), 320)
    assert rule.parallax_px == pytest.approx(12.0)
    assert rule.decide(1, 0.0, 0.1, 0.9, 11.9) is None
    assert rule.decide(1, 0.0, 0.1, 0.9, 12.0) == "parallax"
    assert rule.decide(1, 0.0, 0.1, 0.9, math.nan) is None


def test_gap_and_never_the_same_frame():
    rule = KeyframeRule(KeyframeConfig(max_frame_gap=5), 640)
    assert rule.decide(4, 0.0, 0.4, 1.0, 0.0) is None
    assert rule.decide(5, 0.0, 0.5, 1.0, 0.0) == "gap"
    assert rule.decide(0, 0.0, 0.0, 0.0, 100.0) is None
    assert KeyframeRule(KeyframeConfig(max_frame_gap=None), 640).decide(99, 0, 9.9, 1, 0) is None


def test_scarce_tracks_make_a_keyframe_before_the_spacing():
    rule = KeyframeRule(
        KeyframeConfig(spacing_m=2.0, min_tracked=50), 640, distance=lambda t0, t1: 11 * (t1 - t0)
    )
    assert rule.decide(1, 0.0, 0.1, 0.9, 5.0, tracked=45, lost=5) == "scarce"
    assert rule.decide(1, 0.0, 0.1, 0.9, 5.0, tracked=50, lost=5) is None  # enough left
    assert rule.decide(1, 0.0, 0.1, 1.0, 0.0, tracked=20, lost=0) is None  # stopped: none lost
    assert rule.decide(1, 0.0, 0.1, 0.9, 5.0) is None  # no count given: rule not checked
    assert rule.decide(1, 0.0, 0.1, 0.9, 5.0, tracked=80, lost=5, turned=True) == "turn"
    off = KeyframeRule(KeyframeConfig(min_tracked=0), 640, distance=lambda t0, t1: 0.0)
    assert off.decide(1, 0.0, 0.1, 0.9, 5.0, tracked=3, lost=30) is None


@pytest.mark.parametrize(
    "kw",
    [
        {"spacing_m": 0},
        {"parallax_px": -1},
        {"min_tracked_share": 1.5},
        {"max_frame_gap": 0},
        {"min_tracked": -1},
        {"min_tracked": 2.5},
    ],
)
def test_bad_config(kw):
    with pytest.raises(SlamError, match="KeyframeConfig"):
        KeyframeConfig(**kw)
