"""Reading the sensor logs a user gives the image SLAM: GPS, wheel odometry, road DEM.

Each is a CSV file with a header line; columns are found by name (others are ignored), so the
files ``geoseg render`` writes (``gis/gps.csv``, ``gis/odometry.csv``, ``gis/dem.csv``) and a
user's own files with the same column names both work:

* GPS: ``timestamp`` (seconds, on the images' clock) and ``x, y`` (metres in the world frame)
  or ``lat_deg, lon_deg`` (WGS84, converted by the caller); optional ``valid`` (0 marks a
  dropout, whose position may be empty or NaN);
* odometry: ``timestamp``, ``speed_mps``, optionally ``yaw_rate_radps`` (the heading's rate,
  counter-clockwise seen from above: a gyro or the wheels' speed difference);
* DEM: road segments ``x0, y0, z0, x1, y1, z1`` (metres, world frame).

Every problem (missing file or column, a cell that is not a number, NaN or infinite values where
a number is needed, times that do not increase) is a :class:`slam_bridge.errors.SlamError`
naming the file, the row and the column.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam_bridge.csv_columns import read_columns
from slam_bridge.errors import SlamError
from slam_bridge.factors.dem import DemSegments

__all__ = ["GpsLogData", "read_gps_csv", "read_odometry_csv", "read_dem_csv"]


@dataclass
class GpsLogData:
    """A GPS log as read.

    Attributes:
        timestamps: ``(F,)`` seconds, increasing.
        xy: ``(F, 2)`` world metres (NaN for dropouts), or None when the file gives WGS84.
        lat_lon: ``(F, 2)`` WGS84 degrees (NaN for dropouts), or None.
        path: the file.
    """

    timestamps: np.ndarray
    xy: np.ndarray | None
    lat_lon: np.ndarray | None
    path: Path


def _check_finite(path: Path, cols: dict[str, np.ndarray], names: list[str], rows=None) -> None:
    for name in names:
        bad = ~np.isfinite(cols[name])
        if rows is not None:
            bad &= rows
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SlamError(
                f"{path}: row {i + 2}, column {name!r}: {cols[name][i]} (expected a finite number)"
            )


def _check_times(path: Path, t: np.ndarray) -> None:
    _check_finite(path, {"timestamp": t}, ["timestamp"])
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise SlamError(
            f"{path}: row {i + 2}: timestamp {t[i]} does not follow {t[i - 1]} (expected "
            "increasing times)"
        )


def read_gps_csv(path: str | Path) -> GpsLogData:
    """A GPS log (module docstring).

    Raises:
        SlamError: see :func:`read_columns`; neither ``x, y`` nor ``lat_deg, lon_deg``; a fix
            marked valid with a missing or non-finite position; times that do not increase.
    """
    path = Path(path)
    header = read_columns(path, ["timestamp"], ["valid", "x", "y", "lat_deg", "lon_deg"])
    if {"x", "y"} <= header.keys():
        names = ["x", "y"]
    elif {"lat_deg", "lon_deg"} <= header.keys():
        names = ["lat_deg", "lon_deg"]
    else:
        raise SlamError(f"{path}: expected columns x, y (world metres) or lat_deg, lon_deg (WGS84)")
    t = header["timestamp"]
    _check_times(path, t)
    valid = header["valid"] > 0.5 if "valid" in header else np.ones(t.size, dtype=bool)
    if "valid" in header:
        _check_finite(path, header, ["valid"])
    _check_finite(path, header, names, rows=valid)
    pos = np.column_stack([header[n] for n in names])
    pos[~valid] = np.nan
    if not valid.any():
        raise SlamError(f"{path}: every fix is marked invalid")
    xy = pos if names[0] == "x" else None
    return GpsLogData(t, xy, None if xy is not None else pos, path)


def read_odometry_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Wheel odometry: ``(timestamps (N,), speed_mps (N,), yaw_rate_radps (N,) or None)``.

    Raises:
        SlamError: see :func:`read_columns`; non-finite or negative speeds or non-finite yaw
            rates; times that do not increase; fewer than two samples.
    """
    path = Path(path)
    cols = read_columns(path, ["timestamp", "speed_mps"], ["yaw_rate_radps"])
    _check_times(path, cols["timestamp"])
    _check_finite(path, cols, [n for n in ("speed_mps", "yaw_rate_radps") if n in cols])
    if np.any(cols["speed_mps"] < 0):
        i = int(np.flatnonzero(cols["speed_mps"] < 0)[0])
        raise SlamError(f"{path}: row {i + 2}: negative speed {cols['speed_mps'][i]}")
    if cols["timestamp"].size < 2:
        raise SlamError(f"{path}: expected at least two odometry samples")
    return cols["timestamp"], cols["speed_mps"], cols.get("yaw_rate_radps")


def read_dem_csv(path: str | Path) -> DemSegments:
    """A road DEM as segments (:class:`slam_bridge.factors.dem.DemSegments`).

    Raises:
        SlamError: see :func:`read_columns`; non-finite coordinates.
    """
    path = Path(path)
    names = ["x0", "y0", "z0", "x1", "y1", "z1"]
    cols = read_columns(path, names)
    _check_finite(path, cols, names)
    return DemSegments(
        np.column_stack([cols["x0"], cols["y0"]]),
        np.column_stack([cols["x1"], cols["y1"]]),
        cols["z0"],
        cols["z1"],
    )
