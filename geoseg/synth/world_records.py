"""The records a built city is made of: buildings and their facades, streets, trees, vehicles.

A :class:`~geoseg.synth.world.World` holds these (placed by :mod:`geoseg.synth.world_layout`,
meshed by :mod:`geoseg.synth.world_meshes`); the renderer, the GIS products and the SLAM
experiments read them. They live apart from the builder so that the placement and the
meshing can share them without importing each other. Also here: the :class:`Terrain`
heightfield and :func:`_facade_table`, the facade rows of a list of buildings.

Frames and units: world frame, metric, right-handed, z up (x east, y north), metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np


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
