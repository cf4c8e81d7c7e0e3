"""The georeference of a synthetic world: local metric frame <-> WGS84 (and Lambert-93).

Synthetic worlds are born in a local metric frame (x east, y north, z up, metres; docs/architecture.md).
This module pins that frame to the Earth so that GIS products can also be written in WGS84,
as a real GPS delivers them (thesis §1.9.3):

* the world origin ``(0, 0, 0)`` sits at ``(origin_lat_deg, origin_lon_deg, origin_alt_m)`` on
  the WGS84 ellipsoid (default: Créteil, France, where the thesis's sequences were recorded);
* world axes are the local East-North-Up (ENU) tangent-plane axes at that origin;
* the conversion is the exact ENU <-> ECEF <-> geodetic chain on the WGS84 ellipsoid, written
  with NumPy (no pyproj needed); a round trip world -> WGS84 -> world is exact to well below
  a millimetre. The horizontal position of a WGS84 point depends slightly on the altitude it
  is converted with (by ``|dh| d / R``: 1 cm for a 50 m altitude error 1.3 km from the origin),
  so logs carry the altitude they were converted with.

When the optional ``pyproj`` is installed (``pip install geoseg[geo]``), :func:`wgs84_to_lambert93`
and :func:`lambert93_to_wgs84` convert to and from the French projection Lambert-93 (EPSG:2154)
that the thesis works in.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from geoseg.errors import GeosegError, check_finite, check_shape

logger = logging.getLogger(__name__)

# WGS84 ellipsoid.
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


@dataclass
class Georeference:
    """Where the world origin lies on Earth; world axes are East, North, Up at that point.

    Attributes:
        origin_lat_deg: WGS84 latitude of the world origin, degrees.
        origin_lon_deg: WGS84 longitude of the world origin, degrees.
        origin_alt_m: ellipsoidal height of the world origin, metres.
    """

    origin_lat_deg: float = 48.7904  # Créteil (Val-de-Marne), France
    origin_lon_deg: float = 2.4556
    origin_alt_m: float = 40.0

    def __post_init__(self) -> None:
        if not -90.0 < self.origin_lat_deg < 90.0:
            raise GeosegError(
                f"origin_lat_deg: expected a latitude in (-90, 90), got {self.origin_lat_deg}"
            )
        if not -180.0 <= self.origin_lon_deg <= 180.0:
            raise GeosegError(
                f"origin_lon_deg: expected a longitude in [-180, 180], got {self.origin_lon_deg}"
            )

    def _enu_basis(self) -> tuple[np.ndarray, np.ndarray]:
        """`(3,)` origin in ECEF and `(3, 3)` rotation whose rows are E, N, U in ECEF."""
        lat = np.radians(self.origin_lat_deg)
        lon = np.radians(self.origin_lon_deg)
        origin = geodetic_to_ecef(
            np.array([self.origin_lat_deg]),
            np.array([self.origin_lon_deg]),
            np.array([self.origin_alt_m]),
        )[0]
        sl, cl, sp, cp = np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)
        rows = np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])
        return origin, rows

    def world_to_wgs84(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points to WGS84.

        Args:
            xyz: `(N, 3)` world points (metres), or `(N, 2)` horizontal positions taken at z = 0.

        Returns:
            `(lat_deg (N,), lon_deg (N,), alt_m (N,))`, ellipsoidal height.
        """
        xyz = _as_xyz("xyz", xyz)
        origin, rows = self._enu_basis()
        ecef = origin + xyz @ rows
        return ecef_to_geodetic(ecef)

    def wgs84_to_world(
        self, lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray | float | None = None
    ) -> np.ndarray:
        """WGS84 to world points.

        Args:
            lat_deg: `(N,)` latitudes, degrees.
            lon_deg: `(N,)` longitudes, degrees.
            alt_m: `(N,)` ellipsoidal heights, a scalar, or None for the origin's height
                (``origin_alt_m``): a horizontal fix without a usable altitude.

        Returns:
            `(N, 3)` world points (metres).
        """
        lat = np.atleast_1d(np.asarray(lat_deg, dtype=np.float64))
        lon = np.atleast_1d(np.asarray(lon_deg, dtype=np.float64))
        check_shape("lat_deg", lat, (None,))
        check_shape("lon_deg", lon, (lat.shape[0],))
        alt = self.origin_alt_m if alt_m is None else alt_m
        alt = np.broadcast_to(np.asarray(alt, dtype=np.float64), lat.shape)
        origin, rows = self._enu_basis()
        return (geodetic_to_ecef(lat, lon, alt) - origin) @ rows.T

    def world_to_lambert93(self, xyz: np.ndarray) -> np.ndarray:
        """World points to Lambert-93 (EPSG:2154) through WGS84; needs pyproj.

        Args:
            xyz: `(N, 3)` world points, or `(N, 2)` at z = 0.

        Returns:
            `(N, 3)` Lambert-93 easting, northing (metres) and the ellipsoidal height.
        """
        lat, lon, alt = self.world_to_wgs84(xyz)
        return np.column_stack([wgs84_to_lambert93(lat, lon), alt])


def geodetic_to_ecef(lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray) -> np.ndarray:
    """WGS84 geodetic coordinates to Earth-centred Earth-fixed.

    Args:
        lat_deg: `(N,)` latitudes, degrees.
        lon_deg: `(N,)` longitudes, degrees.
        alt_m: `(N,)` ellipsoidal heights, metres.

    Returns:
        `(N, 3)` ECEF coordinates, metres.
    """
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    alt = np.asarray(alt_m, dtype=np.float64)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    return np.stack(
        [
            (n + alt) * np.cos(lat) * np.cos(lon),
            (n + alt) * np.cos(lat) * np.sin(lon),
            (n * (1.0 - WGS84_E2) + alt) * np.sin(lat),
        ],
        axis=-1,
    )


def ecef_to_geodetic(ecef: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Earth-centred Earth-fixed to WGS84 geodetic coordinates (fixed-point iteration).

    Args:
        ecef: `(N, 3)` ECEF coordinates, metres (not near the Earth's centre).

    Returns:
        `(lat_deg (N,), lon_deg (N,), alt_m (N,))`.
    """
    x, y, z = ecef[:, 0], ecef[:, 1], ecef[:, 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(8):  # converges to ~1e-12 rad in 3-4 iterations near the surface
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        alt = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + alt)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    alt = p / np.cos(lat) - n
    return np.degrees(lat), np.degrees(lon), alt


def wgs84_to_lambert93(lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
    """WGS84 to Lambert-93 (EPSG:2154) through pyproj.

    Args:
        lat_deg: `(N,)` latitudes, degrees.
        lon_deg: `(N,)` longitudes, degrees.

    Returns:
        `(N, 2)` Lambert-93 easting, northing (metres).

    Raises:
        GeosegError: pyproj is not installed.
    """
    transformer = _transformer("EPSG:4326", "EPSG:2154")
    e, n = transformer.transform(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
    return np.stack([np.asarray(e), np.asarray(n)], axis=-1)


def lambert93_to_wgs84(easting_northing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lambert-93 (EPSG:2154) to WGS84 through pyproj.

    Args:
        easting_northing: `(N, 2)` Lambert-93 coordinates, metres.

    Returns:
        `(lat_deg (N,), lon_deg (N,))`.

    Raises:
        GeosegError: pyproj is not installed.
    """
    check_shape("easting_northing", easting_northing, (None, 2))
    transformer = _transformer("EPSG:2154", "EPSG:4326")
    lon, lat = transformer.transform(easting_northing[:, 0], easting_northing[:, 1])
    return np.asarray(lat), np.asarray(lon)


def _transformer(source: str, target: str):
    try:
        from pyproj import Transformer
    except ImportError:
        raise GeosegError(
            "Lambert-93 conversion needs pyproj, an optional extra: pip install geoseg[geo]"
        ) from None
    return Transformer.from_crs(source, target, always_xy=True)


def _as_xyz(name: str, value: np.ndarray) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise GeosegError(f"{name}: expected shape (N, 3) or (N, 2), got {arr.shape}")
    check_finite(name, arr)
    if arr.shape[1] == 2:
        arr = np.concatenate([arr, np.zeros((arr.shape[0], 1))], axis=1)
    return arr
