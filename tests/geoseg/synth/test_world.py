"""The procedural city: determinism, layout invariants, terrain, configs and bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geoseg.classes import ROAD, SIDEWALK, TERRAIN
from geoseg.config import load_config
from geoseg.errors import ConfigError, GeosegError
from geoseg.synth.world import WorldConfig, build_world

CONFIGS = Path(__file__).resolve().parents[3] / "configs"


def _fingerprint(world) -> list[bytes]:
    out = [
        b.footprint.tobytes() + np.float64([b.base_z, b.height]).tobytes() for b in world.buildings
    ]
    out += [s.centerline.tobytes() for s in world.streets]
    out += [p.vertices.tobytes() + p.faces.tobytes() + p.instance.tobytes() for p in world.parts]
    return out


def test_same_seed_same_city_other_seed_other_city(make_tiny_config, tiny_world):
    again = build_world(make_tiny_config())
    assert _fingerprint(again) == _fingerprint(tiny_world)
    other = build_world(make_tiny_config(seed=4))
    assert _fingerprint(other) != _fingerprint(tiny_world)
    assert not np.allclose(other.road_graph.nodes, tiny_world.road_graph.nodes)


def test_street_network_has_loops_curves_and_no_dead_ends(tiny_world):
    graph = tiny_world.road_graph
    n_nodes, n_edges = len(graph.nodes), len(graph.edges)
    assert n_edges >= n_nodes  # connected graph with E >= V holds a cycle
    assert np.bincount(graph.edges.ravel(), minlength=n_nodes).min() >= 2
    curved = [s.curved for s in tiny_world.streets]
    assert any(curved) and not all(curved)
    for i, street in enumerate(tiny_world.streets):
        a, b = graph.edges[i]
        np.testing.assert_allclose(street.centerline[0], graph.nodes[a])
        np.testing.assert_allclose(street.centerline[-1], graph.nodes[b])


def test_buildings_are_ccw_on_the_terrain_and_off_the_streets(tiny_world):
    assert len(tiny_world.buildings) >= 20
    for b in tiny_world.buildings:
        x, y = b.footprint[:, 0], b.footprint[:, 1]
        area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
        assert area > 0
        assert b.height > 3.0
        np.testing.assert_allclose(b.base_z, tiny_world.terrain_height(b.footprint).min())
        inner = b.footprint.mean(0) + 0.9 * (b.footprint - b.footprint.mean(0))
        assert (tiny_world.ground_class(inner) == TERRAIN).all()
    assert {b.material for b in tiny_world.buildings} >= {"brick", "plaster"}


def test_facade_table_rows_match_the_footprints(tiny_world):
    table = tiny_world.facades()
    n = sum(len(b.footprint) for b in tiny_world.buildings)
    assert len(table) == n
    np.testing.assert_array_equal(table.facade_id, np.arange(n))
    np.testing.assert_allclose(np.linalg.norm(table.normal, axis=1), 1.0)
    np.testing.assert_allclose(table.normal[:, 2], 0.0)
    edge = table.p1 - table.p0
    np.testing.assert_allclose((edge * table.normal[:, :2]).sum(1), 0.0, atol=1e-9)
    for row in range(n):
        b = tiny_world.buildings[table.building_id[row]]
        mid = 0.5 * (table.p0[row] + table.p1[row])
        outside = np.append(mid + 0.2 * table.normal[row, :2], b.base_z + 1.0)
        inside = np.append(mid - 0.2 * table.normal[row, :2], b.base_z + 1.0)
        assert tiny_world.building_at(outside[None])[0] != b.id
        assert tiny_world.building_at(inside[None])[0] == b.id
        assert table.z_min[row] == b.base_z and table.z_max[row] == b.base_z + b.height


def test_terrain_has_real_but_gentle_slopes(tiny_world):
    rng = np.random.default_rng(0)
    xy = rng.uniform(tiny_world.bounds[0], tiny_world.bounds[1], (2000, 2))
    z = tiny_world.terrain_height(xy)
    grade = np.linalg.norm(tiny_world.terrain.gradient(xy), axis=1)
    assert z.max() - z.min() > 0.5
    assert 0.005 < grade.mean() and grade.max() <= tiny_world.config.terrain.max_grade + 1e-9
    eps = 1e-4
    dx = (tiny_world.terrain_height(xy + [eps, 0]) - tiny_world.terrain_height(xy - [eps, 0])) / (
        2 * eps
    )
    np.testing.assert_allclose(dx, tiny_world.terrain.gradient(xy)[:, 0], atol=1e-6)


def test_ground_classes_follow_the_street_cross_section(tiny_world):
    street = tiny_world.streets[0]
    (p,), (t,) = street.point_at(np.array([street.length / 2]))
    left = np.array([-t[1], t[0]])
    half = street.width / 2
    offsets = np.array([0.0, half - 0.2, half + 0.2, half + street.sidewalk_width - 0.2])
    classes = tiny_world.ground_class(p + offsets[:, None] * left)
    assert classes.tolist() == [ROAD, ROAD, SIDEWALK, SIDEWALK]


def test_presets_change_the_occluders_not_the_city(make_tiny_config, tiny_world):
    light = build_world(make_tiny_config(preset="light"))
    assert (
        _fingerprint(light)[: len(light.buildings)]
        == _fingerprint(tiny_world)[: len(tiny_world.buildings)]
    )
    assert len(light.trees) < len(tiny_world.trees) / 2
    assert len(light.vehicles) < len(tiny_world.vehicles)


def test_moving_vehicles_move(tiny_world):
    moving = [i for i, v in enumerate(tiny_world.vehicles) if v.moving]
    assert moving
    xy0, _ = tiny_world.vehicle_poses(0.0)
    xy1, _ = tiny_world.vehicle_poses(1.0)
    step = np.linalg.norm(xy1 - xy0, axis=1)
    assert (step[moving] > 1.0).any()
    parked = [i for i, v in enumerate(tiny_world.vehicles) if not v.moving]
    np.testing.assert_array_equal(step[parked], 0.0)


@pytest.mark.parametrize("name", ["world_default", "world_light", "world_dense_occlusion"])
def test_yaml_configs_load(name):
    cfg = load_config(WorldConfig, CONFIGS / f"{name}.yaml")
    assert cfg.preset in ("light", "dense_occlusion")
    extent = cfg.blocks_x * cfg.block_size, cfg.blocks_y * cfg.block_size
    assert max(extent) <= 1000.0


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        ({"block_size": -5.0}, "block_size"),
        ({"blocks_x": 0}, "blocks_x"),
        ({"street_width": 0.0}, "street_width"),
        ({"terrain": {"mesh_spacing": 0.0}}, "terrain.mesh_spacing"),
        ({"buildings": {"depth_max": 1.0}}, "buildings.depth_max"),
        ({"occluders": {"tree_spacing": -1.0}}, "occluders.tree_spacing"),
        ({"parking_width": 5.0}, "parking_width"),
        ({"preset": "jungle"}, "preset"),
        ({"block_siz": 50.0}, "block_siz"),
        ({"blocks_x": "four"}, "blocks_x"),
    ],
)
def test_bad_configs_name_the_key(overrides, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(WorldConfig, overrides)


def test_build_world_rejects_other_objects():
    with pytest.raises(GeosegError, match="config"):
        build_world({"seed": 1})


def test_terrain_height_checks_its_input(tiny_world):
    with pytest.raises(GeosegError, match="xy"):
        tiny_world.terrain_height(np.zeros((4, 3)))
    with pytest.raises(GeosegError, match="xy"):
        tiny_world.terrain_height(np.array([[np.nan, 0.0]]))
