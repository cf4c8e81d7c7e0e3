"""The digital elevation model of the roads: 2D segments along the streets with an altitude at
each end (thesis §1.9.2), with a smooth, hard-bounded altitude error.

A real road DEM gives no cross-slope and no altitude off the road; its error is up to ~2 m and
varies slowly along the road. :func:`build_dem` resamples every street centreline into segments
of about ``segment_length_m``, reads the true road altitude at the segment ends and adds an error
drawn from a smooth random field of the position (a sum of random Fourier features, i.e. an
approximate Gaussian process with correlation length ``correlation_length_m``), hard-clipped to
``max_error_m``. Since the error is a function of the position, segments meeting at a junction
agree on its altitude.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geoseg.atomic import atomic_write
from geoseg.config import to_dict
from geoseg.errors import ConfigError, GeosegError, check_finite, check_shape
from geoseg.synth.georef import Georeference
from geoseg.synth.tables import read_table, write_table

logger = logging.getLogger(__name__)


@dataclass
class DemConfig:
    """Error model and sampling of the road DEM.

    Attributes:
        segment_length_m: target length of a DEM segment along a centreline.
        max_error_m: hard bound on the altitude error at every segment end.
        error_std_m: standard deviation of the smooth error field (before clipping).
        correlation_length_m: correlation length of the error field.
        num_features: random Fourier features of the error field.
    """

    segment_length_m: float = 10.0
    max_error_m: float = 2.0
    error_std_m: float = 0.8
    correlation_length_m: float = 60.0
    num_features: int = 64

    def __post_init__(self) -> None:
        for name in ("segment_length_m", "correlation_length_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: expected > 0, got {getattr(self, name)}")
        for name in ("max_error_m", "error_std_m"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if self.num_features < 1:
            raise ConfigError(f"num_features: expected >= 1, got {self.num_features}")


@dataclass(frozen=True)
class SmoothErrorField:
    """A smooth random scalar field of the plane, hard-clipped: ``e(x) in [-bound, bound]``.

    ``e(x) = clip(std * sqrt(2 / K) * sum_k cos(w_k · x + phi_k), -bound, bound)`` with
    ``w_k ~ N(0, I / length^2)``: an approximate Gaussian process with a squared-exponential
    kernel of length ``length``.

    Attributes:
        frequencies: `(K, 2)` angular frequencies, rad/m.
        phases: `(K,)` phases, rad.
        std: field standard deviation before clipping.
        bound: hard bound.
    """

    frequencies: np.ndarray
    phases: np.ndarray
    std: float
    bound: float

    @classmethod
    def draw(
        cls, rng: np.random.Generator, *, std: float, length: float, bound: float, features: int
    ) -> SmoothErrorField:
        return cls(
            frequencies=rng.normal(0.0, 1.0 / length, size=(features, 2)),
            phases=rng.uniform(0.0, 2.0 * np.pi, size=features),
            std=float(std),
            bound=float(bound),
        )

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """Field values at `(N, 2)` points; returns `(N,)`."""
        k = len(self.phases)
        raw = np.cos(xy @ self.frequencies.T + self.phases).sum(axis=1)
        return np.clip(self.std * np.sqrt(2.0 / k) * raw, -self.bound, self.bound)


@dataclass(frozen=True)
class DemModel:
    """Road DEM: S segments with an altitude at each end.

    Attributes:
        p0: `(S, 2)` segment starts, world metres.
        p1: `(S, 2)` segment ends.
        z0: `(S,)` model altitude at ``p0`` (with error).
        z1: `(S,)` model altitude at ``p1``.
        street_id: `(S,)` index of the street the segment lies on.
        true_z0: `(S,)` true road altitude at ``p0`` (ground truth, not given to the SLAM).
        true_z1: `(S,)` true road altitude at ``p1``.
        config: the error model used.
        seed: the seed used.
    """

    p0: np.ndarray
    p1: np.ndarray
    z0: np.ndarray
    z1: np.ndarray
    street_id: np.ndarray
    true_z0: np.ndarray
    true_z1: np.ndarray
    config: DemConfig = field(default_factory=DemConfig)
    seed: int = 0

    def __len__(self) -> int:
        return int(self.p0.shape[0])

    @property
    def error0(self) -> np.ndarray:
        """`(S,)` altitude error at the segment starts."""
        return self.z0 - self.true_z0

    @property
    def error1(self) -> np.ndarray:
        """`(S,)` altitude error at the segment ends."""
        return self.z1 - self.true_z1

    def nearest_segment(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The nearest segment of each point.

        Args:
            xy: `(N, 2)` horizontal positions, world metres.

        Returns:
            `(index (N,) int, t (N,) in [0, 1] position along the segment, distance (N,) m)`.
        """
        xy = np.asarray(xy, dtype=np.float64)
        check_shape("xy", xy, (None, 2))
        check_finite("xy", xy)
        if len(self) == 0:
            raise GeosegError("DEM: the model has no segment")
        ab = self.p1 - self.p0
        denom = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
        index = np.empty(len(xy), dtype=np.int64)
        t_out = np.empty(len(xy))
        dist_out = np.empty(len(xy))
        chunk = max(1, 2_000_000 // max(len(self), 1))
        for start in range(0, len(xy), chunk):
            p = xy[start : start + chunk]
            ap = p[:, None, :] - self.p0[None]
            t = np.clip(np.einsum("nsk,sk->ns", ap, ab) / denom, 0.0, 1.0)
            d2 = ((ap - t[..., None] * ab[None]) ** 2).sum(axis=2)
            best = np.argmin(d2, axis=1)
            rows = np.arange(len(p))
            index[start : start + chunk] = best
            t_out[start : start + chunk] = t[rows, best]
            dist_out[start : start + chunk] = np.sqrt(d2[rows, best])
        return index, t_out, dist_out

    def altitude_at(self, xy: np.ndarray) -> np.ndarray:
        """Model road altitude under points: nearest segment, linear along it.

        Args:
            xy: `(N, 2)` horizontal positions, world metres.

        Returns:
            `(N,)` altitudes, metres.
        """
        index, t, _ = self.nearest_segment(xy)
        return self.z0[index] + t * (self.z1[index] - self.z0[index])

    CSV_HEADER = "segment_id,street_id,x0,y0,z0,x1,y1,z1,true_z0,true_z1"

    def write_csv(self, path: str | Path) -> Path:
        """Write the segments as CSV (columns :attr:`CSV_HEADER`; ``true_*`` is ground truth)."""
        path = Path(path)
        table = np.column_stack(
            [
                np.arange(len(self)),
                self.street_id,
                self.p0,
                self.z0,
                self.p1,
                self.z1,
                self.true_z0,
                self.true_z1,
            ]
        )
        fmt = ["%d", "%d"] + ["%.4f"] * 8
        return write_table(path, table, fmt, self.CSV_HEADER)

    @classmethod
    def read_csv(cls, path: str | Path) -> DemModel:
        """Read segments written by :meth:`write_csv` (values rounded to 0.1 mm)."""
        t = read_table(path, cls.CSV_HEADER)
        return cls(
            p0=t[:, 2:4],
            z0=t[:, 4],
            p1=t[:, 5:7],
            z1=t[:, 7],
            street_id=t[:, 1].astype(np.int64),
            true_z0=t[:, 8],
            true_z1=t[:, 9],
        )

    def to_geojson(self, georef: Georeference | None = None) -> dict[str, Any]:
        """GeoJSON FeatureCollection (RFC 7946): one LineString per segment.

        Coordinates are WGS84 ``[lon, lat, altitude]`` through ``georef``; the altitude is the
        model road altitude in the world frame (metres above the world origin). Each feature's
        properties carry the segment id, street id and world-frame end points.
        """
        georef = georef or Georeference()
        features = []
        if len(self):
            ends = np.concatenate([self.p0, self.p1])
            lat, lon, _ = georef.world_to_wgs84(ends)
            n = len(self)
            for s in range(n):
                features.append(
                    {
                        "type": "Feature",
                        "geometry": {
                            "type": "LineString",
                            "coordinates": [
                                [round(lon[s], 9), round(lat[s], 9), round(float(self.z0[s]), 4)],
                                [
                                    round(lon[n + s], 9),
                                    round(lat[n + s], 9),
                                    round(float(self.z1[s]), 4),
                                ],
                            ],
                        },
                        "properties": {
                            "segment_id": s,
                            "street_id": int(self.street_id[s]),
                            "world_xyz0": [*np.round(self.p0[s], 4).tolist(), float(self.z0[s])],
                            "world_xyz1": [*np.round(self.p1[s], 4).tolist(), float(self.z1[s])],
                        },
                    }
                )
        return {
            "type": "FeatureCollection",
            "name": "road_dem",
            "georeference": to_dict(georef),
            "features": features,
        }

    def write(self, directory: str | Path, georef: Georeference | None = None) -> dict:
        """Write ``dem.csv`` and ``dem.geojson``; returns name -> path."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        paths = {"dem_csv": directory / "dem.csv", "dem_geojson": directory / "dem.geojson"}
        self.write_csv(paths["dem_csv"])
        atomic_write(paths["dem_geojson"], json.dumps(self.to_geojson(georef)), fsync=False)
        return paths


def build_dem(
    centerlines: Sequence[np.ndarray],
    terrain_height: Callable[[np.ndarray], np.ndarray],
    config: DemConfig | None = None,
    *,
    seed: int = 0,
) -> DemModel:
    """Road DEM with a smooth, bounded altitude error.

    Args:
        centerlines: per street a `(M_i, 2)` centreline polyline, world metres.
        terrain_height: maps `(N, 2)` positions to `(N,)` true road altitudes
            (e.g. ``World.terrain_height``).
        config: error model and sampling (defaults when None).
        seed: random seed; the same seed gives the same DEM.

    Returns:
        The DEM model.
    """
    config = config or DemConfig()
    rng = np.random.default_rng([int(seed), 0xD3E])
    field_ = SmoothErrorField.draw(
        rng,
        std=config.error_std_m,
        length=config.correlation_length_m,
        bound=config.max_error_m,
        features=config.num_features,
    )
    p0, p1, sid = [], [], []
    for i, line in enumerate(centerlines):
        line = np.asarray(line, dtype=np.float64)
        check_shape(f"centerlines[{i}]", line, (None, 2))
        check_finite(f"centerlines[{i}]", line)
        pts = resample_polyline(line, config.segment_length_m)
        if len(pts) < 2:
            logger.warning("street %d: centreline shorter than two points, no DEM segment", i)
            continue
        p0.append(pts[:-1])
        p1.append(pts[1:])
        sid.append(np.full(len(pts) - 1, i))
    if not p0:
        raise GeosegError("centerlines: expected at least one street with two points, got none")
    p0a, p1a = np.concatenate(p0), np.concatenate(p1)
    true_z0 = np.asarray(terrain_height(p0a), dtype=np.float64).reshape(-1)
    true_z1 = np.asarray(terrain_height(p1a), dtype=np.float64).reshape(-1)
    check_shape("terrain_height(xy)", true_z0, (len(p0a),))
    return DemModel(
        p0=p0a,
        p1=p1a,
        z0=true_z0 + field_(p0a),
        z1=true_z1 + field_(p1a),
        street_id=np.concatenate(sid).astype(np.int64),
        true_z0=true_z0,
        true_z1=true_z1,
        config=config,
        seed=int(seed),
    )


def resample_polyline(line: np.ndarray, step: float) -> np.ndarray:
    """Points along a polyline every ~``step`` metres, keeping both ends and every vertex
    where the direction turns by more than 10 degrees.

    Args:
        line: `(M, 2)` polyline.
        step: target spacing, metres.

    Returns:
        `(P, 2)` points (consecutive duplicates removed).
    """
    keep = np.concatenate([[True], np.linalg.norm(np.diff(line, axis=0), axis=1) > 1e-9])
    line = line[keep]
    if len(line) < 2:
        return line
    # Split at sharp corners so that they stay exact segment ends.
    d = np.diff(line, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    turn = np.abs(np.angle(np.exp(1j * np.diff(heading))))
    cuts = [0, *(np.nonzero(turn > np.radians(10.0))[0] + 1).tolist(), len(line) - 1]
    out = [line[:1]]
    for a, b in zip(cuts[:-1], cuts[1:]):
        piece = line[a : b + 1]
        seg = np.linalg.norm(np.diff(piece, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        n = max(1, int(np.ceil(s[-1] / step - 1e-9)))
        targets = np.linspace(0.0, s[-1], n + 1)[1:]
        out.append(
            np.column_stack(
                [np.interp(targets, s, piece[:, 0]), np.interp(targets, s, piece[:, 1])]
            )
        )
    return np.concatenate(out)
