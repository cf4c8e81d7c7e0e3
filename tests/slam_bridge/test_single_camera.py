"""The shared base of the one-camera position factors (GPS, odometry, DEM)."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.ba.factor import Factor
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.factors.dem import DEMFactor, DemSegments
from slam_bridge.factors.gps import GPSFactor, GPSFixError
from slam_bridge.factors.odometry import OdometryFactor
from slam_bridge.factors.single_camera import SingleCameraFactor, check_weights
from slam_bridge.geometry.lie import so3_exp


def _state(C: int = 4) -> BAState:
    rng = np.random.default_rng(3)
    R = so3_exp(rng.normal(scale=0.2, size=(C, 3)))
    t = np.cumsum(rng.normal(size=(C, 3)) + [1.0, 0.0, 0.0], axis=0)
    return BAState(R, t, rng.normal(size=(2, 3)))


def _factors(kernel: str | None = None) -> list[SingleCameraFactor]:
    dem = DemSegments([[-10.0, -10.0]], [[10.0, 10.0]], [0.0], [2.0])
    return [
        GPSFactor([0, 2, 3], np.ones((3, 2)), [1.0, 2.0, 0.5], kernel=kernel),
        OdometryFactor([1, 3], np.zeros((2, 3)), [0.5, 3.0], kernel=kernel),
        DEMFactor([0, 1, 2], dem, 1.5, [1.0, 1.0, 2.0], kernel=kernel),
    ]


@pytest.mark.parametrize("kernel", [None, "huber"])
def test_cost_matches_the_block_cost(kernel) -> None:
    state = _state()
    for f in _factors(kernel):
        assert isinstance(f, Factor)
        blk = f.evaluate(state)
        assert blk.cameras.shape == (blk.num_rows, 1)
        np.testing.assert_array_equal(blk.cameras[:, 0], f.cameras)
        assert f.cost(state) == pytest.approx(blk.cost(), rel=1e-12)


def test_camera_index_out_of_range() -> None:
    state = _state(C=2)
    for f in _factors():
        with pytest.raises(SlamError, match="camera index out of range for 2"):
            f.cost(state)
        with pytest.raises(SlamError, match="camera index out of range for 2"):
            f.evaluate(state)


def test_weight_messages_name_the_family() -> None:
    dem = DemSegments([[0.0, 0.0]], [[1.0, 0.0]], [0.0], [0.0])
    with pytest.raises(GPSFixError, match="non-negative GPS weights"):
        GPSFactor([0], [[0.0, 0.0]], [-1.0])
    with pytest.raises(GeosegError, match="non-negative odometry weights"):
        OdometryFactor([0], [[0.0, 0.0]], [np.nan])
    with pytest.raises(GeosegError, match="non-negative DEM weights"):
        DEMFactor([0], dem, 1.0, [np.inf])
    with pytest.raises(GeosegError, match="weights"):
        check_weights([1.0, 2.0], 3, "x")
    np.testing.assert_array_equal(check_weights(None, 2, "x"), [1.0, 1.0])
