"""Procedural textures: surface colours computed from world-space hit coordinates.

All functions are vectorised over ``N`` hit points and return float32 RGB albedo in [0, 1]
(display space, the renderer multiplies by the light). Patterns are chosen to be stable at
the usual viewing distances (a few pixels per feature at 320x240 and 10-40 m) and rich in
corners, so that ORB/Harris find features on facades (window frames, storey bands, shop signs,
doors), roads (lane dashes, zebra crossings, repair patches, kerb line), sidewalks (paving
tiles) and trees (leaf clusters).

Randomness comes from an integer hash of cell coordinates (no state, :mod:`geoseg.synth.noise`),
so textures are deterministic and identical from any viewpoint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geoseg.classes import ROAD, SIDEWALK
from geoseg.synth.noise import hash01, hash_u32, random_colours, value_noise

MATERIAL_CODES = {"brick": 0, "plaster": 1, "stone": 2, "concrete": 3}


def _rgb(value: np.ndarray | float, color) -> np.ndarray:
    return np.asarray(value, dtype=np.float32)[..., None] * np.asarray(color, dtype=np.float32)


# --------------------------------------------------------------------------------------------
# Facades
# --------------------------------------------------------------------------------------------
@dataclass
class FacadeStyles:
    """Per-facade texture parameters, ``F`` rows (computed once per world).

    Attributes:
        length: `(F,)` facade length, metres.
        base_z: `(F,)` float64 bottom of the facade, metres.
        material: `(F,)` int :data:`MATERIAL_CODES`.
        storey_height: `(F,)` metres (the ground floor is 1.3x).
        storeys: `(F,)` number of storeys.
        tint: `(F, 3)` wall colour.
        spacing: `(F,)` window column spacing, metres.
        window_width: `(F,)` metres.
        n_cols: `(F,)` window columns.
        u0: `(F,)` start of the window grid along the facade, metres.
        door_col: `(F,)` column of the door.
        frame_rgb: `(F, 3)` window frame colour.
    """

    length: np.ndarray
    base_z: np.ndarray
    material: np.ndarray
    storey_height: np.ndarray
    storeys: np.ndarray
    tint: np.ndarray
    spacing: np.ndarray
    window_width: np.ndarray
    n_cols: np.ndarray
    u0: np.ndarray
    door_col: np.ndarray
    frame_rgb: np.ndarray


def facade_styles(
    length: np.ndarray,
    base_z: np.ndarray,
    material: np.ndarray,
    storey_height: np.ndarray,
    storeys: np.ndarray,
    tint: np.ndarray,
) -> FacadeStyles:
    """Derive the window grid and colours of ``F`` facades (row index = facade id)."""
    key = np.arange(len(length))
    spacing = (2.6 + 1.0 * hash01(key, seed=21)).astype(np.float32)
    width = spacing * (0.42 + 0.2 * hash01(key, seed=22))
    n_cols = np.floor((length - 1.6) / spacing).astype(np.float32)
    u0 = ((length - n_cols * spacing) / 2).astype(np.float32)
    door_col = np.floor(hash01(key, seed=23) * np.maximum(n_cols, 1)).astype(np.float32)
    frame_rgb = np.where(
        (hash01(key, seed=26) < 0.7)[:, None],
        np.float32([0.92, 0.92, 0.9]),
        np.float32([0.3, 0.25, 0.22]),
    ).astype(np.float32)
    return FacadeStyles(
        length=np.asarray(length, dtype=np.float32),
        base_z=np.asarray(base_z, dtype=np.float64),
        material=np.asarray(material, dtype=np.int64),
        storey_height=np.asarray(storey_height, dtype=np.float32),
        storeys=np.asarray(storeys, dtype=np.float32),
        tint=np.asarray(tint, dtype=np.float32).reshape(-1, 3),
        spacing=spacing,
        window_width=width.astype(np.float32),
        n_cols=n_cols,
        u0=u0,
        door_col=door_col,
        frame_rgb=frame_rgb,
    )


def facade_albedo(
    u: np.ndarray, v: np.ndarray, row: np.ndarray, styles: FacadeStyles, window_light: float
) -> tuple[np.ndarray, np.ndarray]:
    """Facade colour from facade-plane coordinates.

    Args:
        u: `(N,)` metres along the facade from its start corner p0.
        v: `(N,)` metres above the facade's base_z.
        row: `(N,)` int facade id (row of ``styles``).
        styles: per-facade parameters.
        window_light: share of windows lit (night), 0..1.

    Returns:
        albedo `(N, 3)` float32 and emissive `(N, 3)` float32 (lit windows).
    """
    u = u.astype(np.float32)
    v = v.astype(np.float32)
    n = len(u)
    h = styles.storey_height[row]
    material = styles.material[row]
    wall = np.ones(n, dtype=np.float32)

    # material patterns (per-cell brightness, stable at the usual distances)
    i = np.nonzero(material == 0)[0]  # brick
    if len(i):
        course = np.floor(v[i] / 0.16)
        cell = np.floor((u[i] + 0.15 * (course % 2)) / 0.3)
        wall[i] = 0.9 + 0.2 * hash01(cell, course, row[i], seed=11)
    i = np.nonzero(material == 1)[0]  # plaster
    if len(i):
        wall[i] = (
            0.92 + 0.14 * value_noise(u[i] / 2.5, v[i] / 2.5, seed=13) - 0.12 * np.exp(-v[i] / 0.8)
        )
    i = np.nonzero(material == 2)[0]  # stone blocks
    if len(i):
        srow = np.floor(v[i] / 0.5)
        us = u[i] + 0.45 * (srow % 2)
        joint = ((v[i] % 0.5) < 0.045) | ((us % 0.9) < 0.045)
        value = 0.88 + 0.22 * hash01(np.floor(us / 0.9), srow, row[i], seed=12)
        wall[i] = np.where(joint, 0.72, value)
    i = np.nonzero(material == 3)[0]  # concrete panels
    if len(i):
        joint = ((v[i] % h[i]) < 0.06) | ((u[i] % 3.0) < 0.06)
        wall[i] = np.where(joint, 0.6, 0.86 + 0.2 * value_noise(u[i] / 1.5, v[i] / 4.0, seed=14))

    # storey bands (cornices) above the ground floor
    ground_h = 1.3 * h
    storeys = styles.storeys[row]
    above = v - ground_h
    band = (above >= 0) & ((above % h) < 0.2) & (above < (storeys - 1) * h)
    wall[band] *= 0.72
    albedo = wall[:, None] * styles.tint[row]

    # window grid
    spacing = styles.spacing[row]
    width = styles.window_width[row]
    col = np.floor((u - styles.u0[row]) / spacing)
    in_cols = (col >= 0) & (col < styles.n_cols[row])
    du = np.abs((u - styles.u0[row]) - (col + 0.5) * spacing)  # from the window axis
    storey = np.floor(above / h)
    dv = above - storey * h
    win_top = 0.9 + h * 0.5
    upper = in_cols & (above >= 0) & (storey < storeys - 1)
    frame = upper & (du < width / 2 + 0.1) & (dv > 0.8) & (dv < win_top + 0.1)
    sill = upper & (du < width / 2 + 0.18) & (dv > 0.62) & (dv <= 0.8)
    glass = frame & (du < width / 2) & (dv > 0.9) & (dv < win_top)
    # ground floor: shop windows, shop sign band and one door per facade
    ground = in_cols & (v < ground_h)
    is_door_col = ground & (col == styles.door_col[row])
    door = is_door_col & (du < 0.65) & (v < 2.3)
    door_frame = is_door_col & (du < 0.8) & (v < 2.45) & ~door
    shop_w = spacing * 0.36
    shop_area = ground & ~is_door_col & (v > 0.33) & (v < 2.72) & (du < shop_w + 0.12)
    shop = shop_area & (du < shop_w) & (v > 0.45) & (v < 2.6)
    sign = in_cols & (v > 2.95) & (v < 3.45) & (du < spacing * 0.45)

    framed = np.nonzero(frame | sill | door_frame | shop_area)[0]
    albedo[framed] = styles.frame_rgb[row[framed]]
    lit_rows = np.zeros(0, dtype=np.int64)
    g = np.nonzero(glass)[0]
    if len(g):
        key = hash01(row[g], col[g], storey[g], seed=25)
        albedo[g] = _rgb(0.1 + 0.22 * key, (0.85, 0.95, 1.1))
        if window_light > 0:
            lit_rows = g[key < window_light]
    sh = np.nonzero(shop)[0]
    if len(sh):
        key = hash01(row[sh], col[sh], seed=25)
        albedo[sh] = _rgb(0.08 + 0.18 * key, (0.9, 0.95, 1.05))
        if window_light > 0.3:
            lit_rows = np.concatenate([lit_rows, sh])
    albedo[door] = np.float32([0.28, 0.17, 0.1])
    sg = np.nonzero(sign)[0]
    if len(sg):
        on = hash01(row[sg], col[sg], seed=24) < 0.5
        sg = sg[on]
        keys = (row[sg], col[sg])
        rgb = np.stack([hash01(*keys, seed=27), hash01(*keys, seed=28), hash01(*keys, seed=29)], 1)
        albedo[sg] = 0.15 + 0.8 * rgb

    emissive = np.zeros((n, 3), dtype=np.float32)
    if len(lit_rows):
        emissive[lit_rows] = np.float32([0.95, 0.8, 0.5])
    return albedo, emissive


def shopfront_albedo(
    u: np.ndarray, v: np.ndarray, row: np.ndarray, styles: FacadeStyles, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Shop-front ground floors (realism option): a fascia board with letter-like marks across
    the facade, display windows with coloured goods behind the glass between pilasters, a stall
    riser, and on some facades a striped awning painted over the windows.

    Args:
        u, v, row: as in :func:`facade_albedo` (only hits on shop-front facades).
        styles: per-facade parameters.
        seed: varies the colours and the awnings.

    Returns:
        ``(inside, albedo)``: `(N,)` bool, True for hits on the ground floor (the only ones
        changed), and `(N, 3)` float32 albedo of those hits (rows where ``inside`` is False are
        undefined).
    """
    u = u.astype(np.float32)
    v = v.astype(np.float32)
    n = len(u)
    ground_h = 1.3 * styles.storey_height[row]
    inside = v < ground_h - 0.15
    albedo = np.zeros((n, 3), dtype=np.float32)
    fascia_bottom = ground_h - 1.0
    spacing = styles.spacing[row]
    rel = u - styles.u0[row]
    col = np.floor(rel / spacing)
    du = np.abs(rel - (col + 0.5) * spacing)
    in_cols = (col >= 0) & (col < styles.n_cols[row])
    fascia_rgb = random_colours(row, seed + 101, 0.75)
    pier_rgb = random_colours(row, seed + 102, 0.3)

    # fascia board and its lettering
    fascia = inside & (v >= fascia_bottom)
    albedo[fascia] = fascia_rgb[fascia]
    lum = 0.3 * fascia_rgb[:, 0] + 0.59 * fascia_rgb[:, 1] + 0.11 * fascia_rgb[:, 2]
    letter_rgb = np.where((lum > 0.45)[:, None], np.float32(0.08), np.float32(0.95))
    text = fascia & (v > fascia_bottom + 0.2) & (v < ground_h - 0.35) & in_cols
    text &= du < spacing * (0.2 + 0.2 * hash01(row, col, seed=seed + 103))
    cell_u = np.floor(rel / 0.11)
    cell_v = np.floor((v - fascia_bottom) / 0.12)
    text &= (hash01(row, cell_u, cell_v, seed=seed + 104) < 0.55) & (cell_u % 4 != 3)
    albedo[text] = letter_rgb[text]

    # below the fascia: pilasters, stall riser, display windows, door
    lower = inside & ~fascia
    pier = lower & (~in_cols | (du > spacing * 0.44))
    riser = lower & ~pier & (v < 0.55)
    glass = lower & ~pier & ~riser
    albedo[pier] = pier_rgb[pier]
    albedo[riser] = 0.6 * pier_rgb[riser]
    goods = random_colours(
        hash_u32(row, np.floor(u / 0.35), np.floor(v / 0.3), seed=seed + 105).view(np.int32),
        seed + 106,
        0.7,
    )
    depth = np.clip((v - 0.55) / np.maximum(fascia_bottom - 0.55, 0.1), 0.0, 1.0)
    reflection = (0.18 + 0.25 * depth)[:, None] * np.float32([0.85, 0.92, 1.0])
    mix = 0.35 + 0.4 * hash01(row, col, seed=seed + 107)[:, None]
    albedo[glass] = (mix * goods * 0.8 + (1 - mix) * reflection)[glass]
    door = glass & (col == styles.door_col[row]) & (du < 0.6) & (v < 2.3)
    albedo[door] = 0.5 * albedo[door] + 0.5 * pier_rgb[door] * 0.5

    # striped awnings over the windows of some facades
    has_awning = hash01(row, seed=seed + 108) < 0.45
    awning = lower & has_awning & (v > fascia_bottom - 0.75) & in_cols & (du < spacing * 0.47)
    stripe = (np.floor(u / 0.3) % 2) == 0
    awning_rgb = random_colours(row, seed + 109, 0.85)
    shade = (0.75 + 0.25 * (v - (fascia_bottom - 0.75)) / 0.75)[:, None]
    on = awning & stripe
    albedo[on] = (awning_rgb * shade)[on]
    off = awning & ~stripe
    albedo[off] = (np.float32([0.92, 0.9, 0.86]) * shade)[off]
    return inside, albedo


def poster_albedo(
    u: np.ndarray, v: np.ndarray, row: np.ndarray, styles: FacadeStyles, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Poster hoardings over ground floors (realism option): a board 2.4-3.2 m high across the
    facade, covered with posters (1.2-3 m wide, one background colour each, mostly pale, with
    bold colour blocks and dark marks: the look of advertising panels).

    Args:
        u, v, row: as in :func:`facade_albedo` (only hits on facades with a hoarding).
        styles: per-facade parameters.
        seed: varies the posters.

    Returns:
        ``(inside, albedo)`` as :func:`shopfront_albedo`: the hits on the hoarding and their
        `(N, 3)` float32 albedo.
    """
    u = u.astype(np.float32)
    v = v.astype(np.float32)
    n = len(u)
    top = np.minimum(2.4 + 0.8 * hash01(row, seed=seed + 121), 1.3 * styles.storey_height[row])
    inside = v < top
    albedo = np.zeros((n, 3), dtype=np.float32)
    board_rgb = random_colours(row, seed + 122, 0.25) * 0.6 + 0.1
    albedo[:] = board_rgb
    width = 1.2 + 1.8 * hash01(row, seed=seed + 123)  # poster width on this facade
    col = np.floor(u / width)
    du = u - col * width
    bottom = 0.3 + 0.3 * hash01(row, seed=seed + 124)
    poster = inside & (du > 0.08) & (du < width - 0.08) & (v > bottom) & (v < top - 0.15)
    poster &= hash01(row, col, seed=seed + 125) < 0.9  # a few bare boards
    key = hash_u32(row, col, seed=seed + 126).view(np.int32)
    pale = hash01(row, col, seed=seed + 127) < 0.6
    background = np.where(
        pale[:, None],
        0.75 + 0.2 * random_colours(key, seed + 128, 0.2),
        random_colours(key, seed + 129, 0.8),
    )
    albedo[poster] = background[poster]
    # bold blocks (pictures, bands) and dark marks (text) on a coarse grid per poster
    cu = np.floor(du / 0.3)
    cv = np.floor(v / 0.25)
    block = poster & (hash01(row, col, cu, cv, seed=seed + 130) < 0.3)
    block_key = hash_u32(row, col, np.floor(cv / 2), seed=seed + 131).view(np.int32)
    albedo[block] = random_colours(block_key, seed + 132, 0.9)[block]
    fine_u = np.floor(du / 0.07)
    fine_v = np.floor(v / 0.09)
    text_band = (cv % 3) == 0
    mark = poster & text_band & (hash01(row, col, fine_u, fine_v, seed=seed + 133) < 0.45)
    albedo[mark] = np.float32([0.08, 0.08, 0.1])
    return inside, albedo.astype(np.float32)


# --------------------------------------------------------------------------------------------
# Ground
# --------------------------------------------------------------------------------------------
def ground_albedo(
    xy: np.ndarray,
    cls: np.ndarray,
    side: np.ndarray,
    s: np.ndarray,
    street_length: np.ndarray,
    half_width: float,
    sidewalk_width: float,
    parking_width: float,
    classes: tuple[int, int, int],
    ground_tint: np.ndarray,
) -> np.ndarray:
    """Road (asphalt, lane markings, parking bays, zebra crossings), sidewalk (paving, kerb)
    and terrain (grass, dirt).

    Args:
        xy: `(N, 2)` world xy of the hits.
        cls: `(N,)` ground class per hit (road / sidewalk / terrain ids given in ``classes``).
        side: `(N,)` signed distance to the nearest centreline (> 0 left), metres (finite).
        s: `(N,)` arc length along that street, metres.
        street_length: `(N,)` that street's length, metres.
        half_width: half the carriageway width, metres.
        sidewalk_width: metres.
        parking_width: width of the parking strip along each kerb, metres.
        classes: the ids of (road, sidewalk, terrain).
        ground_tint: `(3,)` multiplier of grass.

    Returns:
        `(N, 3)` float32 albedo.
    """
    road_id, walk_id, _ = classes
    n = len(xy)
    out = np.empty((n, 3), dtype=np.float32)

    r = np.nonzero(cls == road_id)[0]
    if len(r):
        x, y = xy[r, 0], xy[r, 1]
        sd, sr, length = side[r].astype(np.float32), s[r].astype(np.float32), street_length[r]
        dist = np.abs(sd)
        # asphalt: mottled grey, bright/dark grit, rectangular repair patches
        coarse = value_noise(x / 1.7, y / 1.7, seed=31)
        grit = hash01(np.floor(x / 0.09), np.floor(y / 0.09), seed=32)
        value = 0.30 + 0.08 * coarse
        value += np.where(grit > 0.9, 0.1, 0.0) - np.where(grit < 0.1, 0.06, 0.0)
        s5 = sr % 5.0
        patch = (s5 > 1.0) & (s5 < 4.2) & ((sd % 2.5) > 0.4)
        patch &= hash01(np.floor(sr / 5.0), np.floor(sd / 2.5), seed=33) < 0.12
        value[patch] -= 0.07
        junction_zone = half_width + sidewalk_width + 0.5
        inner = (sr > junction_zone) & (sr < length - junction_zone)
        lane_edge = half_width - parking_width
        marking = (dist < 0.08) & ((sr % 6.0) < 3.0)  # dashed centre line
        marking |= (dist > lane_edge - 0.15) & (dist < lane_edge)  # lane / parking edge
        if parking_width > 0:
            marking |= (dist > lane_edge) & ((sr % 6.2) < 0.12)  # parking bays
        marking &= inner
        zebra_s = np.minimum(sr - junction_zone, length - junction_zone - sr)
        zebra = (zebra_s > 0.3) & (zebra_s < 3.3) & (dist < half_width - 0.4)
        zebra &= (np.floor((sd + half_width) / 0.55) % 2) == 0
        marking |= zebra
        value[marking] = 0.82 + 0.05 * coarse[marking]
        out[r] = value[:, None]

    w = np.nonzero(cls == walk_id)[0]
    if len(w):
        sd = side[w].astype(np.float32)
        tile = hash01(np.floor(sd / 0.6), np.floor(s[w] / 0.6), seed=34)
        paving = 0.52 + 0.18 * tile
        paving[np.abs(sd) < half_width + 0.25] = 0.7  # kerb stones
        out[w] = _rgb(paving, (0.98, 0.96, 0.92))

    o = np.nonzero((cls != walk_id) & (cls != road_id))[0]
    if len(o):
        x, y = xy[o, 0], xy[o, 1]
        grass = value_noise(x / 0.8, y / 0.8, seed=35)
        dirt = value_noise(x / 6.0, y / 6.0, seed=36) > 0.72
        out[o] = _rgb(0.55 + 0.45 * grass, (0.3, 0.45, 0.17)) * ground_tint.astype(np.float32)
        out[o[dirt]] = _rgb(0.5 + 0.2 * grass[dirt], (0.6, 0.5, 0.38))
    return out


def kerb_and_paving(
    albedo: np.ndarray,
    g: np.ndarray,
    cls: np.ndarray,
    side: np.ndarray,
    s: np.ndarray,
    half_width: float,
    kerb_face: float,
    slab_m: float,
    tone: float = 0.6,
) -> None:
    """Kerbs, gutters and slab paving painted on the ground rows ``g`` of ``albedo`` (in place;
    the labels stay: the kerb's face and top are sidewalk, the gutter is road).

    Args:
        albedo: `(M, 3)` float32 albedo of all hits; rows ``g`` `(N,)` are the ground hits.
        g: `(N,)` rows of the ground hits.
        cls: `(N,)` their class (ROAD / SIDEWALK / other).
        side: `(N,)` signed distance to the centreline, metres.
        s: `(N,)` arc length along the street, metres.
        half_width: half the carriageway width (the kerb line), metres.
        kerb_face: brightness of the kerb's face (0.12 m band) relative to its top stone.
        slab_m: paving slab edge, metres (0: keep the tiles).
        tone: mean brightness of the slabs (their hue stays the frame's paving hue).
    """
    dist = np.abs(side).astype(np.float32)
    sr = s.astype(np.float32)
    w = np.nonzero(cls == SIDEWALK)[0]
    if len(w) and slab_m > 0:
        across = dist[w] - half_width
        a_cell, s_cell = np.floor(across / slab_m), np.floor(sr[w] / slab_m)
        joint = (across - a_cell * slab_m < 0.025) | (sr[w] - s_cell * slab_m < 0.025)
        slab = 0.9 + 0.2 * hash01(a_cell, s_cell, np.floor(side[w] / 50.0), seed=37)
        dirt = 0.85 + 0.3 * value_noise(sr[w] / 2.3, across / 2.3, seed=38)
        rows = g[w]
        base = albedo[rows].mean(axis=1, keepdims=True)  # the frame's paving tone and colour
        colour = albedo[rows] / np.maximum(base, 1e-3) * np.float32(tone)
        value = (slab * dirt * np.where(joint, 0.6, 1.0)).astype(np.float32)
        albedo[rows] = colour * value[:, None]
        kerb = across < 0.32
        top = np.float32([0.72, 0.71, 0.68])
        albedo[rows[kerb]] = top
        albedo[rows[kerb & (across < 0.12)]] = top * np.float32(kerb_face)
    elif len(w):
        across = dist[w] - half_width
        top = albedo[g[w][across < 0.12]]
        albedo[g[w][across < 0.12]] = top * np.float32(kerb_face)
    r = np.nonzero((cls == ROAD) & (dist > half_width - 0.35))[0]
    if len(r):
        grime = 0.7 + 0.15 * value_noise(sr[r] / 1.5, dist[r] * 3.0, seed=39)
        grate = ((sr[r] % 11.0) < 0.5) & (dist[r] > half_width - 0.3)
        albedo[g[r]] *= np.where(grate, 0.45, grime)[:, None].astype(np.float32)


def kerb_lines(
    albedo: np.ndarray,
    g: np.ndarray,
    cls: np.ndarray,
    side: np.ndarray,
    street: np.ndarray,
    half_width: float,
    brightness: float,
    seed: int,
) -> None:
    """Paint along the kerbs on the ground rows ``g`` of ``albedo`` (in place; road stays
    road): per street side none, a double yellow line, a single yellow or a single white one.

    Args:
        albedo: `(M, 3)` float32 albedo of all hits; rows ``g`` `(N,)` are the ground hits.
        g: `(N,)` rows of the ground hits.
        cls: `(N,)` their class.
        side: `(N,)` signed distance to the centreline, metres.
        street: `(N,)` index of the nearest street.
        half_width: half the carriageway width (the kerb line), metres.
        brightness: paint brightness (worn < 1).
        seed: keys the style of each street side.
    """
    from_kerb = half_width - np.abs(side).astype(np.float32)
    r = np.nonzero((cls == ROAD) & (from_kerb > 0.15) & (from_kerb < 0.45))[0]
    if len(r) == 0:
        return
    style = hash_u32(street[r], (side[r] > 0).astype(np.int64), seed=seed) % 6  # 0-1: none
    near = from_kerb[r] < 0.25
    far = from_kerb[r] > 0.35
    paint = ((style >= 2) & near) | ((style <= 3) & (style >= 2) & far)  # 2-3: double
    yellow = np.float32([0.85, 0.66, 0.12])
    colour = np.where((style == 5)[:, None], np.float32([0.82, 0.82, 0.8]), yellow)
    rows = g[r[paint]]
    albedo[rows] = colour[paint] * np.float32(brightness)


# --------------------------------------------------------------------------------------------
# Trees, roofs, vehicles, street furniture, sky
# --------------------------------------------------------------------------------------------
def leaf_albedo(X: np.ndarray, leaf_color: np.ndarray) -> np.ndarray:
    """Leaf clusters with dark gaps: `(N, 3)` world hits -> `(N, 3)` float32 albedo."""
    cluster = hash01(*(np.floor(X[:, i] / 0.3) for i in range(3)), seed=41)
    shade = value_noise(X[:, 0] / 0.9 + X[:, 2], X[:, 1] / 0.9 - X[:, 2], seed=42)
    value = np.where(cluster < 0.3, 0.3, 0.8 + 0.8 * cluster * (0.6 + 0.4 * shade))
    return _rgb(value, leaf_color)


def branch_mask(X: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """Bare-crown branches: True where a ray hitting the crown surface at ``X`` stops.

    A sparse voxel pattern (~22 % of 0.14 m voxels per crown layer) stands for the branches of a
    leafless crown; other rays go through and are cast again.

    Args:
        X: `(N, 3)` world hit points on crown surfaces.
        instance: `(N,)` tree instance ids.
    """
    cell = [np.floor(X[:, i] / 0.14) for i in range(3)]
    return hash01(*cell, instance, seed=43) < 0.22


def bark_albedo(X: np.ndarray) -> np.ndarray:
    """`(N, 3)` world hits -> `(N, 3)` float32 bark colour."""
    grain = hash01(np.floor(X[:, 2] / 0.12), np.floor((X[:, 0] + X[:, 1]) / 0.08), seed=44)
    return _rgb(0.75 + 0.5 * grain, (0.32, 0.24, 0.17))


def roof_albedo(X: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """Gravel / tar roofs: `(N, 3)` float32."""
    tone = 0.3 + 0.25 * hash01(instance, seed=51)
    gravel = value_noise(X[:, 0] / 0.7, X[:, 1] / 0.7, seed=52)
    return _rgb(tone * (0.85 + 0.3 * gravel), (1.0, 0.97, 0.93))


def panel_albedo(X: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """Advertising panels, sign plates and lamp heads: bold per-instance stripes/blocks."""
    stripe = np.floor(X[:, 2] * 2.2 + (X[:, 0] + X[:, 1]) * 1.3)
    keys = (instance, stripe)
    rgb = np.stack([hash01(*keys, seed=61), hash01(*keys, seed=62), hash01(*keys, seed=63)], 1)
    return (0.12 + 0.85 * rgb).astype(np.float32)


def sky_color(
    directions_w: np.ndarray,
    zenith: np.ndarray,
    horizon: np.ndarray,
    sun_direction: np.ndarray,
    sun_color: np.ndarray,
    sun_strength: float,
    cloud_cover: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Sky gradient with a sun glow and optional clouds.

    Args:
        directions_w: `(N, 3)` unit ray directions, world frame.
        zenith: `(3,)` RGB overhead.
        horizon: `(3,)` RGB at the horizon.
        sun_direction: `(3,)` unit vector to the sun.
        sun_color: `(3,)` RGB.
        sun_strength: glow strength.
        cloud_cover: 0 (clear) .. 1 (overcast): value-noise clouds, white to grey.
        seed: places the clouds.

    Returns:
        `(N, 3)` float32 RGB.
    """
    elevation = np.clip(directions_w[:, 2], 0.0, 1.0).astype(np.float32)
    t = np.sqrt(elevation)[:, None]
    rgb = horizon.astype(np.float32) * (1 - t) + zenith.astype(np.float32) * t
    if sun_strength > 0:
        d = directions_w
        cos_sun = (
            d[:, 0] * sun_direction[0] + d[:, 1] * sun_direction[1] + d[:, 2] * sun_direction[2]
        )
        cos_sun = np.clip(cos_sun, 0.0, 1.0).astype(np.float32)
        glow = 0.6 * cos_sun**64 + 0.15 * cos_sun**8
        rgb = rgb + (sun_strength * glow)[:, None] * sun_color.astype(np.float32)
    if cloud_cover > 0:
        # clouds on a plane above the camera, seen through the ray's slope
        z = np.maximum(directions_w[:, 2], 0.04).astype(np.float32)
        px = directions_w[:, 0] / z * 2.0 + (seed % 1000)
        py = directions_w[:, 1] / z * 2.0
        fbm = (
            0.5 * value_noise(px, py, seed=seed + 81)
            + 0.3 * value_noise(2.1 * px, 2.1 * py, seed=seed + 82)
            + 0.2 * value_noise(4.3 * px, 4.3 * py, seed=seed + 83)
        )
        edge = 1.0 - cloud_cover
        amount = np.clip((fbm - edge + 0.15) / 0.3, 0.0, 1.0) * 0.95
        tone = 0.72 + 0.25 * value_noise(3 * px, 3 * py, seed=seed + 84)
        cloud = tone[:, None] * np.float32([1.0, 1.0, 1.02])
        rgb = rgb * (1 - amount[:, None]) + cloud * amount[:, None]
    return rgb
