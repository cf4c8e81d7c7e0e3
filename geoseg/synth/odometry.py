"""Wheel odometry: measured speed at the frame rate, and dead reckoning.

The measured speed is ``v_meas = (1 + s) v_true + eps`` with a constant scale error ``s``
(wheel radius, tyre pressure) drawn in ``[-scale_error_max, scale_error_max]`` and white noise
``eps ~ N(0, speed_noise_std_mps²)``; speeds are never negative. The heading that goes with it
(a gyro or the GPS course in a real car) is the true heading plus a slow random-walk drift of
``heading_drift_std_rad_per_sqrt_s``.

Headings are in radians, counter-clockwise from the world x axis (east): the direction of motion
is ``(cos h, sin h)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geoseg.errors import ConfigError, GeosegError, check_finite, check_shape
from geoseg.synth.tables import read_table, write_table

logger = logging.getLogger(__name__)


@dataclass
class OdometryConfig:
    """Wheel-odometry error model.

    Attributes:
        speed_noise_std_mps: standard deviation of the white speed noise.
        scale_error_max: bound of the constant relative scale error.
        heading_drift_std_rad_per_sqrt_s: random-walk intensity of the heading error.
    """

    speed_noise_std_mps: float = 0.05
    scale_error_max: float = 0.02
    heading_drift_std_rad_per_sqrt_s: float = 0.002

    def __post_init__(self) -> None:
        for name in ("speed_noise_std_mps", "scale_error_max", "heading_drift_std_rad_per_sqrt_s"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if self.scale_error_max >= 1.0:
            raise ConfigError(f"scale_error_max: expected < 1, got {self.scale_error_max}")


@dataclass(frozen=True)
class OdometryLog:
    """Odometry at the frame rate.

    Attributes:
        timestamps: `(T,)` seconds.
        speed: `(T,)` measured speed, m/s.
        heading: `(T,)` measured heading, rad.
        true_speed: `(T,)` ground-truth speed.
        true_heading: `(T,)` ground-truth heading.
        scale: the relative scale error ``s`` used.
        config: the error model used.
    """

    timestamps: np.ndarray
    speed: np.ndarray
    heading: np.ndarray
    true_speed: np.ndarray
    true_heading: np.ndarray
    scale: float
    config: OdometryConfig = field(default_factory=OdometryConfig)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    CSV_HEADER = "timestamp,speed_mps,heading_rad,true_speed_mps,true_heading_rad"

    def write_csv(self, path: str | Path) -> Path:
        """Write the log as CSV (columns :attr:`CSV_HEADER`; ``true_*`` is ground truth)."""
        path = Path(path)
        table = np.column_stack(
            [self.timestamps, self.speed, self.heading, self.true_speed, self.true_heading]
        )
        return write_table(path, table, ["%.6f", "%.5f", "%.6f", "%.5f", "%.6f"], self.CSV_HEADER)

    @classmethod
    def read_csv(cls, path: str | Path) -> OdometryLog:
        """Read a log written by :meth:`write_csv` (``scale`` unknown: NaN)."""
        t = read_table(path, cls.CSV_HEADER)
        return cls(
            timestamps=t[:, 0],
            speed=t[:, 1],
            heading=t[:, 2],
            true_speed=t[:, 3],
            true_heading=t[:, 4],
            scale=float("nan"),
        )

    def dead_reckon(self, start_xy: np.ndarray) -> np.ndarray:
        """The track integrated from the measured speed and heading; `(T, 2)`."""
        return dead_reckon(self.timestamps, self.speed, self.heading, start_xy)


def simulate_odometry(
    timestamps: np.ndarray,
    speed: np.ndarray,
    heading: np.ndarray,
    config: OdometryConfig | None = None,
    *,
    seed: int = 0,
) -> OdometryLog:
    """Measured odometry from the true speed and heading.

    Args:
        timestamps: `(T,)` increasing times, seconds.
        speed: `(T,)` true speed, m/s.
        heading: `(T,)` true heading, rad.
        config: error model (defaults when None).
        seed: random seed.

    Returns:
        The odometry log.
    """
    config = config or OdometryConfig()
    timestamps, speed, heading = _checked(timestamps, speed, heading)
    rng = np.random.default_rng([int(seed), 0x0D0])
    scale = float(rng.uniform(-config.scale_error_max, config.scale_error_max))
    noise = rng.normal(0.0, config.speed_noise_std_mps, size=len(speed))
    dt = np.diff(timestamps, prepend=timestamps[0])
    drift = np.cumsum(rng.normal(0.0, 1.0, size=len(speed)) * np.sqrt(dt))
    measured = np.maximum((1.0 + scale) * speed + noise, 0.0)
    return OdometryLog(
        timestamps=timestamps,
        speed=measured,
        heading=heading + config.heading_drift_std_rad_per_sqrt_s * drift,
        true_speed=speed,
        true_heading=heading,
        scale=scale,
        config=config,
    )


def dead_reckon(
    timestamps: np.ndarray, speed: np.ndarray, heading: np.ndarray, start_xy: np.ndarray
) -> np.ndarray:
    """Integrate speed and heading into a horizontal track.

    Between two samples the motion is taken as an arc of constant speed (the mean of the two)
    and constant turn rate; the displacement is the arc's chord,
    ``v dt sinc(dh / 2) (cos h_mid, sin h_mid)``, exact for straight lines and circles.

    Args:
        timestamps: `(T,)` increasing times, seconds.
        speed: `(T,)` speeds, m/s.
        heading: `(T,)` headings, rad (counter-clockwise from x).
        start_xy: `(2,)` position at ``timestamps[0]``.

    Returns:
        `(T, 2)` positions, world metres.
    """
    timestamps, speed, heading = _checked(timestamps, speed, heading)
    start_xy = np.asarray(start_xy, dtype=np.float64)
    check_shape("start_xy", start_xy, (2,))
    dt = np.diff(timestamps)
    v = 0.5 * (speed[1:] + speed[:-1])
    dh = np.angle(np.exp(1j * np.diff(heading)))  # wrapped turn
    h_mid = heading[:-1] + 0.5 * dh
    chord = v * dt * np.sinc(dh / (2.0 * np.pi))  # np.sinc(x) = sin(pi x) / (pi x)
    steps = chord[:, None] * np.column_stack([np.cos(h_mid), np.sin(h_mid)])
    return start_xy + np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])


def _checked(
    timestamps: np.ndarray, speed: np.ndarray, heading: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    timestamps = np.asarray(timestamps, dtype=np.float64)
    speed = np.asarray(speed, dtype=np.float64)
    heading = np.asarray(heading, dtype=np.float64)
    check_shape("timestamps", timestamps, (None,))
    check_shape("speed", speed, timestamps.shape)
    check_shape("heading", heading, timestamps.shape)
    for name, arr in (("timestamps", timestamps), ("speed", speed), ("heading", heading)):
        check_finite(name, arr)
    if len(timestamps) == 0:
        raise GeosegError("timestamps: expected at least one sample, got none")
    if np.any(np.diff(timestamps) <= 0):
        raise GeosegError("timestamps: expected strictly increasing times")
    return timestamps, speed, heading
