"""The geometric baseline behind occluders: the facade_occluded city puts its occluders where it
says, the false associations are counted by class and distance, and the bench's flag parses."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from geoseg.classes import BUILDING, VEGETATION, VEHICLE
from geoseg.errors import ConfigError
from geoseg.synth.world import WorldConfig, build_world
from geoseg.synth.world_config import FACADE_OCCLUDED_LAYOUT, with_layout
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError
from slam_bridge.experiments import buildings_ch4 as ch4
from slam_bridge.experiments.occluded_ch4 import (
    false_associations,
    occluded_config,
    occluder_gaps,
    point_classes,
)

ROOT = Path(__file__).resolve().parents[3]


def _gaps(preset: str, layout: dict) -> dict[str, float]:
    world = build_world(
        with_layout(WorldConfig(seed=3, preset=preset, blocks_x=1, blocks_y=1), layout)
    )
    return {kind: float(np.median(g)) for kind, g in occluder_gaps(world).items() if g.size}


def test_facade_occluded_city_puts_its_occluders_close_in_front_of_the_facades():
    near = _gaps("facade_occluded", FACADE_OCCLUDED_LAYOUT)
    usual = _gaps("dense_occlusion", {})
    # the trunks ~1 m, the parked vehicles' near sides ~1.6 m in front of the facades
    assert near["tree"] < 1.2 and near["parked"] < 2.0 and near["panel"] < 1.2
    # the chapter-4 city's: 3 m sidewalks and up to 1.5 m setbacks
    assert usual["tree"] > 2.5 and usual["parked"] > 3.5
    assert min(usual[k] - near[k] for k in ("tree", "parked")) > 1.5


def test_with_layout_replaces_fields_and_refuses_unknown_ones():
    cfg = with_layout(WorldConfig(seed=1), FACADE_OCCLUDED_LAYOUT)
    assert cfg.sidewalk_width == 1.0 and cfg.buildings.setback_max == 0.0
    assert cfg.buildings.frontage_min == WorldConfig().buildings.frontage_min
    with pytest.raises(ConfigError, match="unknown WorldConfig field 'sidewalk'"):
        with_layout(WorldConfig(), {"sidewalk": 1.0})
    with pytest.raises(ConfigError, match="layout.buildings"):
        with_layout(WorldConfig(), {"buildings": {"setback": 0.0}})
    with pytest.raises(ConfigError, match="sidewalk_width"):  # still checked
        with_layout(WorldConfig(), {"sidewalk_width": -1.0})


def test_drive_world_reaches_the_city_and_leaves_other_runs_signatures_alone():
    base = ch4.BuildingsConfig(methods=["raycast"], models=["exact"])
    cfg = occluded_config(base, seed=41, length_m=120.0, methods=["raycast", "bayes"])
    world = cfg.drive.world_config()
    assert (world.preset, world.seed, world.sidewalk_width) == ("facade_occluded", 41, 1.0)
    assert cfg.models == ["exact"] and cfg.methods == ["raycast", "bayes"]
    assert '"world"' in ch4._signature(cfg, "raycast", "exact", False)
    assert '"world"' not in ch4._signature(base, "raycast", "exact", False)


def _facade() -> Facades:
    """One facade along y = 10, facing -y (towards the street)."""
    return Facades(
        p0=np.array([[0.0, 10.0]]), p1=np.array([[20.0, 10.0]]), z_min=np.zeros(1),
        z_max=np.full(1, 10.0), normal=np.array([[0.0, -1.0, 0.0]]), d=np.array([-10.0]),
        true_facade_id=np.array([0]),
    )  # fmt: skip


def test_false_associations_by_class_and_distance():
    true_points = np.array(
        [
            [5.0, 10.0, 2.0],  # building point on the facade, associated: right
            [6.0, 9.2, 4.0],  # tree crown 0.8 m in front, associated: wrong
            [7.0, 8.8, 4.0],  # tree 1.2 m in front, associated: wrong
            [8.0, 7.0, 1.0],  # vehicle 3 m in front, associated: wrong
            [9.0, 5.0, 1.0],  # vehicle 5 m in front, not associated
            [9.0, 5.0, 1.0],  # not triangulated
        ]
    )
    run = {
        "facade": np.array([0, 0, 0, 0, -1, 0]),
        "right": np.array([True, False, False, False, False, False]),
        "true_points": true_points,
        "true_class": np.array([BUILDING, VEGETATION, VEGETATION, VEHICLE, VEHICLE, VEHICLE]),
        "points": np.vstack([true_points[:5], [np.nan] * 3]),
    }
    f = false_associations(run, _facade())
    assert (f["associated"], f["false"]) == (4, 3) and f["false_share"] == pytest.approx(0.75)
    assert (f["false_vegetation"], f["false_vehicle"], f["false_building"]) == (2, 1, 0)
    assert f["false_by_distance"]["0.5-1"] == 1 and f["false_by_distance"]["1-1.5"] == 1
    assert f["false_by_distance"]["3-5"] == 1 and sum(f["false_by_distance"].values()) == 3
    assert f["occluder_points"] == 4  # the triangulated points of trees, vehicles, objects
    assert f["occluder_within_1m"] == pytest.approx(0.25)
    assert f["occluder_within_1.5m"] == pytest.approx(0.5)
    assert f["occluder_within_3m"] == pytest.approx(0.75)
    assert (f["vegetation_points"], f["vehicle_points"], f["object_points"]) == (2, 2, 0)
    assert f["vegetation_within_1m"] == pytest.approx(0.5) and f["object_within_1m"] is None
    assert f["vehicle_within_3m"] == pytest.approx(0.5)
    assert f["vegetation_distance_median_m"] == pytest.approx(1.0)
    with pytest.raises(SlamError, match="true_class"):
        false_associations({k: v for k, v in run.items() if k != "true_class"}, _facade())


def test_point_classes_are_the_majority_of_the_observed_labels(tmp_path):
    (tmp_path / "labels").mkdir()
    frame0 = np.full((4, 6), BUILDING, np.uint8)
    frame1 = frame0.copy()
    frame1[:, 3:] = VEGETATION
    for f, lab in enumerate((frame0, frame1)):
        cv2.imwrite(str(tmp_path / "labels" / f"{f:06d}.png"), lab)
    obs = np.array([(0, 0, 1, 1), (1, 0, 2, 2), (0, 1, 4, 1), (1, 1, 4, 1), (1, 1, 5, 3),
                    (0, 2, 9, 9)], dtype=np.float64)  # fmt: skip
    slam_map = SimpleNamespace(
        num_keyframes=2, num_points=4, timestamps=np.array([0.0, 0.1]),
        obs_point=obs[:, 1].astype(np.int64), obs_uv=obs[:, 2:4],
        keyframe_observations=lambda k: np.flatnonzero(obs[:, 0] == k),
    )  # fmt: skip
    classes = point_classes(tmp_path, slam_map, np.array([0.0, 0.1]))
    np.testing.assert_array_equal(classes, [BUILDING, VEGETATION, -1, -1])


def _bench():
    sys.path.insert(0, str(ROOT / "bench"))
    spec = importlib.util.spec_from_file_location("ch4_bench", ROOT / "bench" / "buildings_ch4.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_occluded_flag_parses():
    bench = _bench()
    args = bench.parse_args(["--occluded", "--drives", "41,42", "--length-m", "80"])
    assert args.occluded and args.drives == [41, 42] and args.length_m == 80.0
    assert args.out.name == "buildings_ch4_occluded"
    assert bench.parse_args([]).out.name == "buildings_ch4"
    for bad in (["--occluded", "--full"], ["--occluded", "--drives", "a,b"]):
        with pytest.raises(SystemExit):
            bench.parse_args(bad)


def test_bench_sums_the_drives_counts_and_averages_their_shares():
    drives = [
        {"false": 3, "false_by_distance": {"0-0.5": 1}, "vegetation_within_1.5m": 0.2,
         "vegetation_distance_median_m": 2.0, "object_within_1m": None, "false_share": 0.5},
        {"false": 5, "false_by_distance": {"0-0.5": 4}, "vegetation_within_1.5m": 0.4,
         "vegetation_distance_median_m": 4.0, "object_within_1m": 0.1, "false_share": 0.25},
    ]  # fmt: skip
    total = _bench()._sum_false(drives)
    assert total["false"] == 8 and total["false_by_distance"] == {"0-0.5": 5}
    assert total["vegetation_within_1.5m"] == pytest.approx(0.3)
    assert total["vegetation_distance_median_m"] == pytest.approx(3.0)
    assert total["object_within_1m"] == pytest.approx(0.1)  # the drives that have one
    assert total["false_share"] == pytest.approx(0.375)
