"""A low-cost GPS log (thesis §1.9.3, eq. 1.84): ``x_gps = x_true + V_gps + eps``.

* 1 Hz fixes (``rate_hz``), horizontal position in the world frame and in WGS84 through a
  :class:`~geoseg.synth.georef.Georeference`;
* ``V_gps``, a **locally constant bias**: piecewise constant over holds of random duration
  (``bias_hold_s`` on average, between half and one and a half times it), with a linear ramp of
  ``bias_ramp_s`` from one value to the next; each value ~ N(0, bias_std_m² I) with its
  magnitude hard-clipped to ``bias_max_m`` (so the bias never exceeds it, ramps included);
* ``eps``, small white Gaussian noise of ``noise_std_m`` per axis;
* dropouts: missing fixes in bursts (a two-state Markov chain whose stationary share of missing
  fixes is ``dropout_share`` and mean burst length ``dropout_burst_s``); a missing fix has
  ``valid = False`` and NaN coordinates;
* the altitude is unreliable (the thesis ignores it): true altitude + a large slowly varying
  error; kept only because a GPS outputs one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geoseg.errors import ConfigError, GeosegError, check_finite, check_shape
from geoseg.synth.georef import Georeference
from geoseg.synth.tables import read_table, write_table

logger = logging.getLogger(__name__)


@dataclass
class GpsConfig:
    """GPS error model (eq. 1.84).

    Attributes:
        rate_hz: fix rate.
        bias_max_m: hard bound on the horizontal bias magnitude.
        bias_std_m: per-axis standard deviation of each bias value (before clipping).
        bias_hold_s: mean duration over which the bias stays constant.
        bias_ramp_s: duration of the linear transition between two bias values.
        noise_std_m: per-axis standard deviation of the white horizontal noise.
        dropout_share: long-run share of missing fixes.
        dropout_burst_s: mean duration of a run of missing fixes.
        altitude_error_std_m: standard deviation of the (unreliable) altitude error.
    """

    rate_hz: float = 1.0
    bias_max_m: float = 3.0
    bias_std_m: float = 1.5
    bias_hold_s: float = 30.0
    bias_ramp_s: float = 5.0
    noise_std_m: float = 0.3
    dropout_share: float = 0.05
    dropout_burst_s: float = 3.0
    altitude_error_std_m: float = 5.0

    def __post_init__(self) -> None:
        for name in ("rate_hz", "bias_hold_s", "dropout_burst_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: expected > 0, got {getattr(self, name)}")
        for name in ("bias_max_m", "bias_std_m", "bias_ramp_s", "noise_std_m"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if self.altitude_error_std_m < 0:
            raise ConfigError(
                f"altitude_error_std_m: expected >= 0, got {self.altitude_error_std_m}"
            )
        if not 0.0 <= self.dropout_share < 1.0:
            raise ConfigError(
                f"dropout_share: expected a share in [0, 1), got {self.dropout_share}"
            )


@dataclass(frozen=True)
class GpsLog:
    """G GPS fixes.

    Attributes:
        timestamps: `(G,)` seconds, on the trajectory's clock.
        valid: `(G,)` bool, False for a dropout.
        xy: `(G, 2)` measured horizontal position, world metres (NaN where invalid).
        z: `(G,)` measured altitude in the world frame (unreliable; NaN where invalid).
        lat_deg: `(G,)` WGS84 latitude of the measured fix (NaN where invalid).
        lon_deg: `(G,)` WGS84 longitude (NaN where invalid).
        height_m: `(G,)` WGS84 ellipsoidal height of the fix (NaN where invalid); ``(lat, lon,
            height)`` converts back to exactly ``(x, y, z)``.
        true_xyz: `(G, 3)` true position (ground truth, not given to the SLAM).
        bias: `(G, 2)` the bias ``V_gps`` of each fix (ground truth).
        config: the error model used.
        georef: the georeference of the WGS84 columns.
    """

    timestamps: np.ndarray
    valid: np.ndarray
    xy: np.ndarray
    z: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    height_m: np.ndarray
    true_xyz: np.ndarray
    bias: np.ndarray
    config: GpsConfig = field(default_factory=GpsConfig)
    georef: Georeference = field(default_factory=Georeference)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    CSV_HEADER = "timestamp,valid,x,y,z,lat_deg,lon_deg,height_m,true_x,true_y,true_z,bias_x,bias_y"

    def write_csv(self, path: str | Path) -> Path:
        """Write the log as CSV (columns :attr:`CSV_HEADER`; ``true_*`` and ``bias_*`` are
        ground truth; invalid fixes have ``valid = 0`` and ``nan`` measurements)."""
        path = Path(path)
        table = np.column_stack(
            [
                self.timestamps,
                self.valid.astype(np.int64),
                self.xy,
                self.z,
                self.lat_deg,
                self.lon_deg,
                self.height_m,
                self.true_xyz,
                self.bias,
            ]
        )
        fmt = ["%.6f", "%d", "%.4f", "%.4f", "%.4f", "%.10f", "%.10f", "%.4f"] + ["%.4f"] * 5
        return write_table(path, table, fmt, self.CSV_HEADER)

    @classmethod
    def read_csv(cls, path: str | Path, georef: Georeference | None = None) -> GpsLog:
        """Read a log written by :meth:`write_csv` (``config`` is left at its defaults)."""
        t = read_table(path, cls.CSV_HEADER)
        return cls(
            timestamps=t[:, 0],
            valid=t[:, 1] > 0.5,
            xy=t[:, 2:4],
            z=t[:, 4],
            lat_deg=t[:, 5],
            lon_deg=t[:, 6],
            height_m=t[:, 7],
            true_xyz=t[:, 8:11],
            bias=t[:, 11:13],
            georef=georef or Georeference(),
        )


def simulate_gps(
    timestamps: np.ndarray,
    positions: np.ndarray,
    config: GpsConfig | None = None,
    *,
    seed: int = 0,
    georef: Georeference | None = None,
) -> GpsLog:
    """Sample a GPS log along a trajectory.

    Args:
        timestamps: `(T,)` increasing trajectory times, seconds.
        positions: `(T, 3)` true antenna (vehicle) positions, world metres.
        config: error model (defaults when None).
        seed: random seed; the same seed gives the same log.
        georef: georeference for the WGS84 columns (default :class:`Georeference`).

    Returns:
        Fixes at ``timestamps[0] + k / rate_hz`` up to ``timestamps[-1]``.
    """
    config = config or GpsConfig()
    georef = georef or Georeference()
    timestamps = np.asarray(timestamps, dtype=np.float64)
    positions = np.asarray(positions, dtype=np.float64)
    check_shape("timestamps", timestamps, (None,))
    check_shape("positions", positions, (timestamps.shape[0], 3))
    check_finite("timestamps", timestamps)
    check_finite("positions", positions)
    if len(timestamps) == 0:
        raise GeosegError("timestamps: expected at least one sample, got none")
    if np.any(np.diff(timestamps) <= 0):
        raise GeosegError("timestamps: expected strictly increasing times")
    rng = np.random.default_rng([int(seed), 0x6B5])

    period = 1.0 / config.rate_hz
    count = int(np.floor((timestamps[-1] - timestamps[0]) / period + 1e-9)) + 1
    t = timestamps[0] + period * np.arange(count)
    true_xyz = np.column_stack([np.interp(t, timestamps, positions[:, k]) for k in range(3)])

    bias = locally_constant_bias(t, config, rng)
    noise = rng.normal(0.0, config.noise_std_m, size=(count, 2))
    valid = ~markov_dropouts(
        count, config.dropout_share, config.dropout_burst_s * config.rate_hz, rng
    )
    alt_field = locally_constant_bias(
        t,
        GpsConfig(
            bias_max_m=4.0 * config.altitude_error_std_m,
            bias_std_m=config.altitude_error_std_m,
            bias_hold_s=config.bias_hold_s,
            bias_ramp_s=config.bias_ramp_s,
        ),
        rng,
    )[:, 0]

    xy = true_xyz[:, :2] + bias + noise
    z = true_xyz[:, 2] + alt_field
    lat, lon, height = georef.world_to_wgs84(np.column_stack([xy, z]))
    for arr in (xy, z, lat, lon, height):
        arr[~valid] = np.nan
    logger.debug("GPS: %d fixes, %d dropouts", count, int((~valid).sum()))
    return GpsLog(
        timestamps=t,
        valid=valid,
        xy=xy,
        z=z,
        lat_deg=lat,
        lon_deg=lon,
        height_m=height,
        true_xyz=true_xyz,
        bias=bias,
        config=config,
        georef=georef,
    )


def locally_constant_bias(t: np.ndarray, config: GpsConfig, rng: np.random.Generator) -> np.ndarray:
    """Piecewise-constant 2D bias with linear ramps, magnitude <= ``config.bias_max_m``.

    Args:
        t: `(G,)` increasing times, seconds.
        config: ``bias_std_m``, ``bias_max_m``, ``bias_hold_s``, ``bias_ramp_s``.
        rng: random generator.

    Returns:
        `(G, 2)` bias, metres.
    """
    if len(t) == 0:
        return np.zeros((0, 2))
    # Knot k starts hold k; the first knot lies before t[0] (random phase).
    start = t[0] - rng.uniform(0.0, config.bias_hold_s)
    knots = [start]
    while knots[-1] <= t[-1]:
        knots.append(knots[-1] + config.bias_hold_s * rng.uniform(0.5, 1.5))
    knots_arr = np.asarray(knots)
    values = rng.normal(0.0, config.bias_std_m, size=(len(knots_arr) + 1, 2))
    norms = np.linalg.norm(values, axis=1, keepdims=True)
    values *= np.minimum(1.0, config.bias_max_m / np.maximum(norms, 1e-12))
    # values[k + 1] holds from knots[k]; values[0] is the one before the first knot.
    k = np.searchsorted(knots_arr, t, side="right") - 1  # hold index, >= 0
    into = t - knots_arr[k]
    ramp = config.bias_ramp_s
    w = np.ones_like(t) if ramp <= 0 else np.clip(into / ramp, 0.0, 1.0)
    return (1.0 - w)[:, None] * values[k] + w[:, None] * values[k + 1]


def markov_dropouts(
    count: int, share: float, mean_burst: float, rng: np.random.Generator
) -> np.ndarray:
    """Bursts of missing samples from a two-state Markov chain.

    Args:
        count: number of samples G.
        share: stationary probability of a missing sample.
        mean_burst: mean run length of missing samples, in samples (>= 1 is meaningful).
        rng: random generator.

    Returns:
        `(G,)` bool, True where the sample is missing.
    """
    missing = np.zeros(count, dtype=bool)
    if share <= 0 or count == 0:
        return missing
    p_end = min(1.0, 1.0 / max(mean_burst, 1.0))
    p_start = min(1.0, share * p_end / (1.0 - share))
    draws = rng.random(count)
    state = draws[0] < share
    for i in range(count):
        if i > 0:
            state = (draws[i] >= p_end) if state else (draws[i] < p_start)
        missing[i] = state
    return missing
