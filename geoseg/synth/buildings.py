"""The building model as given to the SLAM: the world's buildings with the errors of a real GIS.

Real 2.5D building databases (thesis §1.9.1, IGN models) represent each facade by one plane,
carry a horizontal error of up to ~2.5 m, have unreliable heights, and may be outdated
(demolished buildings still present, new ones missing). :func:`build_building_model` derives
such a model from the true buildings, deterministically from a seed:

* **horizontal error**: each building's footprint is rotated about its centroid and shifted.
  The displacement of every footprint vertex, hence of every point of every facade (the motion
  is affine), is hard-bounded by ``max_horizontal_error_m``: the shift is clipped to the bound
  and the rotation only uses the budget the shift leaves;
* **heights**: multiplied by a random factor or replaced by a storey-count guess;
* **outdated database**: a share of the true buildings is missing, and a few ``extra`` buildings
  (demolished ones) stand on free ground, away from the streets.

The model keeps the correspondence with the truth: a model building has the id of the true
building it comes from (``true_id``), an extra has ``true_id == -1`` and an id above every true
id; facade ``k`` of a model building is the image of edge ``k`` of the true footprint.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import numpy as np

from geoseg.atomic import atomic_write
from geoseg.config import to_dict
from geoseg.errors import ConfigError, GeosegError, check_finite, check_shape
from geoseg.synth.tables import read_table, write_table

logger = logging.getLogger(__name__)

PRESENT, MISSING, EXTRA = "present", "missing", "extra"


@dataclass
class BuildingErrorConfig:
    """Error model of the GIS building database.

    Attributes:
        max_horizontal_error_m: hard bound on the horizontal displacement of any facade point.
        horizontal_error_std_m: per-axis standard deviation of the per-building shift (before
            clipping to the bound).
        max_rotation_deg: bound on the per-building rotation about its centroid.
        height_error: ``"scale"`` (true height times a factor in ``height_scale_range``),
            ``"storeys"`` (a storey-count guess times ``storey_height_m``) or ``"mixed"`` (each
            building draws one of the two).
        height_scale_range: range of the height factor.
        storey_height_m: storey height the database assumes.
        storey_count_error: the storey guess is off by up to this many storeys.
        min_height_m: no model building is lower than this.
        missing_share: share of the true buildings absent from the database (at least one when
            the share is positive and there are two buildings or more).
        extra_count: number of demolished buildings still in the database.
        extra_size_range_m: side lengths of the extra (rectangular) buildings.
        street_clearance_m: extra buildings keep this distance from the sidewalk edge.
    """

    max_horizontal_error_m: float = 2.5
    horizontal_error_std_m: float = 1.2
    max_rotation_deg: float = 3.0
    height_error: Literal["scale", "storeys", "mixed"] = "mixed"
    height_scale_range: tuple[float, float] = (0.6, 1.5)
    storey_height_m: float = 3.0
    storey_count_error: int = 2
    min_height_m: float = 3.0
    missing_share: float = 0.08
    extra_count: int = 2
    extra_size_range_m: tuple[float, float] = (8.0, 18.0)
    street_clearance_m: float = 1.5

    def __post_init__(self) -> None:
        for name in ("max_horizontal_error_m", "horizontal_error_std_m", "max_rotation_deg"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}: expected >= 0, got {getattr(self, name)}")
        lo, hi = self.height_scale_range
        if not 0 < lo <= hi:
            raise ConfigError(f"height_scale_range: expected 0 < low <= high, got {(lo, hi)}")
        lo, hi = self.extra_size_range_m
        if not 0 < lo <= hi:
            raise ConfigError(f"extra_size_range_m: expected 0 < low <= high, got {(lo, hi)}")
        if not 0.0 <= self.missing_share < 1.0:
            raise ConfigError(
                f"missing_share: expected a share in [0, 1), got {self.missing_share}"
            )
        if self.extra_count < 0:
            raise ConfigError(f"extra_count: expected >= 0, got {self.extra_count}")
        if self.storey_height_m <= 0 or self.min_height_m <= 0:
            raise ConfigError("storey_height_m and min_height_m: expected > 0")
        if self.storey_count_error < 0:
            raise ConfigError(f"storey_count_error: expected >= 0, got {self.storey_count_error}")
        if not self.street_clearance_m >= 0:
            raise ConfigError(f"street_clearance_m: expected >= 0, got {self.street_clearance_m}")


@dataclass(frozen=True)
class ModelBuilding:
    """One building of the GIS model.

    Attributes:
        id: building id (the true building's id, or a fresh id for an extra).
        footprint: `(N, 2)` counter-clockwise polygon, world metres.
        base_z: altitude of the ground floor, metres.
        height: height above ``base_z``, metres.
        status: ``"present"`` (a true building, with errors) or ``"extra"`` (not in the world).
        true_id: id of the true building, -1 for an extra.
        shift: `(2,)` translation applied to the centroid, metres.
        rotation_rad: rotation about the centroid, radians (counter-clockwise).
        true_height: the true height, NaN for an extra.
    """

    id: int
    footprint: np.ndarray
    base_z: float
    height: float
    status: str
    true_id: int
    shift: np.ndarray
    rotation_rad: float
    true_height: float = float("nan")


@dataclass(frozen=True)
class FacadePlanes:
    """One vertical plane per facade of the model: ``normal · X_w = d``.

    Attributes:
        plane_id: `(F,)` int, 0..F-1.
        building_id: `(F,)` int, the model building the facade belongs to.
        edge_index: `(F,)` int, the footprint edge (``p0 = footprint[k]``, ``p1 = footprint[k+1]``).
        p0: `(F, 2)` start of the facade's bottom edge (counter-clockwise order), world metres.
        p1: `(F, 2)` its end.
        z_min: `(F,)` bottom altitude.
        z_max: `(F,)` top altitude.
        normal: `(F, 3)` outward unit normal (horizontal).
        d: `(F,)` plane offset, ``normal · X = d`` for every point X of the plane.
        true_facade_id: `(F,)` int, row of the true facade this plane models in the world's
            facade table (buildings in order, each footprint's edges in order, as
            ``World.facades()``); -1 for the facades of extra buildings.
    """

    plane_id: np.ndarray
    building_id: np.ndarray
    edge_index: np.ndarray
    p0: np.ndarray
    p1: np.ndarray
    z_min: np.ndarray
    z_max: np.ndarray
    normal: np.ndarray
    d: np.ndarray
    true_facade_id: np.ndarray

    def __len__(self) -> int:
        return int(self.plane_id.shape[0])

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of points to every (infinite) facade plane.

        Args:
            points: `(N, 3)` world points.

        Returns:
            `(N, F)` distances, positive outside the building.
        """
        check_shape("points", points, (None, 3))
        return points @ self.normal.T - self.d[None, :]

    CSV_HEADER = "plane_id,building_id,edge_index,x0,y0,x1,y1,z_min,z_max,nx,ny,nz,d,true_facade_id"

    def write_csv(self, path: str | Path) -> Path:
        """Write the table as CSV with the columns of :attr:`CSV_HEADER`."""
        path = Path(path)
        table = np.column_stack(
            [
                self.plane_id,
                self.building_id,
                self.edge_index,
                self.p0,
                self.p1,
                self.z_min,
                self.z_max,
                self.normal,
                self.d,
                self.true_facade_id,
            ]
        )
        fmt = ["%d", "%d", "%d"] + ["%.4f"] * 6 + ["%.6f"] * 3 + ["%.4f", "%d"]
        return write_table(path, table, fmt, self.CSV_HEADER)

    @classmethod
    def read_csv(cls, path: str | Path) -> FacadePlanes:
        """Read a table written by :meth:`write_csv` (coordinates rounded to 0.1 mm)."""
        t = read_table(path, cls.CSV_HEADER)
        return cls(
            plane_id=t[:, 0].astype(np.int64),
            building_id=t[:, 1].astype(np.int64),
            edge_index=t[:, 2].astype(np.int64),
            p0=t[:, 3:5],
            p1=t[:, 5:7],
            z_min=t[:, 7],
            z_max=t[:, 8],
            normal=t[:, 9:12],
            d=t[:, 12],
            true_facade_id=t[:, 13].astype(np.int64),
        )


@dataclass(frozen=True)
class BuildingModel:
    """The erroneous building database and its correspondence with the true buildings.

    Attributes:
        buildings: the model's buildings (present ones first, in true-id order, then extras).
        missing_ids: ids of the true buildings absent from the model.
        true_ids: ids of all true buildings, in input order.
        true_facade_offsets: per true building (same order), the row of its first facade in
            the world's facade table.
        config: the error model used.
        seed: the seed used.
    """

    buildings: tuple[ModelBuilding, ...]
    missing_ids: tuple[int, ...]
    true_ids: tuple[int, ...]
    true_facade_offsets: tuple[int, ...] = ()
    config: BuildingErrorConfig = field(default_factory=BuildingErrorConfig)
    seed: int = 0

    @property
    def status(self) -> dict[int, str]:
        """Building id -> ``"present"``, ``"missing"`` (true, not in the model) or ``"extra"``."""
        out = {b.id: b.status for b in self.buildings}
        out.update({i: MISSING for i in self.missing_ids})
        return dict(sorted(out.items()))

    @property
    def true_to_model(self) -> dict[int, int]:
        """True building id -> model building id (missing buildings are absent)."""
        return {b.true_id: b.id for b in self.buildings if b.status == PRESENT}

    @property
    def extra_ids(self) -> tuple[int, ...]:
        return tuple(b.id for b in self.buildings if b.status == EXTRA)

    @cached_property
    def planes(self) -> FacadePlanes:
        """The facade-plane table (one plane per footprint edge of every model building)."""
        keys = ("bid", "edge", "p0", "p1", "z0", "z1", "true")
        rows: dict[str, list[np.ndarray]] = {k: [] for k in keys}
        offsets = dict(zip(self.true_ids, self.true_facade_offsets))
        for b in self.buildings:
            n = len(b.footprint)
            first = offsets.get(b.true_id, -1) if b.status == PRESENT else -1
            rows["true"].append(np.arange(n) + first if first >= 0 else np.full(n, -1))
            rows["bid"].append(np.full(n, b.id))
            rows["edge"].append(np.arange(n))
            rows["p0"].append(b.footprint)
            rows["p1"].append(np.roll(b.footprint, -1, axis=0))
            rows["z0"].append(np.full(n, b.base_z))
            rows["z1"].append(np.full(n, b.base_z + b.height))
        if not self.buildings:
            empty = np.zeros((0,))
            return FacadePlanes(
                empty.astype(int),
                empty.astype(int),
                empty.astype(int),
                np.zeros((0, 2)),
                np.zeros((0, 2)),
                empty,
                empty,
                np.zeros((0, 3)),
                empty,
                empty.astype(int),
            )
        p0 = np.concatenate(rows["p0"]).astype(np.float64)
        p1 = np.concatenate(rows["p1"]).astype(np.float64)
        edge = p1 - p0
        length = np.linalg.norm(edge, axis=1, keepdims=True)
        normal_xy = np.column_stack([edge[:, 1], -edge[:, 0]]) / np.maximum(length, 1e-12)
        normal = np.column_stack([normal_xy, np.zeros(len(p0))])
        return FacadePlanes(
            plane_id=np.arange(len(p0)),
            building_id=np.concatenate(rows["bid"]).astype(np.int64),
            edge_index=np.concatenate(rows["edge"]).astype(np.int64),
            p0=p0,
            p1=p1,
            z_min=np.concatenate(rows["z0"]).astype(np.float64),
            z_max=np.concatenate(rows["z1"]).astype(np.float64),
            normal=normal,
            d=np.einsum("ij,ij->i", normal_xy, p0),
            true_facade_id=np.concatenate(rows["true"]).astype(np.int64),
        )

    def to_mesh(self):
        """The model as a closed triangle mesh of extruded footprints (a ``trimesh.Trimesh``).

        Face attributes: ``building_id`` and ``plane_id`` (-1 for roofs and floors); face colours
        grey for present buildings, red for extras.
        """
        return extrude_footprints(
            [b.footprint for b in self.buildings],
            [b.base_z for b in self.buildings],
            [b.height for b in self.buildings],
            building_ids=[b.id for b in self.buildings],
            colors=[
                (160, 160, 160, 255) if b.status == PRESENT else (220, 40, 40, 255)
                for b in self.buildings
            ],
        )

    def to_json_dict(self) -> dict[str, Any]:
        """Plain-data description: buildings, status, correspondence, error model."""
        return {
            "frame": "world (x east, y north, z up, metres); footprints counter-clockwise",
            "seed": self.seed,
            "error_model": to_dict(self.config),
            "missing_ids": list(self.missing_ids),
            "extra_ids": list(self.extra_ids),
            "true_to_model": {str(k): v for k, v in self.true_to_model.items()},
            "status": {str(k): v for k, v in self.status.items()},
            "buildings": [
                {
                    "id": b.id,
                    "status": b.status,
                    "true_id": b.true_id,
                    "base_z": round(float(b.base_z), 4),
                    "height": round(float(b.height), 4),
                    "true_height": None if np.isnan(b.true_height) else float(b.true_height),
                    "shift": [round(float(v), 4) for v in b.shift],
                    "rotation_rad": float(b.rotation_rad),
                    "footprint": np.round(b.footprint, 4).tolist(),
                }
                for b in self.buildings
            ],
        }

    def write(self, directory: str | Path, *, mesh_format: Literal["ply", "obj"] = "ply") -> dict:
        """Write ``buildings_model.<ply|obj>``, ``facades.csv`` and ``buildings_model.json``.

        Returns:
            name -> path of every file written.
        """
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        paths = {
            "mesh": directory / f"buildings_model.{mesh_format}",
            "facades_csv": directory / "facades.csv",
            "buildings_json": directory / "buildings_model.json",
        }
        write_mesh(self.to_mesh(), paths["mesh"], mesh_format)
        self.planes.write_csv(paths["facades_csv"])
        doc = self.to_json_dict()
        doc["facades"] = {
            "csv": paths["facades_csv"].name,
            "columns": FacadePlanes.CSV_HEADER.split(","),
            "plane": "normal . X = d, normal outward and horizontal",
        }
        atomic_write(paths["buildings_json"], json.dumps(doc, indent=1), fsync=False)
        return paths


def write_mesh(mesh: Any, path: str | Path, mesh_format: Literal["ply", "obj"] = "ply") -> Path:
    """Export a trimesh mesh to ``path`` atomically (no partial mesh on a full disk)."""
    data = mesh.export(file_type=mesh_format)
    atomic_write(path, data if isinstance(data, bytes | str) else bytes(data), fsync=False)
    return Path(path)


def build_building_model(
    buildings: Sequence[Any],
    config: BuildingErrorConfig | None = None,
    *,
    seed: int = 0,
    streets: Sequence[Any] = (),
) -> BuildingModel:
    """Derive the erroneous GIS building model from the true buildings.

    Args:
        buildings: true buildings, each with ``id``, ``footprint`` `(N, 2)` (counter-clockwise),
            ``base_z`` and ``height`` (e.g. :class:`geoseg.synth.world.Building`).
        config: the error model (defaults when None).
        seed: random seed; the same seed gives the same model.
        streets: streets with ``centerline`` `(M, 2)`, ``width`` and ``sidewalk_width``; extra
            buildings are kept off them.

    Returns:
        The model, with per-building status and correspondence.
    """
    config = config or BuildingErrorConfig()
    rng = np.random.default_rng([int(seed), 0xB01D])
    true = [_checked_building(i, b) for i, b in enumerate(buildings)]
    n_true = len(true)

    n_missing = 0
    if config.missing_share > 0 and n_true >= 2:
        n_missing = min(n_true - 1, max(1, int(round(config.missing_share * n_true))))
    missing_idx = (
        set(rng.choice(n_true, size=n_missing, replace=False).tolist()) if n_missing else set()
    )
    missing_ids = tuple(sorted(true[i]["id"] for i in missing_idx))

    model: list[ModelBuilding] = []
    for i, b in enumerate(true):
        # Draw for every building (missing or not) so the others do not depend on the share.
        shift, angle = _draw_horizontal_error(b["footprint"], config, rng)
        height = _draw_height(b["height"], config, rng)
        if i in missing_idx:
            continue
        model.append(
            ModelBuilding(
                id=b["id"],
                footprint=_rigid_about_centroid(b["footprint"], shift, angle),
                base_z=b["base_z"],
                height=height,
                status=PRESENT,
                true_id=b["id"],
                shift=shift,
                rotation_rad=angle,
                true_height=b["height"],
            )
        )

    extras = _place_extras(true, streets, config, rng)
    next_id = max((b["id"] for b in true), default=-1) + 1
    for k, (footprint, base_z, height) in enumerate(extras):
        model.append(
            ModelBuilding(
                id=next_id + k,
                footprint=footprint,
                base_z=base_z,
                height=height,
                status=EXTRA,
                true_id=-1,
                shift=np.zeros(2),
                rotation_rad=0.0,
            )
        )
    logger.debug(
        "building model: %d true, %d missing, %d extra", n_true, len(missing_ids), len(extras)
    )
    return BuildingModel(
        buildings=tuple(model),
        missing_ids=missing_ids,
        true_ids=tuple(b["id"] for b in true),
        true_facade_offsets=tuple(
            int(v) for v in np.cumsum([0] + [len(b["footprint"]) for b in true])[:-1]
        ),
        config=config,
        seed=int(seed),
    )


def max_vertex_displacement(true_footprint: np.ndarray, model_footprint: np.ndarray) -> float:
    """Largest distance between corresponding vertices of two `(N, 2)` footprints (metres)."""
    return float(np.linalg.norm(model_footprint - true_footprint, axis=1).max())


def extrude_footprints(
    footprints: Sequence[np.ndarray],
    base_z: Sequence[float],
    heights: Sequence[float],
    *,
    building_ids: Sequence[int] | None = None,
    colors: Sequence[tuple[int, int, int, int]] | None = None,
):
    """Closed prism mesh of 2.5D buildings (walls, flat roof, floor), outward normals.

    Args:
        footprints: per building a `(N_b, 2)` counter-clockwise polygon (may be non-convex).
        base_z: per building the floor altitude.
        heights: per building the height.
        building_ids: per building an id stored in the face attribute ``building_id``.
        colors: per building an RGBA face colour.

    Returns:
        ``trimesh.Trimesh`` with face attributes ``building_id`` and ``plane_id`` (the running
        facade index, as in :attr:`BuildingModel.planes`; -1 for roofs and floors).
    """
    import trimesh

    ids = list(range(len(footprints))) if building_ids is None else list(building_ids)
    vertices, faces, face_bid, face_pid, face_col = [], [], [], [], []
    offset = 0
    plane = 0
    for b, poly in enumerate(footprints):
        poly = np.asarray(poly, dtype=np.float64)
        n = len(poly)
        z0, z1 = float(base_z[b]), float(base_z[b]) + float(heights[b])
        bottom = np.column_stack([poly, np.full(n, z0)])
        top = np.column_stack([poly, np.full(n, z1)])
        vertices += [bottom, top]
        i = np.arange(n)
        j = (i + 1) % n
        walls = np.concatenate([np.column_stack([i, j, n + j]), np.column_stack([i, n + j, n + i])])
        wall_pid = np.concatenate([plane + i, plane + i])
        tris = triangulate_polygon(poly)
        roof = tris + n
        floor = tris[:, ::-1]
        f = np.concatenate([walls, roof, floor]) + offset
        faces.append(f)
        face_bid.append(np.full(len(f), ids[b]))
        face_pid.append(np.concatenate([wall_pid, np.full(2 * len(tris), -1)]))
        if colors is not None:
            face_col.append(np.tile(np.asarray(colors[b], dtype=np.uint8), (len(f), 1)))
        offset += 2 * n
        plane += n
    if not faces:
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=int))
    mesh = trimesh.Trimesh(
        vertices=np.concatenate(vertices), faces=np.concatenate(faces), process=False
    )
    mesh.face_attributes["building_id"] = np.concatenate(face_bid).astype(np.int32)
    mesh.face_attributes["plane_id"] = np.concatenate(face_pid).astype(np.int32)
    if colors is not None:
        mesh.visual.face_colors = np.concatenate(face_col)
    return mesh


def triangulate_polygon(polygon: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation of a simple polygon.

    Args:
        polygon: `(N, 2)` counter-clockwise simple polygon, N >= 3.

    Returns:
        `(N - 2, 3)` int vertex indices, each triangle counter-clockwise.
    """
    check_shape("polygon", polygon, (None, 2))
    n = len(polygon)
    if n < 3:
        raise GeosegError(f"polygon: expected at least 3 vertices, got {n}")
    remaining = list(range(n))
    triangles = []
    guard = 0
    while len(remaining) > 3 and guard < 10 * n * n:
        guard += 1
        m = len(remaining)
        for k in range(m):
            a, b, c = remaining[k - 1], remaining[k], remaining[(k + 1) % m]
            pa, pb, pc = polygon[a], polygon[b], polygon[c]
            if _cross(pb - pa, pc - pb) <= 1e-12:
                continue  # reflex or flat vertex: not an ear
            others = [v for v in remaining if v not in (a, b, c)]
            if others and _points_in_triangle(polygon[others], pa, pb, pc).any():
                continue
            triangles.append((a, b, c))
            remaining.pop(k)
            break
        else:  # degenerate polygon (collinear leftovers): fan the rest
            break
    while len(remaining) >= 3:
        triangles.append((remaining[0], remaining[1], remaining[2]))
        remaining.pop(1)
    return np.asarray(triangles, dtype=np.int64)


def points_in_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test.

    Args:
        points: `(N, 2)` query points.
        polygon: `(M, 2)` polygon vertices.

    Returns:
        `(N,)` bool.
    """
    x, y = points[:, 0:1], points[:, 1:2]
    x0, y0 = polygon[:, 0][None, :], polygon[:, 1][None, :]
    x1, y1 = np.roll(polygon[:, 0], -1)[None, :], np.roll(polygon[:, 1], -1)[None, :]
    straddles = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return (np.count_nonzero(straddles & (x < x_cross), axis=1) % 2) == 1


def distance_to_polylines(points: np.ndarray, polylines: Sequence[np.ndarray]) -> np.ndarray:
    """Distance from points to the nearest segment of any polyline.

    Args:
        points: `(N, 2)` query points.
        polylines: each a `(M_i, 2)` polyline.

    Returns:
        `(N,)` distances (inf when there is no segment).
    """
    segs = [(p[:-1], p[1:]) for p in polylines if len(p) >= 2]
    if not segs or len(points) == 0:
        return np.full(len(points), np.inf)
    a = np.concatenate([s[0] for s in segs])
    b = np.concatenate([s[1] for s in segs])
    return _point_segment_distance(points, a, b).min(axis=1)


def _point_segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`(N, S)` distances from `(N, 2)` points to `(S, 2)`-`(S, 2)` segments."""
    ab = b - a
    denom = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
    ap = points[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("nsk,sk->ns", ap, ab) / denom, 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=2)


def _checked_building(index: int, b: Any) -> dict[str, Any]:
    name = f"buildings[{index}]"
    footprint = np.asarray(getattr(b, "footprint", None), dtype=np.float64)
    check_shape(f"{name}.footprint", footprint, (None, 2))
    check_finite(f"{name}.footprint", footprint)
    if len(footprint) < 3:
        raise GeosegError(f"{name}.footprint: expected >= 3 vertices, got {len(footprint)}")
    if _signed_area(footprint) < 0:
        logger.debug("%s: clockwise footprint reversed", name)
        footprint = footprint[::-1].copy()
    height = float(b.height)
    if not height > 0:
        raise GeosegError(f"{name}.height: expected > 0, got {height}")
    return {"id": int(b.id), "footprint": footprint, "base_z": float(b.base_z), "height": height}


def _draw_horizontal_error(
    footprint: np.ndarray, config: BuildingErrorConfig, rng: np.random.Generator
) -> tuple[np.ndarray, float]:
    bound = config.max_horizontal_error_m
    shift = rng.normal(0.0, config.horizontal_error_std_m, size=2)
    norm = float(np.linalg.norm(shift))
    if norm > bound:
        shift *= bound / norm
        norm = bound
    # A rotation by a about the centroid moves a vertex at radius r by 2 r sin(|a|/2): keep
    # |shift| + 2 r_max sin(|a|/2) <= bound (triangle inequality).
    r_max = float(np.linalg.norm(footprint - footprint.mean(axis=0), axis=1).max())
    budget = max(bound - norm, 0.0)
    a_budget = 2.0 * np.arcsin(min(1.0, budget / (2.0 * r_max))) if r_max > 0 else np.pi
    a_max = min(np.radians(config.max_rotation_deg), a_budget)
    angle = float(rng.uniform(-1.0, 1.0) * a_max)
    return shift, angle


def _rigid_about_centroid(footprint: np.ndarray, shift: np.ndarray, angle: float) -> np.ndarray:
    c = footprint.mean(axis=0)
    cs, sn = np.cos(angle), np.sin(angle)
    rot = np.array([[cs, -sn], [sn, cs]])
    return (footprint - c) @ rot.T + c + shift


def _draw_height(
    true_height: float, config: BuildingErrorConfig, rng: np.random.Generator
) -> float:
    mode_draw = rng.random()
    factor = rng.uniform(*config.height_scale_range)
    storey_offset = int(rng.integers(-config.storey_count_error, config.storey_count_error + 1))
    mode = config.height_error
    if mode == "mixed":
        mode = "scale" if mode_draw < 0.5 else "storeys"
    if mode == "scale":
        height = true_height * factor
    else:
        storeys = max(1, int(round(true_height / config.storey_height_m)) + storey_offset)
        height = storeys * config.storey_height_m
    return float(max(height, config.min_height_m))


def _place_extras(
    true: list[dict[str, Any]],
    streets: Sequence[Any],
    config: BuildingErrorConfig,
    rng: np.random.Generator,
) -> list[tuple[np.ndarray, float, float]]:
    """Rectangles on free ground: off the streets, sidewalks and true buildings."""
    if config.extra_count == 0:
        return []
    all_xy = [b["footprint"] for b in true] + [
        np.asarray(s.centerline, dtype=np.float64) for s in streets
    ]
    if not all_xy:
        logger.warning("no buildings or streets: no extra building placed")
        return []
    pts = np.concatenate(all_xy)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    polylines = [np.asarray(s.centerline, dtype=np.float64) for s in streets]
    clearance = np.array(
        [s.width / 2.0 + s.sidewalk_width + config.street_clearance_m for s in streets]
    )
    heights = np.array([b["height"] for b in true]) if true else np.array([12.0])
    base = np.array([b["base_z"] for b in true]) if true else np.array([0.0])
    obstacles = [b["footprint"] for b in true]
    placed: list[tuple[np.ndarray, float, float]] = []
    u = np.linspace(-0.5, 0.5, 5)
    grid = np.stack(np.meshgrid(u, u), axis=-1).reshape(-1, 2)
    for _ in range(200 * config.extra_count):
        if len(placed) == config.extra_count:
            break
        size = rng.uniform(*config.extra_size_range_m, size=2)
        angle = rng.uniform(0.0, np.pi)
        center = rng.uniform(lo, hi)
        cs, sn = np.cos(angle), np.sin(angle)
        rot = np.array([[cs, -sn], [sn, cs]])
        corners = (np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]) * size) @ rot.T
        footprint = corners + center
        samples = (grid * size) @ rot.T + center
        if polylines and _too_close_to_streets(samples, polylines, clearance):
            continue
        if any(
            points_in_polygon(samples, o).any() or points_in_polygon(o, footprint).any()
            for o in obstacles
        ):
            continue
        idx = int(np.argmin(np.linalg.norm(pts - center, axis=1))) % len(base)
        placed.append((footprint, float(base[idx]), float(rng.choice(heights))))
        obstacles.append(footprint)
    if len(placed) < config.extra_count:
        logger.warning(
            "building model: only %d of %d extra buildings fit on free ground",
            len(placed),
            config.extra_count,
        )
    return placed


def _too_close_to_streets(
    samples: np.ndarray, polylines: list[np.ndarray], clearance: np.ndarray
) -> bool:
    for line, c in zip(polylines, clearance):
        if (distance_to_polylines(samples, [line]) < c).any():
            return True
    return False


def _signed_area(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _cross(u: np.ndarray, v: np.ndarray) -> float:
    return float(u[0] * v[1] - u[1] * v[0])


def _points_in_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    def side(p1, p2):
        return (p2[0] - p1[0]) * (p[:, 1] - p1[1]) - (p2[1] - p1[1]) * (p[:, 0] - p1[0])

    return (side(a, b) >= 0) & (side(b, c) >= 0) & (side(c, a) >= 0)
