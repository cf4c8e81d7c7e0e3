"""Leafless crowns: rays through them, their branches drawn as voxels or as limbs.

Under a condition without leaves (``winter``, or the realism option ``p_bare_trees``) a ray that
meets a crown goes on through it unless it meets a branch (:func:`trace_crowns`). By default
the branches are a sparse voxel pattern on the crown's surfaces
(:func:`geoseg.synth.textures.branch_mask`): against the sky it reads as a speckled ball. A real
leafless tree reads as lines: a stem, a few thick limbs that fan out upwards from it, thinner
branches forking off them and twigs at the rim. With the realism option ``p_limbs``
(:mod:`geoseg.synth.realism`) each crown gets such a skeleton (:func:`crown_skeleton`, drawn
from the tree's instance id, so every frame sees the same tree) and a ray that enters the crown
is tested against it over its whole path inside (:meth:`CrownLimbs.intersect`):

- a capsule at least as wide as the ray's pixel (at the capsule's distance) stops the ray: it
  is that limb's hit (bark, labelled ``vegetation``);
- a thinner one covers the share ``radius / half pixel`` of the pixel: the ray goes on and the
  renderer veils what it finds behind with the twigs' colour (:func:`veil`), a line about one
  pixel wide instead of broken dots.

Capsules are straight segments with one radius each; the test is the ray's closest approach to
each segment of its tree (``(rays, segments)`` arrays, tree by tree).

Twigs finer than a pixel (``p_twigs``) veil what lies behind a bare crown. Behind voxel
branches the veil is flat, the same share per crown surface (:func:`haze_cover`). Behind limbs it
is a twig mass (:func:`mass_cover`): its optical depth grows with the ray's path through the
crown (dense across the middle, thin at the rim, as a real crown's twigs overlap) and varies
from clump to clump and twig to twig (:func:`twig_speckle`), so a crown against the sky reads as
a speckled mass with sky showing through, not as a uniform grey.

With the label option ``bare_crown_label`` a crown's pixels are ``vegetation``: its whole
silhouette, or with ``crown_label_cover`` only where branches stop the ray, the sky shows
through, or the twigs and thin limbs cover most of the pixel (:func:`labelled_crown`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geoseg.synth.conditions import Condition
from geoseg.synth.noise import hash01
from geoseg.synth.textures import branch_mask
from geoseg.synth.world_meshes import SurfaceKind
from geoseg.synth.world_records import Tree

__all__ = [
    "CrownLimbs",
    "LimbHits",
    "crown_skeleton",
    "trace_crowns",
    "fine_twig_cover",
    "haze_cover",
    "labelled_crown",
    "mass_cover",
    "twig_colour",
    "twig_speckle",
    "veil",
    "veil_crowns",
]

#: ``(count range, radius factor of the parent, end at this share of the crown radius)`` per
#: level below the stem: limbs off the stem, branches off limbs, twigs off branches
_LEVELS = (((5, 9), 0.45, (0.62, 0.86)), ((2, 4), 0.5, (0.78, 0.95)), ((2, 3), 0.45, (0.9, 1.0)))
#: lattice spacings (metres) of the twig mass's variation: clumps of twigs (smooth), twigs
_CLUMP_CELL, _TWIG_CELL = 0.4, 0.05
#: mean length of a chord through the unit sphere over its projected disc: a twig mass of this
#: normalised path length veils as much as the flat haze's two crown surfaces
_MEAN_CHORD = 4.0 / 3.0


def _on_shell(tree: Tree, azimuth: float, elevation: float, share: float) -> np.ndarray:
    """`(3,)` the point at ``share`` of the crown's radius from its centre in a direction."""
    d = np.array(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ]
    )
    return np.asarray(tree.crown_center, np.float64) + share * np.asarray(tree.crown_radii) * d


def crown_skeleton(tree: Tree) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The capsules of one leafless crown, deterministic in ``tree.instance``.

    A stem from the trunk's top to above the crown's centre; limbs from points along the stem
    out and up towards the crown's surface, evenly spread in azimuth; branches forking off each
    limb, turned sideways; twigs forking off each branch to the crown's rim.

    Returns:
        ``(a, b, radius)``: `(S, 3)` segment starts and ends (world, metres) and `(S,)` radii.
    """
    rng = np.random.default_rng([int(tree.instance), 977])
    base = np.asarray(tree.xyz, np.float64) + [0.0, 0.0, tree.trunk_height]
    top = np.asarray(tree.crown_center, np.float64) + [0.0, 0.0, 0.45 * tree.crown_radii[2]]
    top[:2] += rng.normal(0.0, 0.15, 2)
    a, b, r = [base], [top], [0.7 * tree.trunk_radius]
    # parents: (start point, end point, radius, azimuth, elevation) of the level above
    parents = [(base, top, 0.7 * tree.trunk_radius, rng.uniform(0, 2 * np.pi), np.pi / 2)]
    for level, ((lo, hi), radius_factor, (near, far)) in enumerate(_LEVELS):
        children = []
        for p0, p1, p_radius, p_az, p_el in parents:
            n = int(rng.integers(lo, hi + 1))
            for i in range(n):
                if level == 0:  # limbs: spread around the stem, out and up
                    az = p_az + 2 * np.pi * (i + rng.uniform(-0.3, 0.3)) / n
                    el = rng.uniform(np.radians(5), np.radians(60))
                    fork = rng.uniform(0.0, 0.55)
                else:  # turned sideways from the parent, on alternate sides
                    side = 1.0 if i % 2 == 0 else -1.0
                    az = p_az + side * rng.uniform(0.3, 0.9)
                    el = np.clip(p_el + rng.uniform(-0.35, 0.35), np.radians(-20), np.radians(80))
                    fork = rng.uniform(0.35, 0.8)
                start = p0 + fork * (p1 - p0)
                end = _on_shell(tree, az, el, rng.uniform(near, far))
                radius = p_radius * radius_factor * rng.uniform(0.85, 1.15)
                a.append(start)
                b.append(end)
                r.append(radius)
                children.append((start, end, radius, az, el))
        parents = children
    return np.array(a), np.array(b), np.array(r)


@dataclass
class LimbHits:
    """What the limbs of their crowns do to some rays (``M`` rays).

    Attributes:
        distance: `(M,)` ray parameter of the first capsule that stops the ray (inf: none).
        normal: `(M, 3)` float32 unit normal of that capsule at the hit (zeros where none).
        cover: `(M,)` float32 share of the pixel the thinner capsules in front cover.
        path: `(M,)` length of the ray's path through the crown up to that capsule or the
            crown's far side, measured with the crown scaled to the unit sphere (a path
            across the middle: 2): how much of the twig mass it goes through.
    """

    distance: np.ndarray
    normal: np.ndarray
    cover: np.ndarray
    path: np.ndarray


class CrownLimbs:
    """The skeletons of a world's trees, built on first use and kept.

    Args:
        trees: the world's trees (``Tree.instance`` is what the ray cast reports).
    """

    def __init__(self, trees: list[Tree]) -> None:
        self._trees = {int(t.instance): t for t in trees}
        self._skeletons: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def skeleton(self, instance: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`crown_skeleton` of the tree ``instance``."""
        if instance not in self._skeletons:
            self._skeletons[instance] = crown_skeleton(self._trees[instance])
        return self._skeletons[instance]

    def intersect(
        self,
        origins: np.ndarray,
        dirs: np.ndarray,
        instance: np.ndarray,
        distance_so_far: np.ndarray,
        pixel_angle: float,
    ) -> LimbHits:
        """Rays entering crowns against those crowns' limbs.

        Args:
            origins: `(M, 3)` where each ray enters its crown.
            dirs: `(M, 3)` unit ray directions.
            instance: `(M,)` the crown's tree instance.
            distance_so_far: `(M,)` the camera's distance to ``origins`` (pixel footprint).
            pixel_angle: the angle one pixel spans, radians (``1 / f_x``).

        Returns:
            A :class:`LimbHits`, distances from ``origins``.
        """
        m = len(origins)
        out = LimbHits(
            np.full(m, np.inf), np.zeros((m, 3), np.float32), np.zeros(m, np.float32), np.zeros(m)
        )
        for tree in np.unique(instance):
            rows = np.nonzero(instance == tree)[0]
            a, b, radius = self.skeleton(int(tree))
            s, dist, closest = _closest_approach(origins[rows], dirs[rows], a, b)
            half_pixel = 0.5 * pixel_angle * (distance_so_far[rows, None] + s)
            solid = (radius >= half_pixel) & (dist < radius)
            enter = np.where(solid, s - np.sqrt(np.maximum(radius**2 - dist**2, 0.0)), np.inf)
            first = np.argmin(enter, axis=1)
            hit_s = enter[np.arange(len(rows)), first]
            thin = (radius < half_pixel) & (dist < half_pixel) & (s < hit_s[:, None])
            share = np.where(thin, radius / np.maximum(half_pixel, 1e-9), 0.0)
            out.cover[rows] = 1.0 - np.prod(1.0 - share, axis=1)
            hit = np.isfinite(hit_s)
            out.distance[rows[hit]] = np.maximum(hit_s[hit], 0.0)
            k = first[hit]
            at = origins[rows[hit]] + hit_s[hit, None] * dirs[rows[hit]]
            away = at - closest[hit, k]
            norm = np.linalg.norm(away, axis=1, keepdims=True)
            out.normal[rows[hit]] = np.where(
                norm > 1e-9, away / np.maximum(norm, 1e-12), -dirs[rows[hit]]
            )
            out.path[rows] = self._path_inside(tree, origins[rows], dirs[rows], out.distance[rows])
        return out

    def _path_inside(
        self, instance: int, origins: np.ndarray, dirs: np.ndarray, until: np.ndarray
    ) -> np.ndarray:
        """`(K,)` :attr:`LimbHits.path` of rays ``origins + s dirs`` `(K, 3)` in the crown of
        tree ``instance``, cut at ``until`` `(K,)` metres."""
        t = self._trees[int(instance)]
        radii = np.asarray(t.crown_radii, np.float64)
        u = (origins - np.asarray(t.crown_center, np.float64)) / radii
        v = dirs / radii
        a = np.einsum("ij,ij->i", v, v)
        b = np.einsum("ij,ij->i", u, v)
        c = np.einsum("ij,ij->i", u, u) - 1.0
        far = (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a  # metres: dirs are unit
        return np.clip(np.minimum(far, until), 0.0, None) * np.sqrt(a)


def _closest_approach(
    o: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest approach of rays ``o + s d`` (``s >= 0``) to segments ``a..b``.

    Args:
        o, d: `(M, 3)` ray origins and unit directions.
        a, b: `(S, 3)` segment ends.

    Returns:
        ``(s, dist, closest)``: `(M, S)` ray parameters and distances, `(M, S, 3)` the closest
        points on the segments.
    """
    e = b - a  # (S, 3)
    w = o[:, None, :] - a[None]  # (M, S, 3)
    de = d @ e.T  # (M, S)
    ee = np.einsum("ij,ij->i", e, e)[None]  # (1, S)
    dw = np.einsum("mk,msk->ms", d, w)
    ew = np.einsum("sk,msk->ms", e, w)
    # the segment's parameter of the lines' closest approach, clamped to the segment; then the
    # ray's (clamped to s >= 0) and the segment's once more for that s
    denom = ee - de**2
    u = np.where(denom > 1e-12, (ew - de * dw) / np.maximum(denom, 1e-12), 0.0)
    u = np.clip(u, 0.0, 1.0)
    s = np.maximum(de * u - dw, 0.0)
    u = np.clip((de * s + ew) / np.maximum(ee, 1e-12), 0.0, 1.0)
    closest = a[None] + u[..., None] * e[None]
    gap = o[:, None, :] + s[..., None] * d[:, None, :] - closest
    return s, np.linalg.norm(gap, axis=2), closest


def trace_crowns(hits, t_wc, dirs, cast, limbs: CrownLimbs | None, pixel_angle, passes, step):
    """Rays through leafless crowns (the renderer's bare-crown pass): a ray that meets a crown
    stops at a branch or goes on through the crown and is cast again.

    The branches are the voxel pattern of :func:`geoseg.synth.textures.branch_mask` on each
    crown surface (``limbs`` None), or the limbs of ``limbs``: a ray entering a crown is tested
    against them over its whole path inside and goes through the crown's far surface.

    Args:
        hits: the first cast's hits (``t``, ``kind``, ``instance``, ``normal`` `(N, ...)`),
            updated in place; ``crown`` (the ray met a crown first) and ``passes`` (crown
            surfaces gone through) are set, and with limbs ``cover``
            (:attr:`LimbHits.cover`, combined over the crowns) and ``twigs`` (the twig mass's
            optical path, :func:`mass_cover`).
        t_wc: `(3,)` camera centre; dirs: `(N, 3)` unit ray directions, world frame.
        cast: ``(origins (M, 3), dirs (M, 3)) -> hits`` of the scene.
        limbs: the world's skeletons, or None for the voxel branches.
        pixel_angle: radians per pixel (limbs only).
        passes: most crown surfaces a ray goes through; step: metres it restarts behind one.
    """
    n = len(hits.t)
    travelled = np.zeros(n)
    hits.crown = hits.kind == SurfaceKind.CROWN
    hits.passes = np.zeros(n, dtype=np.int32)
    if limbs is not None:
        hits.cover = np.zeros(n, dtype=np.float32)
        hits.twigs = np.zeros(n, dtype=np.float32)
        tested = np.full((n, 2), -1, np.int64)  # the last two crowns entered: their far sides
    active = np.nonzero(hits.crown)[0]
    for _ in range(passes):
        if len(active) == 0:
            break
        X = t_wc + (travelled[active] + hits.t[active])[:, None] * dirs[active]
        if limbs is None:
            stop = branch_mask(X, hits.instance[active])
        else:
            stop = _stop_at_limbs(hits, active, X, dirs, travelled, tested, limbs, pixel_angle)
        active, X = active[~stop], X[~stop]
        if len(active) == 0:
            break
        hits.passes[active] += 1
        travelled[active] += hits.t[active] + step
        sub = cast(X + step * dirs[active], dirs[active])
        hits.t[active] = sub.t
        hits.kind[active] = sub.kind
        hits.instance[active] = sub.instance
        hits.normal[active] = sub.normal
        active = active[sub.kind == SurfaceKind.CROWN]
    hits.t = hits.t + travelled
    return hits


def _stop_at_limbs(hits, active, X, dirs, travelled, tested, limbs: CrownLimbs, pixel_angle):
    """`(A,)` bool: the ``active`` rays, at crown surfaces ``X`` `(A, 3)`, that stop at a limb
    (their hits moved onto it); the rays entering a crown add the thin limbs' cover and their
    path through the twig mass up to where they stop."""
    inst = hits.instance[active].astype(np.int64)
    entering = np.nonzero((inst != tested[active, 0]) & (inst != tested[active, 1]))[0]
    stop = np.zeros(len(active), dtype=bool)
    if len(entering) == 0:
        return stop
    rows = active[entering]
    got = limbs.intersect(
        X[entering], dirs[rows], inst[entering], travelled[rows] + hits.t[rows], pixel_angle
    )
    hits.cover[rows] = 1.0 - (1.0 - hits.cover[rows]) * (1.0 - got.cover)
    hits.twigs[rows] += got.path * twig_speckle(X[entering], inst[entering])
    solid = np.isfinite(got.distance)
    hits.t[rows[solid]] += got.distance[solid]
    hits.normal[rows[solid]] = got.normal[solid]
    stop[entering[solid]] = True
    tested[rows, 1] = tested[rows, 0]
    tested[rows, 0] = inst[entering]
    return stop


def twig_colour(cond: Condition) -> np.ndarray:
    """`(3,)` float32 colour of twigs finer than a pixel: grey-brown bark, half lit."""
    light = cond.ambient_strength * np.asarray(cond.ambient_color, dtype=np.float32)
    light = light + 0.5 * max(cond.sun_strength, 0.0) * np.asarray(cond.sun_color, np.float32)
    return np.float32([0.27, 0.23, 0.2]) * light


def twig_speckle(X: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """`(M,)` how dense the twigs are around the points ``X`` `(M, 3)` of the crowns
    ``instance`` `(M,)`, relative to their mean (1): smooth clumps (:data:`_CLUMP_CELL`, uniform
    in [0, 2]) times one exponential draw per twig cell (:data:`_TWIG_CELL`), fixed in the world
    so that every frame sees the same crown."""
    clump = 2.0 * _value_noise_3d(X / _CLUMP_CELL, instance, seed=45)
    keys = [np.floor(X[:, i] / _TWIG_CELL) for i in range(3)]
    return clump * -np.log1p(-hash01(*keys, instance, seed=46).astype(np.float64))


def _value_noise_3d(x: np.ndarray, instance: np.ndarray, seed: int) -> np.ndarray:
    """`(M,)` in [0, 1): one uniform value per integer lattice corner, interpolated
    trilinearly at ``x`` `(M, 3)` (lattice units)."""
    base = np.floor(x)
    f = x - base
    out = np.zeros(len(x))
    for corner in np.ndindex(2, 2, 2):
        w = np.prod(np.where(np.array(corner) == 1, f, 1.0 - f), axis=1)
        out += w * hash01(*(base + corner).T, instance, seed=seed)
    return out


def haze_cover(passes: np.ndarray, density: float) -> np.ndarray:
    """`(N,)` float32 share of each pixel covered by a flat haze of twigs finer than a pixel
    (behind voxel branches): each of a ray's `(N,)` ``passes`` through a crown surface covers
    ``density`` of what lies behind."""
    return 1.0 - (1.0 - np.float32(density)) ** passes.astype(np.float32)


def mass_cover(twigs: np.ndarray, density: float) -> np.ndarray:
    """`(N,)` float32 share of each pixel covered by a twig mass (behind limbs): a ray's `(N,)`
    ``twigs`` (its path through bare crowns times their speckle) is its optical depth, in units
    that make a mean path cover as much as :func:`haze_cover`'s two crown surfaces of
    ``density``."""
    depth = -2.0 * np.log1p(-min(float(density), 1.0 - 1e-6)) / _MEAN_CHORD * twigs
    return (-np.expm1(-depth)).astype(np.float32)


def fine_twig_cover(hits, density: float) -> np.ndarray:
    """`(N,)` float32 share of each pixel the twigs finer than a pixel cover, for the
    renderer's hits after :func:`trace_crowns`: a twig mass behind limbs, a flat haze behind
    voxel branches (zeros where ``density`` is 0)."""
    if density <= 0:
        return np.zeros(len(hits.passes), np.float32)
    if hits.twigs is not None:
        return mass_cover(hits.twigs, density)
    return haze_cover(hits.passes, density)


def veil_crowns(rgb: np.ndarray, hits, twig_density: float, cond: Condition) -> None:
    """Veil `(N, 3)` ``rgb`` with what leafless crowns put in front of it (the renderer's
    hits after :func:`trace_crowns`): the twigs finer than a pixel where ``twig_density`` > 0,
    then the thin limbs."""
    veil(rgb, fine_twig_cover(hits, twig_density), cond)
    if hits.cover is not None:
        veil(rgb, hits.cover, cond)


def labelled_crown(hits, sky: np.ndarray, twig_density: float, min_cover: float) -> np.ndarray:
    """`(N,)` bool: the pixels a leafless crown labels ``vegetation`` (the renderer's hits
    after :func:`trace_crowns`; ``sky`` `(N,)` bool: the rays that reach nothing).

    ``min_cover`` 0: every pixel whose ray met a bare crown first, the crown's whole
    silhouette. Above 0: of those, the pixels whose ray stopped at a branch or limb, whose ray
    goes on to the sky (the silhouette against the sky, as real labels draw it), or whose fine
    twigs and thin limbs together cover at least ``min_cover`` of the pixel; where a facade, a
    vehicle or the ground shows through a thin part of the crown, it labels the pixel (a map
    point tracked there lies on it).
    """
    if min_cover <= 0:
        return hits.crown
    cover = 1.0 - (1.0 - fine_twig_cover(hits, twig_density)) * (
        1.0 - (0.0 if hits.cover is None else hits.cover)
    )
    stopped = hits.kind == SurfaceKind.CROWN  # at a branch voxel, a limb, or out of passes
    return hits.crown & (stopped | sky | (cover >= min_cover))


def veil(rgb: np.ndarray, cover: np.ndarray, cond: Condition) -> None:
    """Veil `(N, 3)` ``rgb`` by `(N,)` ``cover`` (the share of each pixel twigs or thin limbs
    cover) with their bark (:func:`twig_colour`)."""
    r = np.nonzero(cover > 0)[0]
    if len(r) == 0:
        return
    c = cover[r, None].astype(np.float32)
    rgb[r] = rgb[r] * (1.0 - c) + twig_colour(cond) * c
