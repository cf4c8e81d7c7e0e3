"""Per-frame street furniture: the thin poles of real streets, labelled ``object``.

The procedural city has a street lamp every 22-40 m and a sign at some street ends; real streets
(CamVid's among them) have many more poles, thin and close to the kerb: sign posts with one or
two plates, traffic lights, lamp posts of other designs, bollards and utility cabinets. The
realism option ``p_furniture`` (:mod:`geoseg.synth.realism`) adds them to a frame: the
:class:`~geoseg.synth.realism.Variation` field ``furniture_spacing`` (mean distance between two
items along one street side, metres; 0: none) and its ``seed`` pick the items, and
:func:`furniture_part` meshes those within :data:`FURNITURE_RADIUS` of the camera. The renderer
casts the frame's rays at them together with the moving vehicles, so labels, depth, normals and
instance ids follow the new geometry (they are ``object``: surface kinds ``POLE`` and
``PANEL``). They cast no shadows (the shadow rays see the static city only).

Placement, per street and side (a Poisson process of rate ``1 / furniture_spacing`` along the
street, keeping clear of the junctions as the city's own furniture does): a share
``kerb_share`` of the items (75 % by default; the Variation field ``furniture_kerb_share``)
stand at the kerb (0.25-0.6 m behind it), the others at the back of the sidewalk, in front of
the facades. The same ``(world, seed, spacing, kerb_share)`` gives the same items whatever the
camera, and the same kinds and sizes whatever ``kerb_share``.

Plates: the sign plates and lamp heads (surface kind ``PANEL``) take the city's advertising
panel shading (bold per-instance stripes and blocks), or with ``furniture_plain_plates``
(:func:`plate_albedo`) one plain sign colour per item.

Instance ids: the items of a frame take ids from ``len(world.instance_class)`` upwards (past
every id of the city, so :attr:`World.instance_class` does not hold them; all are ``object``).
"""

from __future__ import annotations

import numpy as np

from geoseg.synth.noise import hash01
from geoseg.synth.world import World
from geoseg.synth.world_meshes import MeshPart, SurfaceKind, _boxes, concat_parts

FURNITURE_RADIUS = 90.0  # m: items further than this from the camera are not meshed
KINDS = ("sign", "traffic_light", "lamp", "bollards", "cabinet")
_KIND_SHARE = np.array([0.4, 0.12, 0.18, 0.18, 0.12])
# pole paints: grey, dark grey, black, dark green, galvanised silver
_POLE_RGB = np.array(
    [
        [0.42, 0.43, 0.45],
        [0.24, 0.24, 0.25],
        [0.07, 0.07, 0.08],
        [0.1, 0.18, 0.13],
        [0.6, 0.61, 0.6],
    ],
    dtype=np.float32,
)


def furniture_part(
    world: World, seed: int, spacing_m: float, camera_xy: np.ndarray, kerb_share: float = 0.75
) -> MeshPart | None:
    """The street furniture of draw ``seed`` near the camera.

    Args:
        world: the city (streets, terrain, instance ids).
        seed: the draw (:attr:`~geoseg.synth.realism.Variation.seed`).
        spacing_m: mean distance between two items along one street side, metres (> 0).
        camera_xy: `(2,)` camera centre, world xy.
        kerb_share: share of the items at the kerb (the others at the back of the sidewalk).

    Returns:
        boxes of kinds ``POLE`` and ``PANEL`` (instance ids from ``len(world.instance_class)``),
        or None when no item stands within :data:`FURNITURE_RADIUS`.
    """
    camera_xy = np.asarray(camera_xy, dtype=np.float64)[:2]
    cfg = world.config
    half, sw = cfg.street_width / 2, cfg.sidewalk_width
    clear = half + sw + 2.0
    first = len(world.instance_class)
    parts: list[MeshPart] = []
    item = 0
    for si, street in enumerate(world.streets):
        usable = street.length - 2 * clear
        if usable <= 2.0:
            continue
        ss = np.random.SeedSequence([int(seed) % 2**32, si, 5151])
        rng = np.random.default_rng(ss)
        for side in (1.0, -1.0):
            n = rng.poisson(usable / spacing_m)
            s_all = np.sort(clear + usable * rng.random(n))
            draws = rng.random((n, 8))
            if n == 0:
                continue
            pts, tans = street.point_at(s_all)
            left = np.stack([-tans[:, 1], tans[:, 0]], 1) * side
            at_kerb = draws[:, 0] < kerb_share
            depth = np.where(at_kerb, half + 0.25 + 0.35 * draws[:, 1], half + sw - 0.45)
            xy = pts + left * depth[:, None]
            near = np.linalg.norm(xy - camera_xy, axis=1) < FURNITURE_RADIUS
            for k in np.nonzero(near)[0]:
                kind = KINDS[int(np.searchsorted(np.cumsum(_KIND_SHARE), draws[k, 2] * 0.9999))]
                part = _item(world, kind, xy[k], tans[k], left[k], draws[k, 3:], first + item)
                parts.append(part)
                item += 1
    return concat_parts(parts) if parts else None


def _item(
    world: World,
    kind: str,
    xy: np.ndarray,
    tangent: np.ndarray,
    left: np.ndarray,
    u: np.ndarray,
    instance: int,
) -> MeshPart:
    """One item's boxes: ``xy`` `(2,)` its foot, ``tangent`` / ``left`` `(2,)` the street's
    direction and the unit vector from the street towards this side, ``u`` `(5,)` uniform
    draws for its sizes."""
    z = float(world.terrain.height(xy[None])[0]) - 0.2
    base = np.array([xy[0], xy[1], z])
    along = float(np.arctan2(tangent[1], tangent[0]))  # plates facing the traffic
    to_road = np.array([-left[0], -left[1], 0.0])
    boxes: list[tuple[np.ndarray, tuple[float, float, float], float, SurfaceKind]] = []

    def add(center, size, heading=along, kind=SurfaceKind.POLE):
        boxes.append((np.asarray(center, dtype=np.float64), size, heading, kind))

    if kind == "sign":
        width = 0.06 + 0.05 * u[0]
        height = 2.4 + 1.3 * u[1]
        add(base, (width, width, height))
        heading = along if u[2] < 0.7 else along + np.pi / 2  # most face the traffic
        plates = 1 if u[3] < 0.6 else 2
        for i in range(plates):
            w = 0.45 + 0.6 * hash01(np.array([instance]), seed=11 + i)[0]
            h = 0.3 + 0.5 * hash01(np.array([instance]), seed=21 + i)[0]
            top = height + 0.2 - i * (h + 0.15)
            add(base + [0, 0, top - h], (0.04, w, h), heading, SurfaceKind.PANEL)
    elif kind == "traffic_light":
        height = 2.8 + 1.2 * u[0]
        add(base, (0.12, 0.12, height))
        add(base + [0, 0, height - 1.0], (0.3, 0.34, 0.95), along)  # the dark signal head
        if u[1] < 0.4:  # a second head on the road side
            add(base + to_road * 0.3 + [0, 0, height - 2.2], (0.28, 0.3, 0.85), along)
    elif kind == "lamp":
        height = 5.5 + 3.5 * u[0]
        width = 0.12 + 0.1 * u[1]
        add(base, (width, width, height))
        heading = float(np.arctan2(to_road[1], to_road[0]))
        arm = 0.4 + 1.4 * u[2]
        add(base + to_road * arm / 2 + [0, 0, height - 0.1], (arm, 0.1, 0.1), heading)
        add(
            base + to_road * arm + [0, 0, height - 0.25],
            (0.55, 0.28, 0.2),
            heading,
            SurfaceKind.PANEL,
        )
    elif kind == "bollards":
        count = 2 + int(4 * u[0])
        height = 0.75 + 0.35 * u[1]
        width = 0.12 + 0.08 * u[2]
        t3 = np.array([tangent[0], tangent[1], 0.0])
        for i in range(count):
            add(base + t3 * (1.3 * (i - (count - 1) / 2)), (width, width, height))
    else:  # a utility cabinet
        size = (0.35 + 0.25 * u[0], 0.5 + 0.5 * u[1], 1.0 + 0.5 * u[2])
        add(base, size, along + np.pi / 2)
    centers = np.array([b[0] for b in boxes])
    sizes = np.array([b[1] for b in boxes], dtype=np.float64)
    headings = np.array([b[2] for b in boxes], dtype=np.float64)
    verts, faces = _boxes(centers, sizes, headings)
    kinds = np.repeat(np.array([b[3] for b in boxes], dtype=np.uint8), 12)
    return MeshPart(verts, faces, kinds, np.full(len(faces), instance, dtype=np.int32))


# plain sign plate colours: white, sign blue, red, yellow, green, brown, mid grey, black
_PLATE_RGB = np.array(
    [
        [0.85, 0.85, 0.83],
        [0.06, 0.2, 0.55],
        [0.62, 0.08, 0.07],
        [0.85, 0.7, 0.08],
        [0.05, 0.33, 0.18],
        [0.35, 0.2, 0.1],
        [0.45, 0.46, 0.47],
        [0.06, 0.06, 0.07],
    ],
    dtype=np.float32,
)


def plate_albedo(instance: np.ndarray, first: int, albedo: np.ndarray) -> np.ndarray:
    """`(N, 3)` float32 plate colours: the frame's furniture (``instance >= first``) in one
    plain sign colour per item, the city's own panels keeping ``albedo`` `(N, 3)`."""
    instance = np.asarray(instance)
    out = np.array(albedo, dtype=np.float32, copy=True).reshape(len(instance), 3)
    own = instance >= first
    pick = (hash01(instance[own], seed=41) * len(_PLATE_RGB)).astype(np.int64)
    out[own] = _PLATE_RGB[np.minimum(pick, len(_PLATE_RGB) - 1)]
    return out


def pole_albedo(instance: np.ndarray, first: int, albedo: np.ndarray) -> np.ndarray:
    """`(N, 3)` float32 pole colours: the frame's furniture (``instance >= first``) painted grey,
    black, dark green or silver per item, the city's own poles keeping ``albedo`` `(3,)`."""
    instance = np.asarray(instance)
    out = np.broadcast_to(np.asarray(albedo, dtype=np.float32), (len(instance), 3)).copy()
    own = instance >= first
    pick = (hash01(instance[own], seed=31) * len(_POLE_RGB)).astype(np.int64)
    out[own] = _POLE_RGB[np.minimum(pick, len(_POLE_RGB) - 1)]
    return out
