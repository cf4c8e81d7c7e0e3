"""The city's triangles: surface kinds, :class:`MeshPart`, and meshing the placed records.

Every scene triangle carries a :class:`SurfaceKind` (it drives shading; :data:`SURFACE_CLASS`
gives its class) and an instance id. :func:`_build_parts`, the last step of
:func:`~geoseg.synth.world.build_world`, hands out the instance ids and meshes the ground, the
buildings, the trees, the parked vehicles and the street furniture once;
:func:`vehicle_mesh_part` meshes the moving vehicles again for each frame time, and
:func:`_boxes` also builds the renderer's extra street furniture
(:mod:`geoseg.synth.street_furniture`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from functools import cache
from typing import TYPE_CHECKING, Protocol

import numpy as np
import trimesh

from geoseg.classes import BUILDING, OBJECT, ROAD, VEGETATION, VEHICLE
from geoseg.synth.world_records import Vehicle

if TYPE_CHECKING:
    from geoseg.synth.street_index import StreetIndex
    from geoseg.synth.world_config import WorldConfig
    from geoseg.synth.world_records import (
        Building,
        FacadeTable,
        RoadGraph,
        Street,
        Terrain,
        Tree,
    )


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


class WorldView(Protocol):
    """What the build steps (here and :mod:`geoseg.synth.world_layout`) read and fill of the
    city (:class:`geoseg.synth.world.World` is one): they depend on this, not on the world's
    module, which imports them.

    Attributes:
        config: the configuration.
        bounds: `(2, 2)` [[xmin, ymin], [xmax, ymax]] of the built area.
        terrain: the heightfield.
        streets: the streets (``S``).
        road_graph: junctions and streets as a graph.
        street_index: distance-to-street lookup.
        buildings, trees, vehicles: the placed records.
        furniture: ``(kind, xy (2,), heading)`` per item.
        parts: static scene geometry, one :class:`MeshPart` per surface group.
        instance_class: `(I,)` uint8 class of each instance id.
        n_static_instances: ids ``>=`` this belong to moving vehicles.
    """

    config: WorldConfig
    bounds: np.ndarray
    terrain: Terrain
    streets: list[Street]
    road_graph: RoadGraph
    street_index: StreetIndex
    buildings: list[Building]
    trees: list[Tree]
    vehicles: list[Vehicle]
    furniture: list[tuple[str, np.ndarray, float]]
    parts: list[MeshPart]
    instance_class: np.ndarray
    n_static_instances: int

    def terrain_normal(self, xy: np.ndarray) -> np.ndarray:
        """`(N, 2)` world xy -> `(N, 3)` upward unit normals."""
        ...

    def facades(self) -> FacadeTable:
        """The facade table (one row per footprint edge of every building)."""
        ...


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


def vehicle_mesh_part(
    world: WorldView, vehicles: list[Vehicle], xy: np.ndarray, heading: np.ndarray
):
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


def _ground_part(world: WorldView, instance: int) -> MeshPart:
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


def _building_parts(world: WorldView) -> list[MeshPart]:
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


def _tree_parts(world: WorldView, rng: np.random.Generator) -> list[MeshPart]:
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


def _furniture_parts(world: WorldView, first_instance: int) -> tuple[list[MeshPart], int]:
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


def _build_parts(world: WorldView, rng: np.random.Generator) -> None:
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
