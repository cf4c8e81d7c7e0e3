"""The procedural city: streets, terrain, buildings, trees, vehicles and street furniture.

A :class:`World` is built from a :class:`WorldConfig` by :func:`build_world`, deterministically:
the same seed and config give a bit-identical city, another seed another city.

Frames and units: world frame metric, right-handed, z up (x east, y north), metres.

Layout:

- **Street network**: a jittered grid of junctions, ``(blocks_x + 1) x (blocks_y + 1)`` nodes,
  linked to their 4 neighbours; a share of the inner links is removed (every junction keeps at
  least 2 streets and the network stays connected, so it always holds loops); a share of the
  streets bends sideways (a half sine), the others are straight. Each street is a
  :class:`Street` (centreline polyline, carriageway width, sidewalk width).
- **Terrain**: a smooth heightfield (a sum of 3 plane waves) with grades of a few per cent,
  :meth:`World.terrain_height`. The ground mesh is one triangulated heightfield (spacing
  ``terrain.mesh_spacing``, within ~1 cm of the true surface); roads, sidewalks and plain terrain
  are the same surface, told apart per point by :meth:`World.ground_class` (distance to the
  nearest centreline), so curved kerbs are exact at any resolution. Sidewalks are flush with the
  road (no raised kerb).
- **Buildings**: rectangular 2.5D lots along both sides of every street (convex, CCW
  footprints), extruded from the terrain (``base_z`` = terrain height at the lowest corner;
  walls reach 1 m below it in the mesh so that no gap shows on slopes) to ``base_z + height``.
- **Carriageway**: two driving lanes (``WorldConfig.lane_offset`` from the centreline) and a
  parking strip along each kerb (``parking_width``); lane markings, parking bays and zebra
  crossings are painted by the renderer's textures.
- **Occluders** (their density comes from the preset unless set explicitly): trees on the
  sidewalks near the kerb (trunk + crown), parked vehicles in the parking strips, moving
  vehicles in the lanes (their position depends on time, see :meth:`World.vehicle_poses`),
  street lamps, traffic signs near junctions, bus shelters and advertising panels on the
  sidewalks.

Instance ids (written by the renderer): facades ``0 .. F-1`` (the :class:`FacadeTable` row),
roofs ``F + building index``, the ground ``F + B``, then one id per tree, static vehicle and
object, then the moving vehicles. :attr:`World.instance_class` maps an id to its class.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from enum import IntEnum
from functools import cache, cached_property
from typing import Literal

import numpy as np
import trimesh

from geoseg.classes import BUILDING, OBJECT, ROAD, SIDEWALK, TERRAIN, VEGETATION, VEHICLE
from geoseg.errors import ConfigError, GeosegError, check_finite, check_shape

logger = logging.getLogger(__name__)

PresetName = Literal["light", "dense_occlusion"]


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------
@dataclass
class TerrainConfig:
    """The smooth heightfield.

    Attributes:
        max_grade: the largest slope (rise over run) the three waves can add up to.
        min_wavelength: shortest wave length, metres.
        max_wavelength: longest wave length, metres.
        mesh_spacing: grid spacing of the ground mesh, metres.
        skirt: how far the ground extends beyond the built area, metres (the horizon).
    """

    max_grade: float = 0.05
    min_wavelength: float = 250.0
    max_wavelength: float = 600.0
    mesh_spacing: float = 5.0
    skirt: float = 150.0


@dataclass
class BuildingConfig:
    """Lots along the streets.

    Attributes:
        frontage_min: smallest facade length along the street, metres.
        frontage_max: largest facade length along the street, metres.
        depth_min: smallest lot depth, metres.
        depth_max: largest lot depth, metres.
        storeys_min: fewest storeys.
        storeys_max: most storeys.
        storey_height: height of an upper storey, metres (ground floor is 1.3x).
        setback_max: largest gap between the sidewalk and the facade, metres.
        gap_share: probability of leaving a gap (3-12 m) before a lot.
    """

    frontage_min: float = 10.0
    frontage_max: float = 24.0
    depth_min: float = 10.0
    depth_max: float = 18.0
    storeys_min: int = 3
    storeys_max: int = 8
    storey_height: float = 3.0
    setback_max: float = 1.5
    gap_share: float = 0.15


@dataclass
class OccluderConfig:
    """Occluder densities; ``None`` takes the preset's value (see :data:`PRESETS`).

    Attributes:
        tree_spacing: distance between trees along a tree-lined street side, metres.
        tree_street_share: share of street sides that are tree-lined.
        parked_share: share of kerb slots (every 6 m) holding a parked vehicle.
        moving_per_100m: moving vehicles per 100 m of street.
        lamp_spacing: distance between street lamps along a street, metres.
        shelter_share: probability that a street side has a bus shelter.
        panel_share: probability that a street side has an advertising panel.
        sign_share: probability that a street end has a traffic sign.
    """

    tree_spacing: float | None = None
    tree_street_share: float | None = None
    parked_share: float | None = None
    moving_per_100m: float | None = None
    lamp_spacing: float | None = None
    shelter_share: float | None = None
    panel_share: float | None = None
    sign_share: float | None = None


PRESETS: dict[str, dict[str, float]] = {
    "light": dict(
        tree_spacing=14.0,
        tree_street_share=0.2,
        parked_share=0.12,
        moving_per_100m=0.3,
        lamp_spacing=40.0,
        shelter_share=0.08,
        panel_share=0.08,
        sign_share=0.3,
    ),
    "dense_occlusion": dict(
        tree_spacing=7.5,
        tree_street_share=0.9,
        parked_share=0.75,
        moving_per_100m=0.8,
        lamp_spacing=22.0,
        shelter_share=0.45,
        panel_share=0.45,
        sign_share=0.7,
    ),
}


@dataclass
class WorldConfig:
    """Everything that defines a synthetic city (with the seed).

    Attributes:
        seed: the random seed; same seed and config give a bit-identical city.
        preset: occluder density preset, ``light`` or ``dense_occlusion``.
        blocks_x: city blocks along x (junctions: ``blocks_x + 1`` per row).
        blocks_y: city blocks along y.
        block_size: distance between neighbouring junctions, metres.
        street_width: carriageway width (2 driving lanes + 2 parking strips), metres.
        parking_width: width of the parking strip along each kerb, metres (0: no parking).
        sidewalk_width: width of each sidewalk, metres.
        node_jitter: random displacement of the junctions, metres.
        curved_street_share: share of the streets that bend.
        curve_amplitude: largest sideways bend of a curved street, metres.
        removed_street_share: share of the inner streets removed (keeps >= 2 per junction).
        terrain: heightfield parameters.
        buildings: lot parameters.
        occluders: occluder densities overriding the preset.
    """

    seed: int = 0
    preset: PresetName = "light"
    blocks_x: int = 4
    blocks_y: int = 3
    block_size: float = 110.0
    street_width: float = 12.0
    sidewalk_width: float = 3.0
    parking_width: float = 2.2
    node_jitter: float = 8.0
    curved_street_share: float = 0.35
    curve_amplitude: float = 10.0
    removed_street_share: float = 0.15
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    buildings: BuildingConfig = field(default_factory=BuildingConfig)
    occluders: OccluderConfig = field(default_factory=OccluderConfig)

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def lane_offset(self) -> float:
        """Distance from the centreline to the middle of a driving lane, metres."""
        return (self.street_width / 2 - self.parking_width) / 2

    def occluder(self, name: str) -> float:
        """The effective occluder density ``name`` (explicit value, else the preset's)."""
        value = getattr(self.occluders, name)
        return float(PRESETS[self.preset][name] if value is None else value)


def _validate(cfg: WorldConfig) -> None:
    def positive(key: str, value: float) -> None:
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            raise ConfigError(f"{key}: expected a number > 0, got {value!r}")

    def share(key: str, value: float | None) -> None:
        if value is not None and not 0.0 <= value <= 1.0:
            raise ConfigError(f"{key}: expected a share in [0, 1], got {value!r}")

    if cfg.preset not in PRESETS:
        raise ConfigError(f"preset: expected one of {sorted(PRESETS)}, got {cfg.preset!r}")
    if isinstance(cfg.seed, bool) or not isinstance(cfg.seed, int) or not 0 <= cfg.seed < 2**63:
        raise ConfigError(f"seed: expected an integer in [0, 2**63), got {cfg.seed!r}")
    for key in ("blocks_x", "blocks_y"):
        value = getattr(cfg, key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(
                f"{key}: expected an integer >= 1 (0 blocks is an empty street network), "
                f"got {value!r}"
            )
    for key in ("block_size", "street_width", "sidewalk_width"):
        positive(key, getattr(cfg, key))
    for key in ("node_jitter", "curve_amplitude"):
        if not getattr(cfg, key) >= 0:
            raise ConfigError(f"{key}: expected a number >= 0, got {getattr(cfg, key)!r}")
    share("curved_street_share", cfg.curved_street_share)
    if not 0 <= cfg.parking_width <= cfg.street_width / 2 - 2.5:
        raise ConfigError(
            f"parking_width: expected a number in [0, street_width / 2 - 2.5 = "
            f"{cfg.street_width / 2 - 2.5:g}] (a driving lane is >= 2.5 m), got {cfg.parking_width}"
        )
    share("removed_street_share", cfg.removed_street_share)
    min_block = cfg.street_width + 2 * cfg.sidewalk_width + 4 * cfg.node_jitter + 10.0
    if cfg.block_size < min_block:
        raise ConfigError(
            f"block_size: expected >= {min_block:g} m for street_width={cfg.street_width:g}, "
            f"sidewalk_width={cfg.sidewalk_width:g}, node_jitter={cfg.node_jitter:g}; "
            f"got {cfg.block_size:g}"
        )
    t = cfg.terrain
    if not 0 <= t.max_grade <= 0.3:
        raise ConfigError(f"terrain.max_grade: expected a number in [0, 0.3], got {t.max_grade}")
    for key in ("min_wavelength", "max_wavelength", "mesh_spacing", "skirt"):
        positive(f"terrain.{key}", getattr(t, key))
    if t.max_wavelength < t.min_wavelength:
        raise ConfigError(
            f"terrain.max_wavelength: expected >= terrain.min_wavelength={t.min_wavelength}, "
            f"got {t.max_wavelength}"
        )
    b = cfg.buildings
    for key in (
        "frontage_min",
        "frontage_max",
        "depth_min",
        "depth_max",
        "storey_height",
        "storeys_min",
        "storeys_max",
    ):
        positive(f"buildings.{key}", getattr(b, key))
    for lo, hi in (("frontage_min", "frontage_max"), ("depth_min", "depth_max")):
        if getattr(b, hi) < getattr(b, lo):
            raise ConfigError(f"buildings.{hi}: expected >= buildings.{lo}, got {getattr(b, hi)}")
    if b.storeys_max < b.storeys_min:
        raise ConfigError(f"buildings.storeys_max: expected >= storeys_min, got {b.storeys_max}")
    if not b.setback_max >= 0:
        raise ConfigError(f"buildings.setback_max: expected >= 0, got {b.setback_max}")
    share("buildings.gap_share", b.gap_share)
    o = cfg.occluders
    for key in ("tree_spacing", "lamp_spacing"):
        value = getattr(o, key)
        if value is not None:
            positive(f"occluders.{key}", value)
    for key in ("tree_street_share", "parked_share", "shelter_share", "panel_share", "sign_share"):
        share(f"occluders.{key}", getattr(o, key))
    if o.moving_per_100m is not None and not o.moving_per_100m >= 0:
        raise ConfigError(f"occluders.moving_per_100m: expected >= 0, got {o.moving_per_100m}")


# --------------------------------------------------------------------------------------------
# Public records
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Building:
    """One 2.5D building (extruded convex footprint).

    Attributes:
        id: index in :attr:`World.buildings`.
        footprint: `(N, 2)` float64 counter-clockwise polygon, world xy, metres.
        base_z: terrain height at the footprint's lowest corner (the floor), metres.
        height: height above ``base_z``, metres.
        material: facade material, one of :data:`MATERIALS`.
        storey_height: upper storey height, metres (the ground floor is 1.3x).
        storeys: number of storeys.
        tint: `(3,)` float RGB multiplier in ~[0.7, 1.3] for this building's colour.
        street: index of the street the building fronts.
    """

    id: int
    footprint: np.ndarray
    base_z: float
    height: float
    material: str
    storey_height: float = 3.0
    storeys: int = 3
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    street: int = -1


MATERIALS: tuple[str, ...] = ("brick", "plaster", "stone", "concrete")


@dataclass
class FacadeTable:
    """One row per facade (one footprint edge), ``F`` rows.

    Attributes:
        building_id: `(F,)` int64 index of the building.
        p0: `(F, 2)` float64 edge start, world xy (CCW order along the footprint).
        p1: `(F, 2)` float64 edge end.
        z_min: `(F,)` float64 bottom (the building's ``base_z``).
        z_max: `(F,)` float64 top (``base_z + height``).
        normal: `(F, 3)` float64 outward unit normal (horizontal).
        facade_id: `(F,)` int64 instance id the renderer writes for the facade's pixels
            (equal to the row index).
    """

    building_id: np.ndarray
    p0: np.ndarray
    p1: np.ndarray
    z_min: np.ndarray
    z_max: np.ndarray
    normal: np.ndarray
    facade_id: np.ndarray

    def __len__(self) -> int:
        return int(self.building_id.shape[0])


@dataclass
class Street:
    """One street between two junctions.

    Attributes:
        centerline: `(M, 2)` float64 polyline, world xy, from ``start_node`` to ``end_node``.
        width: carriageway width, metres (two lanes).
        sidewalk_width: width of each sidewalk, metres.
        start_node: index in :attr:`RoadGraph.nodes`.
        end_node: index in :attr:`RoadGraph.nodes`.
        curved: whether the street bends.
    """

    centerline: np.ndarray
    width: float
    sidewalk_width: float
    start_node: int = -1
    end_node: int = -1
    curved: bool = False

    @cached_property
    def arclength(self) -> np.ndarray:
        """`(M,)` cumulative length along the centreline, metres (computed once)."""
        steps = np.linalg.norm(np.diff(self.centerline, axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(steps)])

    @cached_property
    def length(self) -> float:
        """Centreline length, metres."""
        return float(self.arclength[-1])

    def point_at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points and unit tangents at arc lengths ``s``.

        Args:
            s: `(N,)` arc lengths, metres (clipped to the street).

        Returns:
            `(N, 2)` points and `(N, 2)` unit tangents (direction start -> end).
        """
        arc = self.arclength
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, arc[-1])
        seg = np.clip(np.searchsorted(arc, s, side="right") - 1, 0, len(arc) - 2)
        a, b = self.centerline[seg], self.centerline[seg + 1]
        seg_len = np.maximum(arc[seg + 1] - arc[seg], 1e-9)
        frac = (s - arc[seg]) / seg_len
        tangent = (b - a) / seg_len[:, None]
        return a + frac[:, None] * (b - a), tangent


@dataclass
class RoadGraph:
    """The street network as a graph.

    Attributes:
        nodes: `(K, 2)` float64 junction positions, world xy.
        edges: `(E, 2)` int64 node index pairs; edge ``i`` is :attr:`World.streets` ``[i]``.
    """

    nodes: np.ndarray
    edges: np.ndarray


class SurfaceKind(IntEnum):
    """What a scene triangle is (drives shading; :data:`SURFACE_CLASS` gives its class)."""

    GROUND = 0
    FACADE = 1
    ROOF = 2
    TRUNK = 3
    CROWN = 4
    VEHICLE_BODY = 5
    VEHICLE_GLASS = 6
    VEHICLE_WHEEL = 7
    POLE = 8
    PANEL = 9
    SHELTER_GLASS = 10


# Class of each surface kind; GROUND is resolved per point by World.ground_class.
SURFACE_CLASS = np.array(
    [ROAD, BUILDING, BUILDING, VEGETATION, VEGETATION, VEHICLE, VEHICLE, VEHICLE]
    + [OBJECT, OBJECT, OBJECT],
    dtype=np.uint8,
)


@dataclass
class MeshPart:
    """Triangles of one kind of surface, with per-triangle attributes.

    Attributes:
        vertices: `(V, 3)` float64 world coordinates.
        faces: `(F, 3)` int64 vertex indices.
        kind: `(F,)` uint8 :class:`SurfaceKind`.
        instance: `(F,)` int32 instance id.
    """

    vertices: np.ndarray
    faces: np.ndarray
    kind: np.ndarray
    instance: np.ndarray


@dataclass
class Tree:
    """A street tree: trunk base ``xyz`` `(3,)`, trunk radius/height, crown centre `(3,)` and radii."""

    instance: int
    xyz: np.ndarray
    trunk_radius: float
    trunk_height: float
    crown_center: np.ndarray
    crown_radii: np.ndarray


@dataclass
class Vehicle:
    """A vehicle box model.

    Attributes:
        instance: instance id.
        xy: `(2,)` centre (at ``time_s = 0`` for moving ones), world xy.
        heading: yaw, rad (0 = +x, CCW).
        length: metres.
        width: metres.
        height: metres.
        color: `(3,)` float RGB in [0, 1].
        moving: whether it drives along ``street``.
        street: street index (moving vehicles).
        lane_offset: signed distance to the left of the centreline, metres (moving vehicles).
        s0: arc length at ``time_s = 0`` (moving vehicles).
        speed: signed speed along the street, m/s (moving vehicles; > 0 start -> end).
    """

    instance: int
    xy: np.ndarray
    heading: float
    length: float
    width: float
    height: float
    color: np.ndarray
    moving: bool = False
    street: int = -1
    lane_offset: float = 0.0
    s0: float = 0.0
    speed: float = 0.0


# --------------------------------------------------------------------------------------------
# Terrain
# --------------------------------------------------------------------------------------------
class Terrain:
    """A sum of plane waves ``z = sum_i a_i sin(k_i . xy + phi_i)``.

    Args:
        amplitudes: `(3,)` metres.
        wave_vectors: `(3, 2)` rad/m.
        phases: `(3,)` rad.
    """

    def __init__(self, amplitudes: np.ndarray, wave_vectors: np.ndarray, phases: np.ndarray):
        self.amplitudes = np.asarray(amplitudes, dtype=np.float64)
        self.wave_vectors = np.asarray(wave_vectors, dtype=np.float64)
        self.phases = np.asarray(phases, dtype=np.float64)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """`(N, 2)` world xy -> `(N,)` terrain height, metres."""
        arg = xy @ self.wave_vectors.T + self.phases
        return np.sin(arg) @ self.amplitudes

    def gradient(self, xy: np.ndarray) -> np.ndarray:
        """`(N, 2)` world xy -> `(N, 2)` height gradient (dz/dx, dz/dy)."""
        arg = xy @ self.wave_vectors.T + self.phases
        return (np.cos(arg) * self.amplitudes) @ self.wave_vectors


# --------------------------------------------------------------------------------------------
# Street index: nearest centreline queries
# --------------------------------------------------------------------------------------------
class StreetIndex:
    """Nearest-centreline queries through a 1 m raster of candidate segments.

    Each raster cell keeps the (up to) 4 nearest centreline segments within reach of its centre;
    a query computes exact point-segment distances to those 4.

    Args:
        streets: the streets.
        origin: `(2,)` raster corner, world xy.
        shape: raster `(rows, cols)`; row = y, col = x.
        reach: segments further than this from a cell centre are ignored, metres.
    """

    CELL = 1.0
    K = 4

    def __init__(self, streets: list[Street], origin: np.ndarray, shape: tuple[int, int], reach):
        self.origin = np.asarray(origin, dtype=np.float64)
        self.shape = shape
        self.reach = float(reach)
        a_list, b_list, street_list, s0_list = [], [], [], []
        for i, street in enumerate(streets):
            c = street.centerline
            a_list.append(c[:-1])
            b_list.append(c[1:])
            street_list.append(np.full(len(c) - 1, i))
            s0_list.append(street.arclength[:-1])
        self.seg_a = np.concatenate(a_list)
        self.seg_ab = np.concatenate(b_list) - self.seg_a
        self.seg_len2 = np.maximum((self.seg_ab**2).sum(1), 1e-12)
        self.seg_street = np.concatenate(street_list).astype(np.int64)
        self.seg_s0 = np.concatenate(s0_list)
        self.street_length = np.array([s.length for s in streets])
        rows, cols = shape
        best_d = np.full((rows, cols, self.K), np.inf)
        best_i = np.full((rows, cols, self.K), -1, dtype=np.int64)
        for j in range(len(self.seg_a)):
            a, b = self.seg_a[j], self.seg_a[j] + self.seg_ab[j]
            lo = np.floor((np.minimum(a, b) - self.reach - self.origin) / self.CELL).astype(int)
            hi = np.ceil((np.maximum(a, b) + self.reach - self.origin) / self.CELL).astype(int)
            c0, r0 = np.maximum(lo, 0)
            c1, r1 = min(hi[0], cols), min(hi[1], rows)
            if c1 <= c0 or r1 <= r0:
                continue
            cx = self.origin[0] + (np.arange(c0, c1) + 0.5) * self.CELL
            cy = self.origin[1] + (np.arange(r0, r1) + 0.5) * self.CELL
            px, py = np.meshgrid(cx, cy)
            d = self._dist_to(np.stack([px, py], -1), j)
            d = np.where(d <= self.reach, d, np.inf)
            block_d = best_d[r0:r1, c0:c1]
            block_i = best_i[r0:r1, c0:c1]
            all_d = np.concatenate([block_d, d[..., None]], axis=-1)
            all_i = np.concatenate([block_i, np.full(d.shape + (1,), j)], axis=-1)
            order = np.argsort(all_d, axis=-1, kind="stable")[..., : self.K]
            best_d[r0:r1, c0:c1] = np.take_along_axis(all_d, order, -1)
            best_i[r0:r1, c0:c1] = np.take_along_axis(all_i, order, -1)
        for border in (best_d[0], best_d[-1], best_d[:, 0], best_d[:, -1]):
            border[...] = np.inf  # clipped out-of-raster queries land here: nothing in reach
        self.candidates = np.where(np.isfinite(best_d), best_i, -1)
        # candidates that can be the nearest anywhere in the cell (|d(p) - d(centre)| <= 0.71 m)
        slack = np.sqrt(2.0) * self.CELL + 1e-6
        near = (best_d <= best_d[..., :1] + slack) & np.isfinite(best_d)
        self.n_relevant = near.sum(-1).astype(np.int8)

    def _dist_to(self, p: np.ndarray, j: int) -> np.ndarray:
        rel = p - self.seg_a[j]
        t = np.clip((rel @ self.seg_ab[j]) / self.seg_len2[j], 0.0, 1.0)
        return np.linalg.norm(rel - t[..., None] * self.seg_ab[j], axis=-1)

    def query(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Nearest centreline to each point.

        Args:
            xy: `(N, 2)` world xy.

        Returns:
            dist `(N,)` distance (inf beyond reach), side `(N,)` signed distance (> 0 left of the
            street direction; +-inf beyond reach), s `(N,)` arc length along the street (0 beyond
            reach), street `(N,)` int64 index (-1 beyond reach). Distances are float32-exact
            (~0.1 mm).
        """
        xy = np.asarray(xy)
        n = len(xy)
        if xy.dtype == np.float32:  # renderer hits: stay in float32 (~0.1 mm at 1 km)
            local = xy - self.origin.astype(np.float32)
        else:
            local = (np.asarray(xy, dtype=np.float64) - self.origin).astype(np.float32)
        rows, cols = self.shape
        # the raster's border cells are beyond every street's reach: clip into them
        cx = np.clip(np.floor(local[:, 0] / np.float32(self.CELL)), 0, cols - 1).astype(np.int64)
        cy = np.clip(np.floor(local[:, 1] / np.float32(self.CELL)), 0, rows - 1).astype(np.int64)
        flat = cy * cols + cx
        relevant = self._relevant_flat[flat]
        candidates = self._candidates_flat
        best_d2 = np.full(n, np.inf, dtype=np.float32)
        best_seg = np.zeros(n, dtype=np.int64)
        best_t = np.zeros(n, dtype=np.float32)
        best_cross = np.zeros(n, dtype=np.float32)
        table = self._table
        for k in range(self.K):
            rows_k = np.nonzero(relevant > k)[0]
            if len(rows_k) == 0:
                break
            seg = candidates[flat[rows_k], k]
            row = table[seg]
            rx = local[rows_k, 0] - row[:, 0]
            ry = local[rows_k, 1] - row[:, 1]
            t = np.clip((rx * row[:, 2] + ry * row[:, 3]) * row[:, 4], 0.0, 1.0)
            ox = rx - t * row[:, 2]
            oy = ry - t * row[:, 3]
            d2 = ox * ox + oy * oy
            better = d2 < best_d2[rows_k]
            upd = rows_k[better]
            best_d2[upd] = d2[better]
            best_seg[upd] = seg[better]
            best_t[upd] = t[better]
            best_cross[upd] = (row[:, 2] * ry - row[:, 3] * rx)[better]
        dist = np.sqrt(best_d2).astype(np.float64)
        found = np.isfinite(dist)
        side = np.where(best_cross >= 0, dist, -dist)
        s = np.where(found, self.seg_s0[best_seg] + best_t * self._seg_len[best_seg], 0.0)
        street = np.where(found, self.seg_street[best_seg], -1)
        return dist, side, s, street

    @cached_property
    def _table(self) -> np.ndarray:
        """`(S, 5)` float32 per segment: start (raster-local x, y), direction ab, 1/|ab|^2."""
        a = (self.seg_a - self.origin).astype(np.float32)
        return np.concatenate(
            [a, self.seg_ab.astype(np.float32), (1.0 / self.seg_len2)[:, None].astype(np.float32)],
            axis=1,
        )

    @cached_property
    def _candidates_flat(self) -> np.ndarray:
        return self.candidates.reshape(-1, self.K)

    @cached_property
    def _relevant_flat(self) -> np.ndarray:
        return self.n_relevant.ravel()

    @cached_property
    def _seg_len(self) -> np.ndarray:
        return np.sqrt(self.seg_len2)


# --------------------------------------------------------------------------------------------
# The world
# --------------------------------------------------------------------------------------------
class World:
    """A built city; see the module docstring. Create it with :func:`build_world`.

    Attributes:
        config: the configuration it was built from.
        buildings: the buildings.
        streets: the streets (street ``i`` is road graph edge ``i``).
        road_graph: junctions and streets as a graph.
        trees: the street trees.
        vehicles: parked and moving vehicles.
        furniture: street furniture as ``(kind, xy (2,), heading)``; kind is ``lamp``, ``sign``,
            ``shelter`` or ``panel`` (class object).
        terrain: the heightfield.
        bounds: `(2, 2)` [[xmin, ymin], [xmax, ymax]] of the built area (without the skirt).
        parts: static scene geometry, one :class:`MeshPart` per surface group.
        instance_class: `(I,)` uint8 class of each instance id (ground: ROAD; resolve per
            point with :meth:`ground_class`).
        n_static_instances: ids ``>=`` this belong to moving vehicles.
    """

    def __init__(self, config: WorldConfig):
        self.config = config
        self.buildings: list[Building] = []
        self.streets: list[Street] = []
        self.road_graph = RoadGraph(np.zeros((0, 2)), np.zeros((0, 2), dtype=np.int64))
        self.trees: list[Tree] = []
        self.vehicles: list[Vehicle] = []
        self.furniture: list[tuple[str, np.ndarray, float]] = []
        self.terrain: Terrain
        self.street_index: StreetIndex
        self.bounds = np.zeros((2, 2))
        self.parts: list[MeshPart] = []
        self.instance_class = np.zeros(0, dtype=np.uint8)
        self.n_static_instances = 0
        self._facades: FacadeTable | None = None
        self._renderers: dict = {}  # cache of geoseg.synth.renderer.Renderer by options

    def __getstate__(self) -> dict:
        """Pickle without the renderer cache (embree scenes do not pickle; they rebuild)."""
        state = self.__dict__.copy()
        state["_renderers"] = {}
        return state

    # ---- queries ---------------------------------------------------------------------------
    def terrain_height(self, xy: np.ndarray) -> np.ndarray:
        """True terrain height.

        Args:
            xy: `(N, 2)` world xy, metres.

        Returns:
            `(N,)` float64 heights, metres.
        """
        xy = np.asarray(xy, dtype=np.float64)
        check_shape("xy", xy, (None, 2))
        check_finite("xy", xy)
        return self.terrain.height(xy)

    def terrain_normal(self, xy: np.ndarray) -> np.ndarray:
        """`(N, 2)` world xy -> `(N, 3)` upward unit normals of the true terrain."""
        g = self.terrain.gradient(np.asarray(xy, dtype=np.float64))
        n = np.concatenate([-g, np.ones((len(g), 1))], axis=1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def ground_class(self, xy: np.ndarray) -> np.ndarray:
        """Class of the ground at each point: ROAD, SIDEWALK or TERRAIN.

        Args:
            xy: `(N, 2)` world xy.

        Returns:
            `(N,)` uint8 class ids.
        """
        d = self.street_index.query(np.asarray(xy, dtype=np.float64))[0]
        half = self.config.street_width / 2
        out = np.full(len(d), TERRAIN, dtype=np.uint8)
        out[d < half + self.config.sidewalk_width] = SIDEWALK
        out[d < half] = ROAD
        return out

    def facades(self) -> FacadeTable:
        """The facade table (one row per footprint edge of every building)."""
        if self._facades is None:
            self._facades = _facade_table(self.buildings)
        return self._facades

    def building_at(self, xyz: np.ndarray) -> np.ndarray:
        """Index of the building containing each point (-1 for none).

        Args:
            xyz: `(N, 3)` world points.

        Returns:
            `(N,)` int64 building indices.
        """
        xyz = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        check_shape("xyz", xyz, (None, 3))
        out = np.full(len(xyz), -1, dtype=np.int64)
        if not self.buildings:
            return out
        lo, hi = self._footprint_boxes
        near = np.nonzero(
            (xyz[:, None, 0] >= lo[None, :, 0])
            & (xyz[:, None, 0] <= hi[None, :, 0])
            & (xyz[:, None, 1] >= lo[None, :, 1])
            & (xyz[:, None, 1] <= hi[None, :, 1])
        )
        for p, b in zip(*near):
            bld = self.buildings[b]
            if bld.base_z - 1.0 <= xyz[p, 2] <= bld.base_z + bld.height and _inside_convex(
                bld.footprint, xyz[p, :2]
            ):
                out[p] = b
        return out

    @cached_property
    def _footprint_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.array([b.footprint.min(0) for b in self.buildings])
        hi = np.array([b.footprint.max(0) for b in self.buildings])
        return lo, hi

    def vehicle_poses(self, time_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Positions and headings of all vehicles at ``time_s``.

        Parked vehicles do not move. A moving vehicle drives its lane at constant speed along the
        inner span of its street (away from the junctions) and starts over at the other end of
        the span (no turns at junctions).

        Returns:
            `(V, 2)` centres, world xy, and `(V,)` headings, rad.
        """
        xy, heading = self._parked_poses
        xy, heading = xy.copy(), heading.copy()
        for i in self._mover_ids:
            v = self.vehicles[i]
            street = self.streets[v.street]
            margin = street.width / 2 + street.sidewalk_width + 3.0
            span = max(street.length - 2 * margin, 1.0)
            s = margin + np.mod(v.s0 - margin + v.speed * time_s, span)
            p, t = street.point_at(np.array([s]))
            left = np.array([-t[0, 1], t[0, 0]])
            xy[i] = p[0] + v.lane_offset * left
            heading[i] = np.arctan2(t[0, 1], t[0, 0]) + (np.pi if v.speed < 0 else 0.0)
        return xy, heading

    @cached_property
    def _parked_poses(self) -> tuple[np.ndarray, np.ndarray]:
        xy = np.array([v.xy for v in self.vehicles], dtype=np.float64).reshape(-1, 2)
        return xy, np.array([v.heading for v in self.vehicles], dtype=np.float64)

    @cached_property
    def _mover_ids(self) -> list[int]:
        return [i for i, v in enumerate(self.vehicles) if v.moving]

    def moving_vehicle_mesh(self, time_s: float = 0.0) -> MeshPart:
        """The moving vehicles' triangles at ``time_s`` (empty part when there are none)."""
        movers = [i for i, v in enumerate(self.vehicles) if v.moving]
        xy, heading = self.vehicle_poses(time_s)
        return vehicle_mesh_part(
            self, [self.vehicles[i] for i in movers], xy[movers], heading[movers]
        )

    def meshes(self) -> dict[str, trimesh.Trimesh]:
        """Static scene geometry as trimesh meshes, keyed by surface group name.

        Keys: ``ground``, ``buildings``, ``trees``, ``vehicles`` (parked + moving at t = 0),
        ``objects``. Each mesh carries ``metadata["kind"]`` and ``metadata["instance"]``
        `(F,)` arrays.
        """
        groups = {
            "ground": {SurfaceKind.GROUND},
            "buildings": {SurfaceKind.FACADE, SurfaceKind.ROOF},
            "trees": {SurfaceKind.TRUNK, SurfaceKind.CROWN},
            "vehicles": {SurfaceKind.VEHICLE_BODY, SurfaceKind.VEHICLE_GLASS},
            "objects": {SurfaceKind.POLE, SurfaceKind.PANEL, SurfaceKind.SHELTER_GLASS},
        }
        groups["vehicles"].add(SurfaceKind.VEHICLE_WHEEL)
        part = concat_parts(self.parts + [self.moving_vehicle_mesh(0.0)])
        out = {}
        for name, kinds in groups.items():
            keep = np.isin(part.kind, list(kinds))
            faces = part.faces[keep]
            used, inverse = np.unique(faces, return_inverse=True)
            mesh = trimesh.Trimesh(
                part.vertices[used], inverse.reshape(-1, 3), process=False, validate=False
            )
            mesh.metadata["kind"] = part.kind[keep]
            mesh.metadata["instance"] = part.instance[keep]
            out[name] = mesh
        return out


def concat_parts(parts: list[MeshPart]) -> MeshPart:
    """Concatenate mesh parts into one (face indices shifted)."""
    parts = [p for p in parts if len(p.faces)]
    if not parts:
        return MeshPart(
            np.zeros((0, 3)),
            np.zeros((0, 3), dtype=np.int64),
            np.zeros(0, dtype=np.uint8),
            np.zeros(0, dtype=np.int32),
        )
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return MeshPart(
        np.concatenate([p.vertices for p in parts]),
        np.concatenate([p.faces + o for p, o in zip(parts, offsets)]),
        np.concatenate([p.kind for p in parts]).astype(np.uint8),
        np.concatenate([p.instance for p in parts]).astype(np.int32),
    )


# --------------------------------------------------------------------------------------------
# Building the world
# --------------------------------------------------------------------------------------------
def build_world(config: WorldConfig) -> World:
    """Build the city described by ``config`` (deterministic in ``config.seed``).

    Raises:
        GeosegError: ``config`` is not a :class:`WorldConfig` or describes an impossible city.
    """
    if not isinstance(config, WorldConfig):
        raise GeosegError(f"config: expected a WorldConfig, got {type(config).__name__}")
    _validate(config)
    rng = np.random.default_rng(np.random.SeedSequence([int(config.seed), 20180511]))
    world = World(config)
    _build_streets(world, rng)
    _build_terrain(world, rng)
    _build_street_index(world)
    _build_buildings(world, rng)
    _build_occluders(world, rng)
    _build_parts(world, rng)
    logger.info(
        "built world seed=%d preset=%s: %d streets, %d buildings, %d trees, %d vehicles, "
        "%d triangles",
        config.seed,
        config.preset,
        len(world.streets),
        len(world.buildings),
        len(world.trees),
        len(world.vehicles),
        sum(len(p.faces) for p in world.parts),
    )
    return world


def _build_streets(world: World, rng: np.random.Generator) -> None:
    cfg = world.config
    nx, ny = cfg.blocks_x + 1, cfg.blocks_y + 1
    gx, gy = np.meshgrid(np.arange(nx) * cfg.block_size, np.arange(ny) * cfg.block_size)
    nodes = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float64)
    nodes += rng.uniform(-cfg.node_jitter, cfg.node_jitter, nodes.shape)

    def nid(i: int, j: int) -> int:
        return j * nx + i

    edges = [(nid(i, j), nid(i + 1, j)) for j in range(ny) for i in range(nx - 1)]
    edges += [(nid(i, j), nid(i, j + 1)) for j in range(ny - 1) for i in range(nx)]
    edges = np.array(edges, dtype=np.int64)

    # Remove some inner streets, keeping every junction on >= 2 streets and the graph connected.
    keep = np.ones(len(edges), dtype=bool)
    border = np.array([all(_on_border(int(n), nx, ny) for n in e) for e in edges])
    for e in rng.permutation(len(edges)):
        if border[e] or rng.random() >= cfg.removed_street_share:
            continue
        keep[e] = False
        degree = np.bincount(edges[keep].ravel(), minlength=len(nodes))
        if degree.min() < 2 or not _connected(len(nodes), edges[keep]):
            keep[e] = True
    edges = edges[keep]
    if len(edges) == 0:
        raise ConfigError("blocks_x/blocks_y: the street network is empty")

    streets = []
    for a, b in edges:
        pa, pb = nodes[a], nodes[b]
        length = float(np.linalg.norm(pb - pa))
        curved = bool(rng.random() < cfg.curved_street_share and cfg.curve_amplitude > 0)
        if curved:
            n = max(int(np.ceil(length / 4.0)), 8)
            s = np.linspace(0.0, 1.0, n + 1)
            direction = (pb - pa) / length
            left = np.array([-direction[1], direction[0]])
            amp = min(cfg.curve_amplitude, 0.12 * length) * rng.uniform(0.6, 1.0)
            amp *= rng.choice([-1.0, 1.0])
            line = pa + s[:, None] * (pb - pa) + (amp * np.sin(np.pi * s))[:, None] * left
        else:
            line = np.stack([pa, pb])
        streets.append(
            Street(line, cfg.street_width, cfg.sidewalk_width, int(a), int(b), curved=curved)
        )
    world.streets = streets
    world.road_graph = RoadGraph(nodes, edges)
    margin = cfg.street_width / 2 + cfg.sidewalk_width + cfg.buildings.setback_max
    margin += cfg.buildings.depth_max + 5.0 + cfg.curve_amplitude
    all_pts = np.concatenate([s.centerline for s in streets])
    world.bounds = np.stack([all_pts.min(0) - margin, all_pts.max(0) + margin])


def _on_border(n: int, nx: int, ny: int) -> bool:
    i, j = n % nx, n // nx
    return i in (0, nx - 1) or j in (0, ny - 1)


def _connected(n_nodes: int, edges: np.ndarray) -> bool:
    adjacency: list[list[int]] = [[] for _ in range(n_nodes)]
    for a, b in edges:
        adjacency[a].append(int(b))
        adjacency[b].append(int(a))
    seen = {0}
    stack = [0]
    while stack:
        for m in adjacency[stack.pop()]:
            if m not in seen:
                seen.add(m)
                stack.append(m)
    return len(seen) == n_nodes


def _build_terrain(world: World, rng: np.random.Generator) -> None:
    t = world.config.terrain
    wavelengths = rng.uniform(t.min_wavelength, t.max_wavelength, 3)
    angles = rng.uniform(0, 2 * np.pi, 3)
    weights = rng.dirichlet(np.ones(3))
    grades = t.max_grade * weights
    amplitudes = grades * wavelengths / (2 * np.pi)
    k = 2 * np.pi / wavelengths
    wave_vectors = np.stack([k * np.cos(angles), k * np.sin(angles)], axis=1)
    world.terrain = Terrain(amplitudes, wave_vectors, rng.uniform(0, 2 * np.pi, 3))


def _build_street_index(world: World) -> None:
    cfg = world.config
    reach = cfg.street_width / 2 + cfg.sidewalk_width + 2.0 + cfg.buildings.setback_max
    origin = np.floor(world.bounds[0])
    size = np.ceil(world.bounds[1] - origin).astype(int)
    world.street_index = StreetIndex(world.streets, origin, (int(size[1]), int(size[0])), reach)


def _inside_convex(poly: np.ndarray, p: np.ndarray) -> bool:
    edges = np.roll(poly, -1, axis=0) - poly
    rel = p - poly
    return bool(np.all(edges[:, 0] * rel[:, 1] - edges[:, 1] * rel[:, 0] >= 0))


def _build_buildings(world: World, rng: np.random.Generator) -> None:
    cfg = world.config
    bc = cfg.buildings
    half = cfg.street_width / 2
    clear = half + cfg.sidewalk_width
    origin = world.street_index.origin
    rows, cols = world.street_index.shape
    occ_cell = 0.5
    occupied = np.zeros((2 * rows, 2 * cols), dtype=bool)
    buildings: list[Building] = []
    tints = {
        "brick": (np.array([0.62, 0.32, 0.24]), 0.12),
        "plaster": (np.array([0.85, 0.80, 0.68]), 0.18),
        "stone": (np.array([0.74, 0.70, 0.62]), 0.08),
        "concrete": (np.array([0.62, 0.62, 0.60]), 0.10),
    }
    for si, street in enumerate(world.streets):
        length = street.length
        for side in (1.0, -1.0):
            s = clear + 1.0
            while s < length - clear - 1.0:
                if rng.random() < bc.gap_share:
                    s += rng.uniform(3.0, 12.0)
                    continue
                frontage = rng.uniform(bc.frontage_min, bc.frontage_max)
                frontage = min(frontage, length - clear - 1.0 - s)
                if frontage < bc.frontage_min * 0.6:
                    break
                depth = rng.uniform(bc.depth_min, bc.depth_max)
                setback = rng.uniform(0.0, bc.setback_max)
                (pa, pb), _ = street.point_at(np.array([s, s + frontage]))
                along = (pb - pa) / max(np.linalg.norm(pb - pa), 1e-9)
                left = np.array([-along[1], along[0]]) * side
                front = clear + setback + 0.3
                # the front edge must clear the (possibly curved) street between pa and pb
                mids, _ = street.point_at(np.linspace(s, s + frontage, 5))
                bulge = np.max((mids - pa) @ left)
                front += max(bulge, 0.0)
                q0 = pa + front * left
                q1 = pb + front * left
                q2 = q1 + depth * left
                q3 = q0 + depth * left
                poly = np.stack([q0, q1, q2, q3])
                if side < 0:  # keep counter-clockwise
                    poly = poly[::-1]
                s_next = s + frontage + rng.uniform(0.0, 1.0)
                samples = _polygon_samples(poly, 0.5)
                d = world.street_index.query(samples)[0]
                inner = np.floor((_polygon_samples(_grow(poly, 0.2), 0.25) - origin) / occ_cell)
                inner = inner.astype(int)
                inside = (
                    (inner[:, 0] >= 0)
                    & (inner[:, 0] < occupied.shape[1])
                    & (inner[:, 1] >= 0)
                    & (inner[:, 1] < occupied.shape[0])
                )
                if (
                    np.any(d < clear + 0.25)
                    or not inside.all()
                    or occupied[inner[:, 1], inner[:, 0]].any()
                ):
                    s += 2.5
                    continue
                cells = np.floor((_polygon_samples(poly, 0.25) - origin) / occ_cell).astype(int)
                cells[:, 0] = np.clip(cells[:, 0], 0, occupied.shape[1] - 1)
                cells[:, 1] = np.clip(cells[:, 1], 0, occupied.shape[0] - 1)
                occupied[cells[:, 1], cells[:, 0]] = True
                storeys = int(rng.integers(bc.storeys_min, bc.storeys_max + 1))
                storey_h = bc.storey_height * rng.uniform(0.92, 1.12)
                height = storey_h * (storeys + 0.3) + rng.uniform(0.3, 1.2)
                base_z = float(world.terrain.height(poly).min())
                material = MATERIALS[int(rng.integers(len(MATERIALS)))]
                colour, spread = tints[material]
                tint = np.clip(colour * (1.0 + rng.uniform(-spread, spread, 3)), 0.05, 1.0)
                buildings.append(
                    Building(
                        id=len(buildings),
                        footprint=poly.astype(np.float64),
                        base_z=base_z,
                        height=float(height),
                        material=material,
                        storey_height=float(storey_h),
                        storeys=storeys,
                        tint=tuple(float(c) for c in tint),
                        street=si,
                    )
                )
                s = s_next
    world.buildings = buildings


def _grow(poly: np.ndarray, margin: float) -> np.ndarray:
    centre = poly.mean(0)
    rel = poly - centre
    return centre + rel * (1.0 + margin / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1))


def _polygon_samples(poly: np.ndarray, step: float) -> np.ndarray:
    """Points on the edges and inside a convex quad, spaced ``step``: `(N, 2)`."""
    u = np.linspace(0.0, 1.0, max(int(np.linalg.norm(poly[1] - poly[0]) / step), 2) + 1)
    v = np.linspace(0.0, 1.0, max(int(np.linalg.norm(poly[3] - poly[0]) / step), 2) + 1)
    uu, vv = np.meshgrid(u, v)
    uu, vv = uu.ravel()[:, None], vv.ravel()[:, None]
    return (
        (1 - uu) * (1 - vv) * poly[0]
        + uu * (1 - vv) * poly[1]
        + uu * vv * poly[2]
        + (1 - uu) * vv * poly[3]
    )


def _facade_table(buildings: list[Building]) -> FacadeTable:
    bid, p0, p1, zmin, zmax, normal = [], [], [], [], [], []
    for b in buildings:
        fp = b.footprint
        nxt = np.roll(fp, -1, axis=0)
        edge = nxt - fp
        length = np.linalg.norm(edge, axis=1, keepdims=True)
        out = np.stack([edge[:, 1], -edge[:, 0], np.zeros(len(fp))], axis=1) / np.concatenate(
            [length, length, np.ones_like(length)], axis=1
        )
        out[:, 2] = 0.0
        bid.append(np.full(len(fp), b.id))
        p0.append(fp)
        p1.append(nxt)
        zmin.append(np.full(len(fp), b.base_z))
        zmax.append(np.full(len(fp), b.base_z + b.height))
        normal.append(out)
    if not buildings:
        e = np.zeros(0)
        return FacadeTable(
            e.astype(np.int64),
            np.zeros((0, 2)),
            np.zeros((0, 2)),
            e,
            e,
            np.zeros((0, 3)),
            e.astype(np.int64),
        )
    n = sum(len(x) for x in bid)
    return FacadeTable(
        building_id=np.concatenate(bid).astype(np.int64),
        p0=np.concatenate(p0),
        p1=np.concatenate(p1),
        z_min=np.concatenate(zmin),
        z_max=np.concatenate(zmax),
        normal=np.concatenate(normal),
        facade_id=np.arange(n, dtype=np.int64),
    )


def _build_occluders(world: World, rng: np.random.Generator) -> None:
    """Place trees, vehicles and street furniture (stored as records; meshed later)."""
    cfg = world.config
    half = cfg.street_width / 2
    sw = cfg.sidewalk_width
    clear = half + sw + 2.0
    trees: list[Tree] = []
    vehicles: list[Vehicle] = []
    furniture: list[tuple[str, np.ndarray, float]] = []  # (kind, xy, heading)
    tree_spacing = cfg.occluder("tree_spacing")
    palette = np.array(
        [
            [0.75, 0.75, 0.78],
            [0.12, 0.12, 0.14],
            [0.55, 0.08, 0.08],
            [0.10, 0.22, 0.50],
            [0.90, 0.90, 0.88],
            [0.35, 0.37, 0.40],
            [0.15, 0.35, 0.20],
            [0.80, 0.60, 0.15],
        ]
    )

    def tangent_heading(t: np.ndarray) -> float:
        return float(np.arctan2(t[1], t[0]))

    for si, street in enumerate(world.streets):
        length = street.length
        usable = length - 2 * clear
        if usable <= 2.0:
            continue
        for side in (1.0, -1.0):
            # trees near the kerb
            if rng.random() < cfg.occluder("tree_street_share"):
                n = int(usable // tree_spacing) + 1
                s_all = clear + (np.arange(n) + rng.uniform(0.2, 0.8)) * (usable / n)
                pts, tans = street.point_at(s_all)
                for p, t in zip(pts, tans):
                    if rng.random() < 0.08:
                        continue  # a missing tree
                    left = np.array([-t[1], t[0]]) * side
                    xy = p + left * (half + min(1.0, sw * 0.35)) + rng.normal(0, 0.1, 2)
                    trunk_h = rng.uniform(2.6, 3.6)
                    rh = rng.uniform(2.0, 3.2)
                    rv = rng.uniform(2.2, 3.4)
                    z = float(world.terrain.height(xy[None])[0])
                    centre = np.array([xy[0], xy[1], z + trunk_h + 0.75 * rv])
                    trees.append(
                        Tree(
                            -1,
                            np.array([xy[0], xy[1], z]),
                            rng.uniform(0.14, 0.24),
                            trunk_h,
                            centre,
                            np.array([rh, rh * rng.uniform(0.85, 1.15), rv]),
                        )
                    )
            # parked vehicles along the kerb (in the carriageway)
            slots = np.arange(clear + 3.0, length - clear - 3.0, 6.2)
            if len(slots) and cfg.parking_width > 0:
                pts, tans = street.point_at(slots)
                for p, t in zip(pts, tans):
                    if rng.random() >= cfg.occluder("parked_share"):
                        continue
                    left = np.array([-t[1], t[0]]) * side
                    kind = rng.random()
                    length_v, width_v, height_v = (
                        (rng.uniform(3.9, 4.7), rng.uniform(1.7, 1.85), rng.uniform(1.4, 1.55))
                        if kind < 0.85
                        else (rng.uniform(5.0, 6.2), 2.0, rng.uniform(2.2, 2.6))
                    )
                    kerb_gap = max(cfg.parking_width - width_v, 0.0) / 2 + 0.1
                    xy = p + left * (half - width_v / 2 - kerb_gap) + t * rng.normal(0, 0.3)
                    heading = tangent_heading(t) + (0.0 if side < 0 else np.pi)
                    vehicles.append(
                        Vehicle(
                            -1,
                            xy,
                            heading,
                            length_v,
                            width_v,
                            height_v,
                            palette[int(rng.integers(len(palette)))].copy(),
                        )
                    )
            # bus shelter / advertising panel at the back of the sidewalk
            for kind, share in (("shelter", "shelter_share"), ("panel", "panel_share")):
                if rng.random() < cfg.occluder(share) and usable > 12.0:
                    s = rng.uniform(clear + 4.0, length - clear - 4.0)
                    (p,), (t,) = street.point_at(np.array([s]))
                    left = np.array([-t[1], t[0]]) * side
                    depth_off = half + sw - (1.0 if kind == "shelter" else 0.6)
                    heading = tangent_heading(t) + (0.0 if side > 0 else np.pi)
                    furniture.append((kind, p + left * depth_off, heading))
        # street lamps, alternating sides
        lamp_spacing = cfg.occluder("lamp_spacing")
        n = int(usable // lamp_spacing) + 1
        s_all = clear + (np.arange(n) + 0.5) * (usable / n)
        pts, tans = street.point_at(s_all)
        for i, (p, t) in enumerate(zip(pts, tans)):
            side = 1.0 if i % 2 == 0 else -1.0
            left = np.array([-t[1], t[0]]) * side
            furniture.append(("lamp", p + left * (half + 0.45), tangent_heading(-left)))
        # traffic signs at the street ends (right-hand side when arriving at a junction)
        for end in (0, 1):
            if rng.random() < cfg.occluder("sign_share"):
                s = clear - 0.5 if end == 0 else length - clear + 0.5
                (p,), (t,) = street.point_at(np.array([s]))
                side = 1.0 if end == 0 else -1.0
                left = np.array([-t[1], t[0]]) * side
                furniture.append(("sign", p + left * (half + 0.5), tangent_heading(t * -side)))
        # moving vehicles in the lanes
        n_moving = rng.poisson(cfg.occluder("moving_per_100m") * length / 100.0)
        for _ in range(n_moving):
            direction = rng.choice([-1.0, 1.0])
            speed = direction * rng.uniform(6.0, 12.0)
            s0 = rng.uniform(clear, length - clear)
            lane = -direction * cfg.lane_offset
            length_v = rng.uniform(3.9, 4.7)
            vehicles.append(
                Vehicle(
                    -1,
                    np.zeros(2),
                    0.0,
                    length_v,
                    1.8,
                    rng.uniform(1.4, 1.55),
                    palette[int(rng.integers(len(palette)))].copy(),
                    True,
                    si,
                    lane,
                    s0,
                    speed,
                )
            )
    world.trees = trees
    world.vehicles = vehicles
    world.furniture = furniture


# ---- meshing ---------------------------------------------------------------------------------
_BOX_VERTS = np.array(
    [[x, y, z] for z in (0.0, 1.0) for y in (-0.5, 0.5) for x in (-0.5, 0.5)], dtype=np.float64
)
_BOX_FACES = np.array(
    [
        [0, 2, 1], [1, 2, 3],  # bottom
        [4, 5, 6], [5, 7, 6],  # top
        [0, 1, 4], [1, 5, 4],  # -y
        [2, 6, 3], [3, 6, 7],  # +y
        [0, 4, 2], [2, 4, 6],  # -x
        [1, 3, 5], [3, 7, 5],  # +x
    ],
    dtype=np.int64,
)  # fmt: skip


def _boxes(
    centers: np.ndarray, sizes: np.ndarray, headings: np.ndarray, ups: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Oriented boxes standing on their base centre.

    Args:
        centers: `(n, 3)` base centres, world.
        sizes: `(n, 3)` length (along heading), width, height.
        headings: `(n,)` yaw, rad.
        ups: `(n, 3)` optional unit up vectors (tilt with the terrain).

    Returns:
        vertices `(8n, 3)` and faces `(12n, 3)`.
    """
    n = len(centers)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    local = _BOX_VERTS[None] * sizes[:, None, :]
    fwd = np.stack([np.cos(headings), np.sin(headings), np.zeros(n)], axis=1)
    up = np.tile([0.0, 0.0, 1.0], (n, 1)) if ups is None else ups
    left = np.cross(up, fwd)
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    fwd = np.cross(left, up)
    rot = np.stack([fwd, left, up], axis=2)  # columns
    verts = np.einsum("nij,nkj->nki", rot, local) + centers[:, None, :]
    faces = _BOX_FACES[None] + 8 * np.arange(n)[:, None, None]
    return verts.reshape(-1, 3), faces.reshape(-1, 3)


def _prisms(bases: np.ndarray, radii: np.ndarray, heights: np.ndarray, sides: int = 6):
    """Vertical n-gon prisms (trunks): vertices `(2 s n, 3)`, faces `(3 s n, 3)` (sides + top)."""
    n = len(bases)
    ang = np.arange(sides) * 2 * np.pi / sides
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    verts = np.zeros((n, 2 * sides, 3))
    verts[:, :sides, :2] = bases[:, None, :2] + radii[:, None, None] * ring
    verts[:, sides:, :2] = verts[:, :sides, :2]
    verts[:, :sides, 2] = bases[:, None, 2] - 0.3
    verts[:, sides:, 2] = bases[:, None, 2] + heights[:, None]
    i = np.arange(sides)
    j = (i + 1) % sides
    side_faces = np.concatenate(
        [np.stack([i, j, i + sides], 1), np.stack([j, j + sides, i + sides], 1)]
    )
    top = np.stack([np.full(sides - 2, sides), sides + i[1:-1], sides + i[2:]], axis=1)
    faces = np.concatenate([side_faces, top])
    all_faces = faces[None] + 2 * sides * np.arange(n)[:, None, None]
    return verts.reshape(-1, 3), all_faces.reshape(-1, 3)


def vehicle_mesh_part(world: World, vehicles: list[Vehicle], xy: np.ndarray, heading: np.ndarray):
    """Body, glass cabin and two axle blocks per vehicle, tilted with the terrain.

    Args:
        world: the city (terrain).
        vehicles: the vehicles (``n``).
        xy: `(n, 2)` centres, world xy.
        heading: `(n,)` yaw, rad.

    Returns:
        a :class:`MeshPart` of ``48 n`` triangles.
    """
    if not vehicles:
        return concat_parts([])
    n = len(vehicles)
    z = world.terrain.height(xy)
    ups = world.terrain_normal(xy)
    size = np.array([[v.length, v.width, v.height] for v in vehicles])
    base = np.concatenate([xy, z[:, None]], axis=1)
    fwd = np.stack([np.cos(heading), np.sin(heading), np.zeros(n)], 1)
    inst = np.array([v.instance for v in vehicles], dtype=np.int32)
    # cars: a body (lower 45 %) and a glass cabin on top; vans (> 2 m): a tall body with a
    # windscreen band (glass box slightly wider than the body) at the front
    tall = size[:, 2] > 2.0
    clearance = 0.3
    body_h = np.where(tall, size[:, 2] - 0.45, size[:, 2] * 0.45)
    body_v, body_f = _boxes(
        base + clearance * ups, np.stack([size[:, 0], size[:, 1], body_h], 1), heading, ups
    )
    glass_len = np.where(tall, 0.18, 0.55) * size[:, 0]
    glass_shift = np.where(tall, 0.38, -0.05) * size[:, 0]
    glass_h = np.where(tall, 0.8, size[:, 2] - clearance - body_h)
    glass_z = np.where(tall, clearance + body_h - 0.8, clearance + body_h - 0.02)
    glass_w = size[:, 1] * np.where(tall, 1.02, 0.92)
    cab_v, cab_f = _boxes(
        base + glass_z[:, None] * ups + glass_shift[:, None] * fwd,
        np.stack([glass_len, glass_w, glass_h], 1),
        heading,
        ups,
    )
    axle = np.array([0.33, -0.33])
    wheel_base = base[:, None, :] + axle[None, :, None] * size[:, None, 0:1] * fwd[:, None, :]
    wheel_v, wheel_f = _boxes(
        wheel_base.reshape(-1, 3),
        np.tile(np.array([0.62, 1.0, 0.62]), (2 * n, 1))
        * np.repeat(np.stack([np.ones(n), size[:, 1] + 0.04, np.ones(n)], 1), 2, axis=0),
        np.repeat(heading, 2),
        np.repeat(ups, 2, axis=0),
    )
    parts = [
        MeshPart(
            body_v, body_f, np.full(len(body_f), SurfaceKind.VEHICLE_BODY), np.repeat(inst, 12)
        ),
        MeshPart(cab_v, cab_f, np.full(len(cab_f), SurfaceKind.VEHICLE_GLASS), np.repeat(inst, 12)),
        MeshPart(
            wheel_v, wheel_f, np.full(len(wheel_f), SurfaceKind.VEHICLE_WHEEL), np.repeat(inst, 24)
        ),
    ]
    return concat_parts(parts)


def _ground_part(world: World, instance: int) -> MeshPart:
    t = world.config.terrain
    lo = world.bounds[0] - t.skirt
    hi = world.bounds[1] + t.skirt
    nx = int(np.ceil((hi[0] - lo[0]) / t.mesh_spacing)) + 1
    ny = int(np.ceil((hi[1] - lo[1]) / t.mesh_spacing)) + 1
    xs = lo[0] + np.arange(nx) * t.mesh_spacing
    ys = lo[1] + np.arange(ny) * t.mesh_spacing
    gx, gy = np.meshgrid(xs, ys)
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    verts = np.concatenate([xy, world.terrain.height(xy)[:, None]], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return MeshPart(
        verts,
        faces.astype(np.int64),
        np.full(len(faces), SurfaceKind.GROUND, dtype=np.uint8),
        np.full(len(faces), instance, dtype=np.int32),
    )


def _building_parts(world: World) -> list[MeshPart]:
    table = world.facades()
    n_facades = len(table)
    verts_all, faces_all, kind_all, inst_all = [], [], [], []
    offset = 0
    row = 0
    for b in world.buildings:
        fp = b.footprint
        k = len(fp)
        bottom = np.concatenate([fp, np.full((k, 1), b.base_z - 1.0)], axis=1)
        top = np.concatenate([fp, np.full((k, 1), b.base_z + b.height)], axis=1)
        verts = np.concatenate([bottom, top])
        i = np.arange(k)
        j = (i + 1) % k
        walls = np.stack(
            [np.stack([i, j, j + k], 1), np.stack([i, j + k, i + k], 1)], axis=1
        ).reshape(-1, 3)
        roof = np.stack([np.full(k - 2, k), k + i[1:-1], k + i[2:]], axis=1)
        verts_all.append(verts)
        faces_all.append(np.concatenate([walls, roof]) + offset)
        kind_all.append(
            np.concatenate([np.full(2 * k, SurfaceKind.FACADE), np.full(k - 2, SurfaceKind.ROOF)])
        )
        inst_all.append(np.concatenate([np.repeat(row + i, 2), np.full(k - 2, n_facades + b.id)]))
        offset += 2 * k
        row += k
    if not verts_all:
        return []
    return [
        MeshPart(
            np.concatenate(verts_all),
            np.concatenate(faces_all).astype(np.int64),
            np.concatenate(kind_all).astype(np.uint8),
            np.concatenate(inst_all).astype(np.int32),
        )
    ]


@cache
def _icosphere() -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere (42 vertices, 80 faces): the crown template."""
    ico = trimesh.creation.icosphere(subdivisions=1)
    return np.asarray(ico.vertices, dtype=np.float64), np.asarray(ico.faces, dtype=np.int64)


def _tree_parts(world: World, rng: np.random.Generator) -> list[MeshPart]:
    trees = world.trees
    if not trees:
        return []
    n = len(trees)
    ico_verts, ico_faces = _icosphere()
    inst = np.array([t.instance for t in trees], dtype=np.int32)
    bases = np.array([t.xyz for t in trees])
    radii = np.array([t.trunk_radius for t in trees])
    heights = np.array([t.trunk_height + 0.75 * t.crown_radii[2] for t in trees])
    tv, tf = _prisms(bases, radii, heights)
    bumps = rng.uniform(0.85, 1.12, (n, len(ico_verts), 1))
    cv = (
        ico_verts[None] * bumps * np.array([t.crown_radii for t in trees])[:, None, :]
        + np.array([t.crown_center for t in trees])[:, None, :]
    )
    cf = ico_faces[None] + len(ico_verts) * np.arange(n)[:, None, None]
    return [
        MeshPart(tv, tf, np.full(len(tf), SurfaceKind.TRUNK), np.repeat(inst, len(tf) // n)),
        MeshPart(
            cv.reshape(-1, 3),
            cf.reshape(-1, 3),
            np.full(n * len(ico_faces), SurfaceKind.CROWN),
            np.repeat(inst, len(ico_faces)),
        ),
    ]


def _furniture_parts(world: World, first_instance: int) -> tuple[list[MeshPart], int]:
    """Lamps, signs, shelters and panels as boxes; returns the parts and the next free id."""
    items = world.furniture
    centers, sizes, headings, kinds, insts = [], [], [], [], []
    inst = first_instance

    def add(center, size, heading, kind):
        centers.append(center)
        sizes.append(size)
        headings.append(heading)
        kinds.append(kind)
        insts.append(inst)

    for kind, xy, heading in items:
        z = float(world.terrain.height(xy[None])[0])
        base = np.array([xy[0], xy[1], z - 0.2])
        fwd = np.array([np.cos(heading), np.sin(heading), 0.0])
        side = np.array([-fwd[1], fwd[0], 0.0])
        if kind == "lamp":
            add(base, (0.18, 0.18, 7.4), heading, SurfaceKind.POLE)
            add(base + fwd * 0.8 + [0, 0, 7.2], (1.8, 0.14, 0.14), heading, SurfaceKind.POLE)
            add(base + fwd * 1.6 + [0, 0, 6.95], (0.6, 0.3, 0.22), heading, SurfaceKind.PANEL)
        elif kind == "sign":
            add(base, (0.09, 0.09, 2.9), heading, SurfaceKind.POLE)
            add(base + [0, 0, 2.35], (0.06, 0.75, 0.75), heading, SurfaceKind.PANEL)
        elif kind == "panel":
            for off in (-0.5, 0.5):
                add(base + side * off, (0.1, 0.1, 0.9), heading, SurfaceKind.POLE)
            add(base + [0, 0, 0.9], (0.25, 1.3, 1.9), heading, SurfaceKind.PANEL)
        elif kind == "shelter":
            # heading points from the shelter's back wall towards the street
            add(base - fwd * 0.65, (0.08, 4.0, 2.5), heading, SurfaceKind.SHELTER_GLASS)
            for off in (-1.95, 1.95):
                add(base + side * off, (1.3, 0.08, 2.5), heading, SurfaceKind.SHELTER_GLASS)
                add(base + side * off + fwd * 0.7, (0.1, 0.1, 2.7), heading, SurfaceKind.POLE)
            add(base + [0, 0, 2.7], (1.6, 4.3, 0.12), heading, SurfaceKind.PANEL)
            add(base + side * 2.1 - fwd * 0.3, (0.2, 1.2, 1.8), heading, SurfaceKind.PANEL)
        inst += 1
    if not centers:
        return [], inst
    verts, faces = _boxes(np.array(centers), np.array(sizes, dtype=np.float64), np.array(headings))
    kind_arr = np.repeat(np.array(kinds, dtype=np.uint8), 12)
    inst_arr = np.repeat(np.array(insts, dtype=np.int32), 12)
    return [MeshPart(verts, faces, kind_arr, inst_arr)], inst


def _build_parts(world: World, rng: np.random.Generator) -> None:
    n_facades = len(world.facades())
    n_buildings = len(world.buildings)
    ground_id = n_facades + n_buildings
    classes = [BUILDING] * (n_facades + n_buildings) + [ROAD]
    next_id = ground_id + 1
    for tree in world.trees:
        tree.instance = next_id
        classes.append(VEGETATION)
        next_id += 1
    static = [v for v in world.vehicles if not v.moving]
    for v in static:
        v.instance = next_id
        classes.append(VEHICLE)
        next_id += 1
    parts = [_ground_part(world, ground_id)] + _building_parts(world)
    parts += _tree_parts(world, rng)
    if static:
        xy = np.array([v.xy for v in static])
        parts.append(vehicle_mesh_part(world, static, xy, np.array([v.heading for v in static])))
    furniture, end_id = _furniture_parts(world, next_id)
    parts += furniture
    classes += [OBJECT] * (end_id - next_id)
    next_id = end_id
    world.n_static_instances = next_id
    for v in world.vehicles:
        if v.moving:
            v.instance = next_id
            classes.append(VEHICLE)
            next_id += 1
    world.parts = parts
    world.instance_class = np.array(classes, dtype=np.uint8)
