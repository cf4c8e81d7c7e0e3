"""Camera rigs and driving: heights, optical axes, speeds, timestamps, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from geoseg.synth.trajectory import _lane_path, drive, pinhole_K


def _motion(traj) -> np.ndarray:
    v = np.gradient(traj.vehicle_xyz, axis=0)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def car(tiny_world):
    return drive(tiny_world, rig="car", length_m=250.0, fps=10.0, seed=1)


@pytest.fixture(scope="module")
def tram(tiny_world):
    return drive(tiny_world, rig="tram", length_m=150.0, fps=5.0, seed=2, image_size=(160, 120))


def test_shapes_and_timestamps(car):
    n = len(car)
    assert n > 20
    assert car.R_wc.shape == (n, 3, 3) and car.t_wc.shape == (n, 3)
    assert car.vehicle_xyz.shape == (n, 3) and car.speed.shape == (n,)
    assert car.timestamps[0] == 0.0
    np.testing.assert_allclose(np.diff(car.timestamps), 0.1)
    assert car.image_size == (320, 240) and car.rig == "car"
    distance = np.linalg.norm(np.diff(car.vehicle_xyz, axis=0), axis=1).sum()
    assert 0.9 * 250 < distance < 250 + 15


def test_rotations_are_orthonormal(car, tram):
    for traj in (car, tram):
        gram = np.einsum("tji,tjk->tik", traj.R_wc, traj.R_wc)
        np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(traj.R_wc), 1.0, atol=1e-12)


def test_car_camera_looks_along_the_motion_at_about_1_5_m(tiny_world, car):
    height = car.t_wc[:, 2] - tiny_world.terrain_height(car.t_wc[:, :2])
    np.testing.assert_allclose(height, 1.5, atol=0.05)
    along = (_motion(car) * car.R_wc[:, :, 2]).sum(1)
    assert along.min() > 0.99
    # image y axis points down (world -z) within the terrain slope
    assert (car.R_wc[:, 2, 1] < -0.99).all()


def test_tram_camera_looks_sideways_at_about_2_m(tiny_world, tram):
    height = tram.t_wc[:, 2] - tiny_world.terrain_height(tram.t_wc[:, :2])
    np.testing.assert_allclose(height, 2.0, atol=0.05)
    heading = np.stack([np.cos(tram.vehicle_heading), np.sin(tram.vehicle_heading)], 1)
    np.testing.assert_allclose((heading * tram.R_wc[:, :2, 2]).sum(1), 0.0, atol=1e-9)
    across = (_motion(tram) * tram.R_wc[:, :, 2]).sum(1)
    assert np.abs(across).max() < 0.05  # finite differences at 5 fps, through junctions
    # looking to the right of the motion: axis = motion x up
    right = np.cross(_motion(tram), [0.0, 0.0, 1.0])
    assert ((right * tram.R_wc[:, :, 2]).sum(1) > 0.95).all()


def test_speeds_are_realistic_and_heading_is_smooth(car, tram):
    assert car.speed.max() <= 11.0 + 1e-9 and car.speed.min() >= 0.25 * 11.0 - 1e-9
    # 70 m blocks: many junctions, yet the car reaches its cruise speed between them
    assert np.median(car.speed) > 6.5 and car.speed.max() > 10.9
    assert tram.speed.max() <= 7.0 + 1e-9 and np.median(tram.speed) > 4.5
    step = np.abs(np.angle(np.exp(1j * np.diff(car.vehicle_heading))))
    assert step.max() < np.radians(8.0)  # < 8 degrees per 0.1 s even in junctions
    heading = np.stack([np.cos(car.vehicle_heading), np.sin(car.vehicle_heading)], 1)
    assert ((heading * _motion(car)[:, :2]).sum(1) > 0.99).all()


@pytest.mark.parametrize("turn", ["right", "left"])
def test_lane_turns_without_a_cusp(turn):
    """An L-shaped route in 4 m steps (as the streets are): the lane path turns smoothly on both
    sides of the centreline, a right turn's tighter than a left's, and stays in the lane's side."""
    sign = -1.0 if turn == "right" else 1.0
    leg = np.arange(0.0, 60.0 + 1e-9, 4.0)
    path = np.concatenate(
        [np.stack([leg - 60.0, 0 * leg], 1), np.stack([0 * leg[1:], sign * leg[1:]], 1)]
    )
    xy, heading, arc = _lane_path(path, 1.9)
    step = np.abs(np.angle(np.exp(1j * np.diff(heading))))
    assert step.max() < np.radians(15.0)  # per 0.5 m: a radius of at least ~2 m, no cusp
    assert np.all(np.diff(arc) > 0.2)  # moves on at every step, never back
    total = np.angle(np.exp(1j * (heading[-1] - heading[0])))
    np.testing.assert_allclose(total, sign * np.pi / 2, atol=np.radians(2.0))
    # right of the motion all along: the leg in x at y = -1.9, the other at x = sign * 1.9
    np.testing.assert_allclose(xy[10, 1], -1.9, atol=1e-6)
    np.testing.assert_allclose(xy[-10, 0], sign * 1.9, atol=1e-6)


def test_vehicle_stays_on_the_road_surface(tiny_world, car):
    np.testing.assert_allclose(
        car.vehicle_xyz[:, 2], tiny_world.terrain_height(car.vehicle_xyz[:, :2]), atol=1e-9
    )
    d = tiny_world.street_index.query(car.vehicle_xyz[:, :2])[0]
    assert d.max() < tiny_world.config.street_width / 2


def test_route_is_deterministic_per_seed(tiny_world, car):
    again = drive(tiny_world, rig="car", length_m=250.0, fps=10.0, seed=1)
    np.testing.assert_array_equal(again.t_wc, car.t_wc)
    other = drive(tiny_world, rig="car", length_m=250.0, fps=10.0, seed=7)
    assert other.t_wc.shape != car.t_wc.shape or not np.allclose(other.t_wc, car.t_wc)


def test_pinhole_K():
    K = pinhole_K(640, 480, 90.0)
    np.testing.assert_allclose(K, [[320.0, 0, 319.5], [0, 320.0, 239.5], [0, 0, 1]])
    with pytest.raises(GeosegError, match="hfov_deg"):
        pinhole_K(640, 480, 180.0)
    with pytest.raises(GeosegError, match="image_size"):
        pinhole_K(0, 480)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"rig": "bike"}, "rig"),
        ({"length_m": -1.0}, "length_m"),
        ({"speed_mps": 0.0}, "speed_mps"),
        ({"fps": 0}, "fps"),
        ({"image_size": (320,)}, "image_size"),
        ({"side": "up"}, "side"),
    ],
)
def test_bad_arguments(tiny_world, kwargs, name):
    with pytest.raises(GeosegError, match=name):
        drive(tiny_world, **kwargs)
