"""GIS products of the synthetic world: error models within their bounds, exact geometry."""

from __future__ import annotations

import dataclasses
import importlib.util

import numpy as np
import pytest
import trimesh

from geoseg.errors import ConfigError, GeosegError
from geoseg.synth.buildings import (
    EXTRA,
    MISSING,
    PRESENT,
    BuildingErrorConfig,
    build_building_model,
    distance_to_polylines,
    max_vertex_displacement,
    points_in_polygon,
    triangulate_polygon,
)
from geoseg.synth.dem import DemConfig, DemModel, build_dem, resample_polyline
from geoseg.synth.georef import Georeference, lambert93_to_wgs84, wgs84_to_lambert93
from geoseg.synth.gps import GpsConfig, markov_dropouts, simulate_gps
from geoseg.synth.odometry import OdometryConfig, dead_reckon, simulate_odometry


@dataclasses.dataclass(frozen=True)
class _Building:
    id: int
    footprint: np.ndarray
    base_z: float
    height: float


@dataclasses.dataclass
class _Street:
    centerline: np.ndarray
    width: float = 8.0
    sidewalk_width: float = 3.0


def _rect(cx: float, cy: float, w: float, h: float) -> np.ndarray:
    return np.array(
        [
            [cx - w / 2, cy - h / 2],
            [cx + w / 2, cy - h / 2],
            [cx + w / 2, cy + h / 2],
            [cx - w / 2, cy + h / 2],
        ]
    )


def _town(n_side: int = 6) -> tuple[list[_Building], list[_Street]]:
    """A row of buildings on both sides of one long street along x, plus a big lot."""
    buildings = []
    for k in range(n_side):
        for side in (-1, 1):
            w = 10.0 + 2.0 * (k % 4)
            buildings.append(
                _Building(len(buildings), _rect(25.0 * k, side * 17.0, w, 12.0), 1.0, 9.0 + 3 * k)
            )
    buildings.append(_Building(len(buildings), _rect(60.0, 80.0, 60.0, 20.0), 0.0, 30.0))
    street = _Street(np.array([[-20.0, 0.0], [25.0 * n_side, 0.0]]))
    return buildings, [street]


# ---- building model ------------------------------------------------------------------------
def test_building_horizontal_error_is_hard_bounded_over_many_seeds() -> None:
    buildings, streets = _town()
    by_id = {b.id: b for b in buildings}
    config = BuildingErrorConfig(max_horizontal_error_m=2.5, horizontal_error_std_m=3.0)
    worst = []
    for seed in range(60):
        model = build_building_model(buildings, config, seed=seed, streets=streets)
        for b in model.buildings:
            if b.status == PRESENT:
                worst.append(max_vertex_displacement(by_id[b.true_id].footprint, b.footprint))
    worst = np.array(worst)
    assert worst.max() <= 2.5 + 1e-9
    assert worst.max() > 2.3  # the bound is reached, not just respected
    assert np.mean(worst > 0.1) > 0.9  # nearly every building is displaced


def test_building_model_has_missing_and_extra_buildings_off_the_streets() -> None:
    buildings, streets = _town()
    config = BuildingErrorConfig(missing_share=0.15, extra_count=2)
    model = build_building_model(buildings, config, seed=3, streets=streets)
    status = model.status
    assert sum(v == MISSING for v in status.values()) == round(0.15 * len(buildings))
    assert len(model.extra_ids) == 2 and all(status[i] == EXTRA for i in model.extra_ids)
    assert min(model.extra_ids) > max(b.id for b in buildings)
    assert set(model.true_to_model) == set(range(len(buildings))) - set(model.missing_ids)
    for b in model.buildings:
        if b.status != EXTRA:
            continue
        # off the street (half width + sidewalk) and not overlapping a true building
        assert distance_to_polylines(b.footprint, [streets[0].centerline]).min() >= 7.0
        for t in buildings:
            assert not points_in_polygon(b.footprint, t.footprint).any()
            assert not points_in_polygon(t.footprint, b.footprint).any()


def test_building_heights_are_unreliable_but_bounded() -> None:
    buildings, streets = _town()
    config = BuildingErrorConfig(height_error="scale", height_scale_range=(0.6, 1.5))
    model = build_building_model(buildings, config, seed=1, streets=streets)
    ratios = np.array([b.height / b.true_height for b in model.buildings if b.status == PRESENT])
    assert np.all((ratios >= 0.6 - 1e-9) & (ratios <= 1.5 + 1e-9))
    assert np.mean(np.abs(ratios - 1.0) > 0.02) > 0.8
    storeys = build_building_model(
        buildings, dataclasses.replace(config, height_error="storeys"), seed=1, streets=streets
    )
    heights = np.array([b.height for b in storeys.buildings])
    np.testing.assert_allclose(heights / 3.0, np.round(heights / 3.0))


def test_facade_planes_are_exact_and_outward() -> None:
    buildings, streets = _town()
    model = build_building_model(buildings, seed=2, streets=streets)
    planes = model.planes
    assert len(planes) == sum(len(b.footprint) for b in model.buildings)
    np.testing.assert_allclose(np.linalg.norm(planes.normal, axis=1), 1.0)
    np.testing.assert_allclose(np.einsum("ij,ij->i", planes.normal[:, :2], planes.p0), planes.d)
    np.testing.assert_allclose(np.einsum("ij,ij->i", planes.normal[:, :2], planes.p1), planes.d)
    for b in model.buildings:
        centroid = np.append(b.footprint.mean(axis=0), b.base_z + 1.0)[None]
        rows = planes.building_id == b.id
        assert np.all(planes.signed_distance(centroid)[0, rows] < 0)  # inside all its planes
        assert np.all(planes.z_max[rows] - planes.z_min[rows] == pytest.approx(b.height))
    # facade k of a present building models edge k of the true footprint
    offsets = np.cumsum([0] + [len(b.footprint) for b in buildings])[:-1]
    present = planes.true_facade_id >= 0
    bid = planes.building_id[present]
    assert np.array_equal(planes.true_facade_id[present], offsets[bid] + planes.edge_index[present])
    assert np.all(planes.true_facade_id[np.isin(planes.building_id, model.extra_ids)] == -1)


def test_building_model_is_deterministic() -> None:
    buildings, streets = _town()
    a = build_building_model(buildings, seed=5, streets=streets)
    b = build_building_model(buildings, seed=5, streets=streets)
    c = build_building_model(buildings, seed=6, streets=streets)
    assert np.array_equal(a.planes.p0, b.planes.p0) and a.status == b.status
    assert len(a.planes) != len(c.planes) or not np.allclose(a.planes.p0, c.planes.p0)


def test_building_model_files(tmp_path) -> None:
    buildings, streets = _town()
    model = build_building_model(buildings, seed=0, streets=streets)
    paths = model.write(tmp_path)
    mesh = trimesh.load(paths["mesh"], process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    table = np.loadtxt(paths["facades_csv"], delimiter=",", skiprows=1)
    assert table.shape == (len(model.planes), 14)
    np.testing.assert_allclose(table[:, 12], model.planes.d, atol=1e-3)
    assert paths["buildings_json"].read_text().count('"status"') >= 1


def test_triangulate_non_convex_polygon() -> None:
    l_shape = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 3], [0, 3]], dtype=float)
    tris = triangulate_polygon(l_shape)
    assert tris.shape == (4, 3)
    p = l_shape[tris]
    u, w = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * (u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0])
    assert np.all(area > 0) and area.sum() == pytest.approx(6.0)


def test_building_bad_inputs() -> None:
    with pytest.raises(GeosegError, match="footprint"):
        build_building_model([_Building(0, np.zeros((3, 3)), 0.0, 5.0)])
    with pytest.raises(ConfigError, match="missing_share"):
        BuildingErrorConfig(missing_share=1.5)


# ---- DEM -----------------------------------------------------------------------------------
def test_dem_altitude_at_is_exact_on_a_hand_made_segment() -> None:
    dem = DemModel(
        p0=np.array([[0.0, 0.0], [10.0, 0.0]]),
        p1=np.array([[10.0, 0.0], [10.0, 10.0]]),
        z0=np.array([100.0, 110.0]),
        z1=np.array([110.0, 90.0]),
        street_id=np.array([0, 0]),
        true_z0=np.zeros(2),
        true_z1=np.zeros(2),
    )
    xy = np.array([[0.0, 0.0], [2.5, 1.0], [5.0, -3.0], [10.0, 0.0], [12.0, 7.5], [-4.0, 0.0]])
    np.testing.assert_allclose(dem.altitude_at(xy), [100.0, 102.5, 105.0, 110.0, 95.0, 100.0])
    with pytest.raises(GeosegError, match="xy"):
        dem.altitude_at(np.zeros((3, 3)))


def test_dem_error_is_bounded_smooth_and_consistent_at_junctions() -> None:
    lines = [
        np.array([[0.0, 0.0], [400.0, 0.0]]),
        np.array([[400.0, 0.0], [400.0, 300.0]]),
        np.column_stack([np.linspace(0, 400, 50), 150 + 20 * np.sin(np.linspace(0, np.pi, 50))]),
    ]

    def terrain(xy):
        return 30.0 + 0.03 * xy[:, 0] - 0.02 * xy[:, 1]

    config = DemConfig(max_error_m=2.0, error_std_m=1.5, segment_length_m=5.0)
    errors, neighbour_diffs = [], []
    for seed in range(40):
        dem = build_dem(lines, terrain, config, seed=seed)
        np.testing.assert_allclose(dem.true_z0, terrain(dem.p0))
        errors.append(np.concatenate([dem.error0, dem.error1]))
        neighbour_diffs.append(np.abs(dem.error1 - dem.error0))  # 5 m apart
    errors = np.concatenate(errors)
    assert np.abs(errors).max() <= 2.0 + 1e-12
    assert np.abs(errors).max() > 1.9 and errors.std() > 0.5
    assert np.median(np.concatenate(neighbour_diffs)) < 0.25 * errors.std()
    # junction (400, 0): end of street 0 and start of street 1 agree
    dem = build_dem(lines, terrain, config, seed=0)
    end0 = dem.z1[dem.street_id == 0][-1]
    start1 = dem.z0[dem.street_id == 1][0]
    assert end0 == pytest.approx(start1)


def test_dem_files(tmp_path) -> None:
    dem = build_dem([np.array([[0.0, 0.0], [50.0, 0.0]])], lambda xy: 0.1 * xy[:, 0], seed=1)
    paths = dem.write(tmp_path)
    table = np.loadtxt(paths["dem_csv"], delimiter=",", skiprows=1)
    assert table.shape == (len(dem), 10)
    import json

    geo = json.loads(paths["dem_geojson"].read_text())
    assert geo["type"] == "FeatureCollection" and len(geo["features"]) == len(dem)
    lon, lat, z = geo["features"][0]["geometry"]["coordinates"][0]
    assert abs(lat - Georeference().origin_lat_deg) < 1e-3 and z == pytest.approx(
        dem.z0[0], abs=1e-3
    )


def test_resample_polyline_keeps_ends_and_corners() -> None:
    line = np.array([[0.0, 0.0], [23.0, 0.0], [23.0, 7.0]])
    pts = resample_polyline(line, 5.0)
    assert np.allclose(pts[0], line[0]) and np.allclose(pts[-1], line[-1])
    assert np.any(np.all(np.isclose(pts, line[1]), axis=1))
    assert np.linalg.norm(np.diff(pts, axis=0), axis=1).max() <= 5.0 + 1e-9


# ---- GPS -----------------------------------------------------------------------------------
def _drive(duration_s: float, fps: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, duration_s, 1.0 / fps)
    xyz = np.column_stack([8.0 * t, 30.0 * np.sin(t / 40.0), 35.0 + 0.01 * t])
    return t, xyz


def test_gps_bias_bounded_locally_constant_noise_and_dropouts() -> None:
    t, xyz = _drive(20000.0, fps=2.0)
    config = GpsConfig(
        bias_max_m=3.0, bias_std_m=2.5, bias_hold_s=30.0, bias_ramp_s=4.0,
        noise_std_m=0.3, dropout_share=0.08, dropout_burst_s=3.0,
    )  # fmt: skip
    log = simulate_gps(t, xyz, config, seed=0)
    assert len(log) == 20000 and np.allclose(np.diff(log.timestamps), 1.0)
    mag = np.linalg.norm(log.bias, axis=1)
    assert mag.max() <= 3.0 + 1e-12 and mag.max() > 2.9
    step = np.linalg.norm(np.diff(log.bias, axis=0), axis=1)
    assert np.mean(step < 1e-12) > 1.0 - 4.0 / 30.0 - 0.05  # constant outside the ramps
    assert step.max() <= 2 * 3.0 / 4.0 + 1e-9  # ramps are gradual
    v = log.valid
    residual = log.xy[v] - log.true_xyz[v, :2] - log.bias[v]
    assert residual.std(axis=0) == pytest.approx([0.3, 0.3], rel=0.05)
    assert (~v).mean() == pytest.approx(0.08, abs=0.01)
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], (~v).astype(int), [0]]))))[::2]
    assert runs.mean() == pytest.approx(3.0, rel=0.15)
    assert np.isnan(log.xy[~v]).all() and np.isnan(log.lat_deg[~v]).all()
    # (lat, lon, height) converts back to the fix exactly
    np.testing.assert_allclose(
        log.georef.wgs84_to_world(log.lat_deg[v], log.lon_deg[v], log.height_m[v]),
        np.column_stack([log.xy[v], log.z[v]]),
        atol=1e-3,
    )


def test_gps_is_deterministic_and_samples_at_1hz(tmp_path) -> None:
    t, xyz = _drive(12.5)
    a = simulate_gps(t, xyz, seed=4)
    b = simulate_gps(t, xyz, seed=4)
    c = simulate_gps(t, xyz, seed=5)
    assert len(a) == 13 and np.array_equal(a.xy, b.xy, equal_nan=True)
    assert not np.allclose(a.bias, c.bias)
    np.testing.assert_allclose(a.true_xyz[:, 0], 8.0 * a.timestamps)
    table = np.loadtxt(a.write_csv(tmp_path / "gps.csv"), delimiter=",", skiprows=1)
    assert table.shape == (13, 13)


def test_markov_dropouts_share() -> None:
    rng = np.random.default_rng(0)
    assert markov_dropouts(50000, 0.2, 5.0, rng).mean() == pytest.approx(0.2, abs=0.015)
    assert not markov_dropouts(100, 0.0, 5.0, rng).any()


def test_gps_bad_inputs() -> None:
    t, xyz = _drive(5.0)
    with pytest.raises(GeosegError, match="positions"):
        simulate_gps(t, xyz[:, :2])
    with pytest.raises(GeosegError, match="increasing"):
        simulate_gps(t[::-1], xyz)
    with pytest.raises(ConfigError, match="dropout_share"):
        GpsConfig(dropout_share=1.0)


# ---- georeference --------------------------------------------------------------------------
def test_wgs84_round_trip_below_a_millimetre() -> None:
    georef = Georeference()
    rng = np.random.default_rng(0)
    xyz = rng.uniform([-3000, -3000, -50], [3000, 3000, 200], size=(500, 3))
    lat, lon, alt = georef.world_to_wgs84(xyz)
    back = georef.wgs84_to_world(lat, lon, alt)
    assert np.abs(back - xyz).max() < 1e-3
    lat0, lon0, alt0 = georef.world_to_wgs84(np.zeros((1, 2)))
    assert (lat0[0], lon0[0], alt0[0]) == pytest.approx((48.7904, 2.4556, 40.0), abs=1e-9)
    # 1 km north is ~1/111.2 degree of latitude at 48.8 N
    lat1, lon1, _ = georef.world_to_wgs84(np.array([[0.0, 1000.0]]))
    assert (lat1[0] - 48.7904) * 111_200 == pytest.approx(1000.0, rel=2e-3)
    assert lon1[0] == pytest.approx(2.4556, abs=1e-9)


def test_lambert93_needs_pyproj_or_round_trips() -> None:
    lat, lon = np.array([48.7904]), np.array([2.4556])
    if importlib.util.find_spec("pyproj") is None:
        with pytest.raises(GeosegError, match=r"pip install geoseg\[geo\]"):
            wgs84_to_lambert93(lat, lon)
        return
    en = wgs84_to_lambert93(lat, lon)
    assert 600_000 < en[0, 0] < 700_000 and 6_800_000 < en[0, 1] < 6_900_000
    lat2, lon2 = lambert93_to_wgs84(en)
    assert lat2[0] == pytest.approx(lat[0], abs=1e-9) and lon2[0] == pytest.approx(lon[0], abs=1e-9)


# ---- odometry ------------------------------------------------------------------------------
def test_dead_reckoning_recovers_straight_and_circular_paths() -> None:
    t = np.linspace(0.0, 20.0, 201)
    heading = np.full_like(t, np.radians(30.0))
    track = dead_reckon(t, np.full_like(t, 5.0), heading, np.array([1.0, 2.0]))
    expected = np.array([1.0, 2.0]) + 5.0 * t[:, None] * [np.cos(heading[0]), np.sin(heading[0])]
    np.testing.assert_allclose(track, expected, atol=1e-9)
    # circle of radius 40 m at 8 m/s, sampled coarsely (0.5 s), heading wrapping past pi
    radius, v = 40.0, 8.0
    t = np.arange(0.0, 60.0, 0.5)
    phase = v / radius * t
    heading = np.angle(np.exp(1j * (phase + np.pi / 2)))
    truth = np.column_stack([radius * np.cos(phase), radius * np.sin(phase)])
    track = dead_reckon(t, np.full_like(t, v), heading, truth[0])
    np.testing.assert_allclose(track, truth, atol=1e-9)


def test_odometry_noise_and_scale_within_bounds() -> None:
    t = np.arange(0.0, 2000.0, 0.1)
    speed = 8.0 + np.sin(t / 10.0)
    heading = t / 100.0
    config = OdometryConfig(speed_noise_std_mps=0.05, scale_error_max=0.02)
    for seed in range(10):
        log = simulate_odometry(t, speed, heading, config, seed=seed)
        assert abs(log.scale) <= 0.02
        residual = log.speed - (1.0 + log.scale) * speed
        assert residual.std() == pytest.approx(0.05, rel=0.05)
    exact = simulate_odometry(t[:50], speed[:50], heading[:50], OdometryConfig(0.0, 0.0, 0.0))
    np.testing.assert_array_equal(exact.speed, speed[:50])
    np.testing.assert_array_equal(exact.heading, heading[:50])


def test_odometry_bad_inputs(tmp_path) -> None:
    t = np.arange(5.0)
    with pytest.raises(GeosegError, match="speed"):
        simulate_odometry(t, np.ones(4), np.zeros(5))
    log = simulate_odometry(t, np.ones(5), np.zeros(5), seed=0)
    table = np.loadtxt(log.write_csv(tmp_path / "odo.csv"), delimiter=",", skiprows=1)
    assert table.shape == (5, 5)


# ---- on the world --------------------------------------------------------------------------
def test_gis_products_on_a_tiny_world() -> None:
    import geoseg.synth.world as world_mod

    world = world_mod.build_world(world_mod.WorldConfig(blocks_x=1, blocks_y=1, seed=3))
    model = build_building_model(world.buildings, seed=3, streets=world.streets)
    facades = world.facades()
    planes = model.planes
    present = planes.true_facade_id >= 0
    row = planes.true_facade_id[present]
    assert np.array_equal(facades.building_id[row], planes.building_id[present])
    shift = np.linalg.norm(planes.p0[present] - facades.p0[row], axis=1)
    assert shift.max() <= model.config.max_horizontal_error_m + 1e-9
    np.testing.assert_allclose(planes.normal[present], facades.normal[row], atol=0.06)
    dem = build_dem([s.centerline for s in world.streets], world.terrain_height, seed=3)
    xy = np.concatenate([s.centerline for s in world.streets])
    err = dem.altitude_at(xy) - world.terrain_height(xy)
    assert np.abs(err).max() <= 2.0 + 0.2  # + linear interpolation of a smooth terrain


def test_dead_reckoning_follows_a_real_drive() -> None:
    import geoseg.synth.trajectory as traj_mod
    import geoseg.synth.world as world_mod

    world = world_mod.build_world(world_mod.WorldConfig(blocks_x=2, blocks_y=1, seed=1))
    traj = traj_mod.drive(world, rig="car", length_m=150.0, fps=10.0, seed=1)
    xy = traj.vehicle_xyz[:, :2]
    track = dead_reckon(traj.timestamps, traj.speed, traj.vehicle_heading, xy[0])
    travelled = np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()
    assert np.linalg.norm(track - xy, axis=1).max() < 0.01 * travelled


# ---- CSV round trips -----------------------------------------------------------------------
def test_gis_csv_round_trips(tmp_path) -> None:
    buildings, streets = _town()
    planes = build_building_model(buildings, seed=0, streets=streets).planes
    back = type(planes).read_csv(planes.write_csv(tmp_path / "facades.csv"))
    np.testing.assert_allclose(back.p0, planes.p0, atol=1e-4)
    np.testing.assert_allclose(back.d, planes.d, atol=1e-4)
    assert np.array_equal(back.true_facade_id, planes.true_facade_id)

    dem = build_dem([np.array([[0.0, 0.0], [60.0, 5.0]])], lambda xy: 0.1 * xy[:, 0], seed=2)
    dem_back = DemModel.read_csv(dem.write_csv(tmp_path / "dem.csv"))
    xy = np.array([[10.0, 3.0], [33.0, -2.0]])
    np.testing.assert_allclose(dem_back.altitude_at(xy), dem.altitude_at(xy), atol=1e-3)

    t, xyz = _drive(40.0)
    gps = simulate_gps(t, xyz, GpsConfig(dropout_share=0.3), seed=1)
    from geoseg.synth.gps import GpsLog

    gps_back = GpsLog.read_csv(gps.write_csv(tmp_path / "gps.csv"))
    assert np.array_equal(gps_back.valid, gps.valid)
    np.testing.assert_allclose(gps_back.xy, gps.xy, atol=1e-4)  # nan where invalid
    np.testing.assert_allclose(gps_back.lat_deg, gps.lat_deg, atol=1e-9)

    odo = simulate_odometry(t, np.full_like(t, 5.0), np.zeros_like(t), seed=0)
    from geoseg.synth.odometry import OdometryLog

    odo_back = OdometryLog.read_csv(odo.write_csv(tmp_path / "odo.csv"))
    np.testing.assert_allclose(odo_back.speed, odo.speed, atol=1e-5)
    with pytest.raises(GeosegError, match="columns"):
        OdometryLog.read_csv(tmp_path / "gps.csv")
