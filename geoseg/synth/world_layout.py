"""Where things stand in a new city: streets, terrain, building lots, trees, vehicles, furniture.

The placement steps of :func:`~geoseg.synth.world.build_world`. Each takes the world being
built and the one random generator of the build, draws from it and fills some of the world's
fields with records (:mod:`geoseg.synth.world_records`); the triangles are made afterwards from
those records (:mod:`geoseg.synth.world_meshes`). The steps run in a fixed order and each
draws in a fixed order: changing either changes the city of every seed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from geoseg.errors import ConfigError
from geoseg.synth.street_index import StreetIndex
from geoseg.synth.world_records import (
    MATERIALS,
    Building,
    RoadGraph,
    Street,
    Terrain,
    Tree,
    Vehicle,
)

if TYPE_CHECKING:
    from geoseg.synth.world_config import WorldConfig
    from geoseg.synth.world_meshes import WorldView


def _build_streets(world: WorldView, rng: np.random.Generator) -> None:
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


def _build_terrain(world: WorldView, rng: np.random.Generator) -> None:
    t = world.config.terrain
    wavelengths = rng.uniform(t.min_wavelength, t.max_wavelength, 3)
    angles = rng.uniform(0, 2 * np.pi, 3)
    weights = rng.dirichlet(np.ones(3))
    grades = t.max_grade * weights
    amplitudes = grades * wavelengths / (2 * np.pi)
    k = 2 * np.pi / wavelengths
    wave_vectors = np.stack([k * np.cos(angles), k * np.sin(angles)], axis=1)
    world.terrain = Terrain(amplitudes, wave_vectors, rng.uniform(0, 2 * np.pi, 3))


def _build_street_index(world: WorldView) -> None:
    cfg = world.config
    reach = cfg.street_width / 2 + cfg.sidewalk_width + 2.0 + cfg.buildings.setback_max
    origin = np.floor(world.bounds[0])
    size = np.ceil(world.bounds[1] - origin).astype(int)
    world.street_index = StreetIndex(world.streets, origin, (int(size[1]), int(size[0])), reach)


def _build_buildings(world: WorldView, rng: np.random.Generator) -> None:
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


# Body colours of the vehicles, RGB in [0, 1].
_VEHICLE_PALETTE = np.array(
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

# (kind, xy (2,), heading) of a piece of street furniture
_Furniture = tuple[str, np.ndarray, float]


def _tangent_heading(t: np.ndarray) -> float:
    return float(np.arctan2(t[1], t[0]))


def _build_occluders(world: WorldView, rng: np.random.Generator) -> None:
    """Place trees, vehicles and street furniture (stored as records; meshed later).

    The placements draw from ``rng`` street by street, in a fixed order (per side: trees, parked
    vehicles, shelters and panels; then lamps, signs, moving vehicles): the order is part of
    the city a seed gives."""
    cfg = world.config
    clear = cfg.street_width / 2 + cfg.sidewalk_width + 2.0
    trees: list[Tree] = []
    vehicles: list[Vehicle] = []
    furniture: list[_Furniture] = []
    for si, street in enumerate(world.streets):
        usable = street.length - 2 * clear
        if usable <= 2.0:
            continue
        for side in (1.0, -1.0):
            trees += _kerb_trees(world, street, side, clear, usable, rng)
            vehicles += _parked_vehicles(cfg, street, side, clear, rng)
            furniture += _sidewalk_furniture(cfg, street, side, clear, usable, rng)
        furniture += _lamps(cfg, street, clear, usable)
        furniture += _signs(cfg, street, clear, rng)
        vehicles += _moving_vehicles(cfg, street, si, clear, rng)
    world.trees = trees
    world.vehicles = vehicles
    world.furniture = furniture


def _kerb_trees(
    world: WorldView,
    street: Street,
    side: float,
    clear: float,
    usable: float,
    rng: np.random.Generator,
) -> list[Tree]:
    """Trees near the kerb on one side of ``street`` (on a share of the street sides)."""
    cfg = world.config
    half = cfg.street_width / 2
    sw = cfg.sidewalk_width
    trees: list[Tree] = []
    if rng.random() < cfg.occluder("tree_street_share"):
        n = int(usable // cfg.occluder("tree_spacing")) + 1
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
    return trees


def _parked_vehicles(
    cfg: WorldConfig, street: Street, side: float, clear: float, rng: np.random.Generator
) -> list[Vehicle]:
    """Vehicles parked along the kerb on one side of ``street`` (in the carriageway)."""
    half = cfg.street_width / 2
    length = street.length
    vehicles: list[Vehicle] = []
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
            heading = _tangent_heading(t) + (0.0 if side < 0 else np.pi)
            vehicles.append(
                Vehicle(
                    -1,
                    xy,
                    heading,
                    length_v,
                    width_v,
                    height_v,
                    _VEHICLE_PALETTE[int(rng.integers(len(_VEHICLE_PALETTE)))].copy(),
                )
            )
    return vehicles


def _sidewalk_furniture(
    cfg: WorldConfig,
    street: Street,
    side: float,
    clear: float,
    usable: float,
    rng: np.random.Generator,
) -> list[_Furniture]:
    """A bus shelter and an advertising panel at the back of the sidewalk on one side of
    ``street`` (each on a share of the street sides)."""
    half = cfg.street_width / 2
    sw = cfg.sidewalk_width
    length = street.length
    furniture: list[_Furniture] = []
    for kind, share in (("shelter", "shelter_share"), ("panel", "panel_share")):
        if rng.random() < cfg.occluder(share) and usable > 12.0:
            s = rng.uniform(clear + 4.0, length - clear - 4.0)
            (p,), (t,) = street.point_at(np.array([s]))
            left = np.array([-t[1], t[0]]) * side
            depth_off = half + sw - (1.0 if kind == "shelter" else 0.6)
            heading = _tangent_heading(t) + (0.0 if side > 0 else np.pi)
            furniture.append((kind, p + left * depth_off, heading))
    return furniture


def _lamps(cfg: WorldConfig, street: Street, clear: float, usable: float) -> list[_Furniture]:
    """Street lamps along ``street``, alternating sides (no random draw)."""
    half = cfg.street_width / 2
    furniture: list[_Furniture] = []
    lamp_spacing = cfg.occluder("lamp_spacing")
    n = int(usable // lamp_spacing) + 1
    s_all = clear + (np.arange(n) + 0.5) * (usable / n)
    pts, tans = street.point_at(s_all)
    for i, (p, t) in enumerate(zip(pts, tans)):
        side = 1.0 if i % 2 == 0 else -1.0
        left = np.array([-t[1], t[0]]) * side
        furniture.append(("lamp", p + left * (half + 0.45), _tangent_heading(-left)))
    return furniture


def _signs(
    cfg: WorldConfig, street: Street, clear: float, rng: np.random.Generator
) -> list[_Furniture]:
    """Traffic signs at the ends of ``street`` (right-hand side when arriving at a junction)."""
    half = cfg.street_width / 2
    length = street.length
    furniture: list[_Furniture] = []
    for end in (0, 1):
        if rng.random() < cfg.occluder("sign_share"):
            s = clear - 0.5 if end == 0 else length - clear + 0.5
            (p,), (t,) = street.point_at(np.array([s]))
            side = 1.0 if end == 0 else -1.0
            left = np.array([-t[1], t[0]]) * side
            furniture.append(("sign", p + left * (half + 0.5), _tangent_heading(t * -side)))
    return furniture


def _moving_vehicles(
    cfg: WorldConfig, street: Street, si: int, clear: float, rng: np.random.Generator
) -> list[Vehicle]:
    """Vehicles driving in the lanes of ``street`` (index ``si``)."""
    length = street.length
    vehicles: list[Vehicle] = []
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
                _VEHICLE_PALETTE[int(rng.integers(len(_VEHICLE_PALETTE)))].copy(),
                True,
                si,
                lane,
                s0,
                speed,
            )
        )
    return vehicles
