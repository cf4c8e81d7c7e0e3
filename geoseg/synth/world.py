"""The procedural city: streets, terrain, buildings, trees, vehicles and street furniture.

A :class:`World` is built from a :class:`WorldConfig` by :func:`build_world`, deterministically:
the same seed and config give a bit-identical city, another seed another city. World frame
metric, right-handed, z up (x east, y north), metres. A city is a jittered street grid with loops
and bends, a smooth sloped terrain whose one surface holds roads, sidewalks and plain ground
(told apart per point by :meth:`World.ground_class`), 2.5D buildings along the streets, two lanes
and parking strips per street, and occluders (trees, parked and moving vehicles, street
furniture); the layout in full: ``docs/synthetic_city.md``.

Instance ids (written by the renderer): facades ``0 .. F-1`` (the :class:`FacadeTable` row),
roofs ``F + building index``, the ground ``F + B``, then one id per tree, static vehicle and
object, then the moving vehicles. :attr:`World.instance_class` maps an id to its class.

Modules: the configs are in :mod:`geoseg.synth.world_config`, the records (buildings, streets,
trees, vehicles, terrain) in :mod:`geoseg.synth.world_records`, the nearest-street queries in
:mod:`geoseg.synth.street_index`, the placement steps in :mod:`geoseg.synth.world_layout` and
the meshing in :mod:`geoseg.synth.world_meshes`. This module holds :class:`World` and
:func:`build_world` and re-exports the public names of the others (``__all__``), so
``geoseg.synth.world.X`` keeps working for every name it had.
"""

from __future__ import annotations

import logging
from functools import cached_property

import numpy as np
import trimesh

from geoseg.classes import ROAD, SIDEWALK, TERRAIN
from geoseg.errors import GeosegError, check_finite, check_shape
from geoseg.synth.street_index import StreetIndex
from geoseg.synth.world_config import (
    PRESETS,
    BuildingConfig,
    OccluderConfig,
    PresetName,
    TerrainConfig,
    WorldConfig,
    _validate,
)
from geoseg.synth.world_layout import (
    _build_buildings,
    _build_occluders,
    _build_street_index,
    _build_streets,
    _build_terrain,
)
from geoseg.synth.world_meshes import (
    SURFACE_CLASS,
    MeshPart,
    SurfaceKind,
    _build_parts,
    concat_parts,
    vehicle_mesh_part,
)
from geoseg.synth.world_records import (
    MATERIALS,
    Building,
    FacadeTable,
    RoadGraph,
    Street,
    Terrain,
    Tree,
    Vehicle,
    _facade_table,
)

__all__ = [
    "MATERIALS",
    "PRESETS",
    "SURFACE_CLASS",
    "Building",
    "BuildingConfig",
    "FacadeTable",
    "MeshPart",
    "OccluderConfig",
    "PresetName",
    "RoadGraph",
    "Street",
    "StreetIndex",
    "SurfaceKind",
    "Terrain",
    "TerrainConfig",
    "Tree",
    "Vehicle",
    "World",
    "WorldConfig",
    "build_world",
    "concat_parts",
    "vehicle_mesh_part",
]

logger = logging.getLogger(__name__)


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


def _inside_convex(poly: np.ndarray, p: np.ndarray) -> bool:
    edges = np.roll(poly, -1, axis=0) - poly
    rel = p - poly
    return bool(np.all(edges[:, 0] * rel[:, 1] - edges[:, 1] * rel[:, 0] >= 0))


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
