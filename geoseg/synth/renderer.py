"""Ray-cast renderer: RGB, labels, camera-frame normals, depth and instance ids.

One ray per pixel centre is cast with trimesh's embree backend
(:class:`trimesh.ray.ray_pyembree.RayMeshIntersector`) into one combined static scene mesh
(ground, buildings, trees, parked vehicles, street furniture) with per-triangle kind and
instance arrays, plus a small per-frame mesh of the moving vehicles near the camera (their
positions depend on ``time_s``; a moving vehicle closer than half its length + 1 m to the camera
is left out, so the ego vehicle never drives "inside" one). Everything after the ray cast is
vectorised NumPy in float32: textures from world-space hit coordinates
(:mod:`geoseg.synth.textures`), Lambert sun + sky light, optional cast shadows
(``Renderer(world, shadows=True)``: a second ray cast towards the sun, ~20 % slower; off by
default to keep the speed targets), haze, lit windows and lamps at night, snow and bare trees
in winter (:mod:`geoseg.synth.conditions`). ``bench/render_speed.py`` measures the speed (the
embree call is about half of a frame, shading the other half).

Output conventions (:class:`Frame`):

- ``depth`` is the **z-depth** in the OpenCV camera frame (metres along the optical axis, not
  the ray length); **0 on sky pixels** (no hit).
- ``normals`` are unit vectors in the camera frame, flipped to face the camera; zeros and
  ``normal_valid = False`` on sky. Normals are the triangles' (flat facades; the ground mesh's
  facets are within ~0.1 degree of the true terrain normal).
- ``instance``: the facade id (:class:`~geoseg.synth.world.FacadeTable` row) on facade pixels,
  other ids elsewhere (see :mod:`geoseg.synth.world`), -1 on sky.
- Pixel ``(u, v)`` integer coordinates are pixel centres; ray ``(u, v)`` goes through
  ``K^-1 (u, v, 1)``. No anti-aliasing.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from tqdm import tqdm
from trimesh.ray.ray_pyembree import RayMeshIntersector

from geoseg.classes import OBJECT, ROAD, SIDEWALK, SKY, TERRAIN, VEGETATION, VEHICLE
from geoseg.errors import GeosegError, check_finite, check_shape
from geoseg.synth import bare_crowns, noise, textures
from geoseg.synth.conditions import Condition, get_condition
from geoseg.synth.noise import random_colours
from geoseg.synth.realism import Variation
from geoseg.synth.street_furniture import furniture_part, plate_albedo, pole_albedo
from geoseg.synth.trajectory import Trajectory, check_image_size
from geoseg.synth.world import World
from geoseg.synth.world_meshes import (
    SURFACE_CLASS,
    MeshPart,
    SurfaceKind,
    concat_parts,
    vehicle_mesh_part,
)

logger = logging.getLogger(__name__)

OCCLUDER_CATEGORIES: dict[str, int] = {
    "vegetation": VEGETATION,
    "vehicle": VEHICLE,
    "object": OBJECT,
}
MOVING_VEHICLE_RANGE = 250.0  # m: moving vehicles further than this from the camera are skipped
MAX_CROWN_PASSES = 8  # bare crowns: how many crown surfaces a ray may pass through
CROWN_STEP = 0.02  # m: a ray passing a bare crown surface restarts this far behind it
_NO_HIT = 255


@dataclass
class Frame:
    """One rendered frame (H x W pixels).

    Attributes:
        rgb: `(H, W, 3)` uint8.
        labels: `(H, W)` uint8 class ids (:mod:`geoseg.classes`).
        normals: `(3, H, W)` float32 unit normals, camera frame (zeros where invalid).
        normal_valid: `(H, W)` bool, False on sky.
        depth: `(H, W)` float32 z-depth, metres, camera frame; 0 on sky.
        instance: `(H, W)` int32 instance ids (facade id on facades), -1 on sky.
        K: `(3, 3)` float64 intrinsics.
        R_wc: `(3, 3)` float64 camera-to-world rotation.
        t_wc: `(3,)` float64 camera centre, world.
        condition: name of the appearance condition.
        time_s: the world time of the frame (moving vehicles), seconds.
    """

    rgb: np.ndarray
    labels: np.ndarray
    normals: np.ndarray
    normal_valid: np.ndarray
    depth: np.ndarray
    instance: np.ndarray
    K: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    condition: str
    time_s: float = 0.0


class _Scene:
    """One embree intersector with per-triangle plane, kind and instance arrays."""

    def __init__(self, part: MeshPart):
        self.empty = len(part.faces) == 0
        self.kind = part.kind.astype(np.uint8)
        self.instance = part.instance.astype(np.int32)
        if self.empty:
            return
        mesh = trimesh.Trimesh(part.vertices, part.faces, process=False, validate=False)
        self.intersector = RayMeshIntersector(mesh)
        tri = part.vertices[part.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(normal, axis=1, keepdims=True)
        self.normal = np.where(norm > 1e-12, normal / np.maximum(norm, 1e-300), [0.0, 0.0, 1.0])
        self.normal32 = self.normal.astype(np.float32)
        self.offset = (self.normal * tri[:, 0]).sum(1)

    def cast(
        self, origins: np.ndarray | None, directions: np.ndarray, single_origin=None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """First hits along unit-direction rays.

        Args:
            origins: `(N, 3)` ray origins (ignored when ``single_origin`` is given).
            directions: `(N, 3)` unit directions (float32 is fastest).
            single_origin: `(3,)` the common origin of all rays, or None.

        Returns:
            hit `(M,)` int64 indices of the rays that hit, their triangles `(M,)` int64, ray
            parameters `(M,)` float64 and unit triangle normals `(M, 3)` float32.
        """
        n = len(directions)
        if self.empty or n == 0:
            return _EMPTY_I, _EMPTY_I, _EMPTY_F, _EMPTY_N
        if origins is None:
            origins = np.broadcast_to(np.asarray(single_origin, dtype=np.float64), (n, 3))
        wrap = getattr(self.intersector, "_scene", None)
        if all(hasattr(wrap, a) for a in ("scene", "origin", "scale")):
            # trimesh's embree scene (vertices shifted by ``origin`` and scaled by ``scale``),
            # called with float32 arrays prepared here and asked for the hit distances too
            scaled = np.empty((n, 3), dtype=np.float32)
            if single_origin is not None:
                scaled[:] = (np.asarray(single_origin) - wrap.origin) * wrap.scale
            else:
                scaled[:] = (origins - wrap.origin) * wrap.scale
            dirs32 = np.ascontiguousarray(directions, dtype=np.float32)
            res = wrap.scene.run(scaled, dirs32, output=1)
            hit = np.nonzero(res["primID"] >= 0)[0]
            th = res["primID"][hit].astype(np.int64)
            t = res["tfar"][hit].astype(np.float64) / wrap.scale
            return hit, th, t, self.normal32[th]
        # public trimesh call, ray parameters from the triangle planes
        directions = np.asarray(directions, dtype=np.float64)
        tri = np.asarray(self.intersector.intersects_first(origins, directions), dtype=np.int64)
        hit = np.nonzero(tri >= 0)[0]
        th = tri[hit]
        nrm = self.normal[th]
        d = directions[hit]
        nd = nrm[:, 0] * d[:, 0] + nrm[:, 1] * d[:, 1] + nrm[:, 2] * d[:, 2]
        o = origins[hit]
        num = self.offset[th] - (nrm[:, 0] * o[:, 0] + nrm[:, 1] * o[:, 1] + nrm[:, 2] * o[:, 2])
        safe = np.abs(nd) > 1e-12
        t = np.maximum(np.where(safe, num / np.where(safe, nd, 1.0), 0.0), 0.0)
        return hit, th, t, self.normal32[th]


_EMPTY_I = np.zeros(0, dtype=np.int64)
_EMPTY_F = np.zeros(0, dtype=np.float64)
_EMPTY_N = np.zeros((0, 3), dtype=np.float32)


@dataclass
class _Hits:
    t: np.ndarray  # (N,) ray parameter (unit directions), inf = sky
    kind: np.ndarray  # (N,) uint8 SurfaceKind, 255 = sky
    instance: np.ndarray  # (N,) int32, -1 = sky
    normal: np.ndarray  # (N, 3) float32 world geometric normal
    crown: np.ndarray | None = None  # (N,) bool: the ray met a bare crown first (or None)
    passes: np.ndarray | None = None  # (N,) int: bare crown surfaces the ray went through
    cover: np.ndarray | None = None  # (N,) float32: share of the pixel thin limbs cover
    twigs: np.ndarray | None = None  # (N,) float32: optical path through limbs' twig masses


class Renderer:
    """Renders frames of one world; caches the embree scene and per-triangle attributes.

    Args:
        world: the city.
        drop: occluder categories left out of the scene (``vegetation``, ``vehicle``,
            ``object``), e.g. to measure how much of the facades they hide.
        shadows: cast shadow rays when the condition asks for them (default False: never;
            about 20 % slower).
    """

    def __init__(self, world: World, *, drop: Sequence[str] = (), shadows: bool = False):
        if not isinstance(world, World):
            raise GeosegError(f"world: expected a World, got {type(world).__name__}")
        drop = (drop,) if isinstance(drop, str) else tuple(drop)
        unknown = sorted(set(drop) - set(OCCLUDER_CATEGORIES))
        if unknown:
            raise GeosegError(
                f"drop: expected categories among {sorted(OCCLUDER_CATEGORIES)}, got {unknown}"
            )
        self.world = world
        self.drop = tuple(sorted(set(drop)))
        self.shadows = bool(shadows)
        dropped = [OCCLUDER_CATEGORIES[d] for d in self.drop]
        part = concat_parts(world.parts)
        keep = ~np.isin(SURFACE_CLASS[part.kind], dropped)
        self._static = _Scene(
            MeshPart(part.vertices, part.faces[keep], part.kind[keep], part.instance[keep])
        )
        self._with_movers = "vehicle" not in self.drop
        self._movers = [v for v in world.vehicles if v.moving]
        self._mover_index = np.array([i for i, v in enumerate(world.vehicles) if v.moving], int)
        self._mover_length = np.array([v.length for v in self._movers])
        cfg = world.config
        self._half_width = cfg.street_width / 2
        self._sidewalk = cfg.sidewalk_width

        # per-facade texture parameters
        table = world.facades()
        edge = table.p1 - table.p0
        length = np.linalg.norm(edge, axis=1)
        self._f_dir = edge / np.maximum(length, 1e-9)[:, None]
        self._f_p0 = table.p0
        b = world.buildings
        bld = table.building_id
        self._styles = textures.facade_styles(
            length,
            table.z_min,
            np.array([textures.MATERIAL_CODES[b[i].material] for i in bld], dtype=np.int64),
            np.array([b[i].storey_height for i in bld]),
            np.array([b[i].storeys for i in bld]),
            np.array([b[i].tint for i in bld]).reshape(-1, 3),
        )
        n_inst = len(world.instance_class) + 1
        self._vehicle_color = np.full((n_inst, 3), 0.5, dtype=np.float32)
        for v in world.vehicles:
            self._vehicle_color[v.instance] = v.color
        self._ray_cache: dict[tuple, np.ndarray] = {}
        self._limbs: bare_crowns.CrownLimbs | None = None  # built at the first frame with limbs

    def __reduce__(self):
        """Pickle as the recipe (world and options); the embree scene is rebuilt on load."""
        return (_rebuild_renderer, (self.world, self.drop, self.shadows))

    # ---- public ----------------------------------------------------------------------------
    def render(
        self,
        K: np.ndarray,
        R_wc: np.ndarray,
        t_wc: np.ndarray,
        image_size: tuple[int, int] = (320, 240),
        condition: str | Condition = "summer_day",
        *,
        time_s: float = 0.0,
        variation: Variation | None = None,
    ) -> Frame:
        """Render one frame.

        Args:
            K: `(3, 3)` pinhole intrinsics.
            R_wc: `(3, 3)` camera-to-world rotation (OpenCV camera frame).
            t_wc: `(3,)` camera centre, world frame, metres.
            image_size: ``(W, H)`` pixels.
            condition: appearance condition name (:data:`~geoseg.synth.conditions.CONDITIONS`)
                or a :class:`~geoseg.synth.conditions.Condition`.
            time_s: world time, seconds (positions of the moving vehicles).
            variation: a domain-randomisation draw (:mod:`geoseg.synth.realism`); None: the
                world's own appearance.

        Returns:
            The frame.

        Raises:
            GeosegError: bad shapes/values, a camera inside a building or below the terrain.
        """
        K, R_wc, t_wc = self._check_camera(K, R_wc, t_wc)
        width, height = check_image_size(image_size)
        cond = get_condition(condition)
        if variation is not None:
            cond = variation.condition(cond)
        k1 = 0.0 if variation is None else float(variation.lens_k1)
        dirs_c = self._camera_rays(K, width, height, k1)
        dirs_w = _rotate(dirs_c, R_wc.astype(np.float32))
        extra = None  # the frame's street furniture, cast with the moving vehicles
        if variation is not None and variation.furniture_spacing > 0:
            extra = furniture_part(
                self.world,
                variation.seed,
                variation.furniture_spacing,
                t_wc,
                variation.furniture_kerb_share,
            )
        movers = self._mover_scene(R_wc, t_wc, float(time_s), extra)
        mover_rays = None
        if movers is not None and extra is None:
            mover_rays = self._mover_pixels(movers, K, R_wc, t_wc, width, height, dirs_c, k1)
        limbs = variation is not None and variation.limbs
        pixel_angle = 1.0 / float(K[0, 0]) if limbs else None
        hits = self._trace(t_wc, dirs_w, movers, cond, mover_rays, pixel_angle)
        return self._shade(
            hits, dirs_c, dirs_w, K, R_wc, t_wc, (width, height), cond, time_s, variation
        )

    def render_trajectory(
        self,
        trajectory: Trajectory,
        condition: str | Condition = "summer_day",
        *,
        progress: bool = True,
    ) -> Iterator[Frame]:
        """Render every frame of a trajectory (a generator, with a tqdm progress bar).

        Args:
            trajectory: poses, K, image size and timestamps.
            condition: appearance condition.
            progress: show the progress bar.

        Yields:
            One :class:`Frame` per trajectory frame, in order.
        """
        cond = get_condition(condition)
        for i in tqdm(range(len(trajectory)), desc=f"render {cond.name}", disable=not progress):
            yield self.render(
                trajectory.K,
                trajectory.R_wc[i],
                trajectory.t_wc[i],
                trajectory.image_size,
                cond,
                time_s=float(trajectory.timestamps[i]),
            )

    # ---- checks ----------------------------------------------------------------------------
    def _check_camera(self, K, R_wc, t_wc):
        K = np.asarray(K, dtype=np.float64)
        R_wc = np.asarray(R_wc, dtype=np.float64)
        t_wc = np.asarray(t_wc, dtype=np.float64)
        if t_wc.shape == (3, 1):
            t_wc = t_wc[:, 0]
        check_shape("K", K, (3, 3))
        check_shape("R_wc", R_wc, (3, 3))
        check_shape("t_wc", t_wc, (3,))
        for name, value in (("K", K), ("R_wc", R_wc), ("t_wc", t_wc)):
            check_finite(name, value)
        if not (K[0, 0] > 0 and K[1, 1] > 0 and abs(K[2, 2] - 1) < 1e-9 and not K[2, :2].any()):
            raise GeosegError(
                f"K: expected a pinhole matrix [[fx,s,cx],[0,fy,cy],[0,0,1]], got {K}"
            )
        err = np.abs(R_wc.T @ R_wc - np.eye(3)).max()
        if err > 1e-5 or np.linalg.det(R_wc) < 0:
            raise GeosegError(f"R_wc: expected a rotation matrix, got one off by {err:.2g}")
        building = int(self.world.building_at(t_wc[None])[0])
        if building >= 0:
            raise GeosegError(f"t_wc: the camera {t_wc.round(2)} is inside building {building}")
        ground = float(self.world.terrain_height(t_wc[None, :2])[0])
        if t_wc[2] < ground + 0.05:
            raise GeosegError(
                f"t_wc: the camera {t_wc.round(2)} is below the terrain (height {ground:.2f} m)"
            )
        return K, R_wc, t_wc

    def _camera_rays(self, K: np.ndarray, width: int, height: int, k1: float = 0.0) -> np.ndarray:
        key = (K.tobytes(), width, height, k1)
        rays = self._ray_cache.get(key)
        if rays is None:
            u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height))
            pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
            if k1:  # radial distortion: x_u = x_d (1 + k1 r_d^2), r_d in the image's half-width
                rays = _rotate(pix, np.linalg.inv(K))  # (per frame: no BLAS threads)
                scale = width / 2 / K[0, 0]
                r2 = (rays[:, 0] ** 2 + rays[:, 1] ** 2) / scale**2
                rays[:, :2] *= (1.0 + k1 * r2)[:, None]
                norm = np.sqrt(rays[:, 0] ** 2 + rays[:, 1] ** 2 + rays[:, 2] ** 2)
                return (rays / norm[:, None]).astype(np.float32)
            rays = pix @ np.linalg.inv(K).T
            rays = (rays / np.linalg.norm(rays, axis=1, keepdims=True)).astype(np.float32)
            if len(self._ray_cache) > 8:
                self._ray_cache.clear()
            self._ray_cache[key] = rays
        return rays

    # ---- ray casting -----------------------------------------------------------------------
    def _mover_scene(self, R_wc, t_wc, time_s: float, extra=None) -> _Scene | None:
        """The moving vehicles near the camera, with the :class:`MeshPart` ``extra`` if any."""
        if not self._with_movers or not self._movers:
            return None if extra is None else _Scene(extra)
        xy, heading = self.world.vehicle_poses(time_s)
        xy, heading = xy[self._mover_index], heading[self._mover_index]
        dist = np.linalg.norm(xy - t_wc[:2], axis=1)
        ahead = (xy - t_wc[:2]) @ R_wc[:2, 2] > -self._mover_length  # not behind the camera
        keep = (dist < MOVING_VEHICLE_RANGE) & (dist > self._mover_length / 2 + 1.0) & ahead
        parts = [] if extra is None else [extra]
        if keep.any():
            chosen = [v for v, k in zip(self._movers, keep) if k]
            parts.insert(0, vehicle_mesh_part(self.world, chosen, xy[keep], heading[keep]))
        return _Scene(concat_parts(parts)) if parts else None

    def _mover_pixels(
        self, movers: _Scene, K, R_wc, t_wc, width: int, height: int, dirs_c=None, k1=0.0
    ):
        """Flat indices of the pixels whose rays may hit a moving vehicle (None: all).

        With lens distortion (``k1``), the pixels whose camera rays ``dirs_c`` fall in each
        vehicle's box of normalised image coordinates (a pixel's margin added)."""
        mesh = movers.intersector.mesh
        X_c = (np.asarray(mesh.vertices) - t_wc) @ R_wc
        faces = np.asarray(mesh.faces)
        owner = np.empty(len(X_c), dtype=np.int64)
        owner[faces.ravel()] = np.repeat(movers.instance, 3)
        boxes = []
        for vehicle in np.unique(owner):
            P = X_c[owner == vehicle]
            front = P[:, 2] > 0.05
            if not front.any():
                continue  # behind the camera
            if not front.all():
                return None  # straddles the image plane: cast all rays
            if k1:
                xy = P[:, :2] / P[:, 2:3]
                boxes.append((*xy.min(0), *xy.max(0)))
                continue
            uv = P[:, :2] / P[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
            boxes.append((*uv.min(0), *uv.max(0)))
        if k1:
            if not boxes:
                return np.zeros(0, dtype=np.int64)
            rx = dirs_c[:, 0] / dirs_c[:, 2]
            ry = dirs_c[:, 1] / dirs_c[:, 2]
            mx, my = 2.0 / K[0, 0], 2.0 / K[1, 1]  # margin: two pixels
            hit = np.zeros(len(rx), dtype=bool)
            for x0, y0, x1, y1 in boxes:
                hit |= (rx > x0 - mx) & (rx < x1 + mx) & (ry > y0 - my) & (ry < y1 + my)
            return np.nonzero(hit)[0]
        mask = np.zeros((height, width), dtype=bool)
        for u0, v0, u1, v1 in boxes:
            c0, r0 = max(int(np.floor(u0)), 0), max(int(np.floor(v0)), 0)
            c1, r1 = min(int(np.ceil(u1)) + 1, width), min(int(np.ceil(v1)) + 1, height)
            if c1 > c0 and r1 > r0:
                mask[r0:r1, c0:c1] = True
        return np.nonzero(mask.ravel())[0]

    def _cast_all(self, origins, dirs, movers: _Scene | None, mover_rays=None, t_wc=None) -> _Hits:
        """Static scene + moving vehicles; ``origins`` `(N, 3)` or None with ``t_wc`` `(3,)`."""
        n = len(dirs)
        hit, th, t_hit, nrm = self._static.cast(origins, dirs, t_wc)
        t = np.full(n, np.inf)
        kind = np.full(n, _NO_HIT, dtype=np.uint8)
        instance = np.full(n, -1, dtype=np.int32)
        normal = np.zeros((n, 3), dtype=np.float32)
        t[hit] = t_hit
        kind[hit] = self._static.kind[th]
        instance[hit] = self._static.instance[th]
        normal[hit] = nrm
        if movers is not None:
            rays = np.arange(n) if mover_rays is None else mover_rays
            sub_origins = None if origins is None else origins[rays]
            hit2, th2, t2, nrm2 = movers.cast(sub_origins, dirs[rays], t_wc)
            closer = t2 < t[rays[hit2]]
            sel = rays[hit2[closer]]
            t[sel] = t2[closer]
            kind[sel] = movers.kind[th2[closer]]
            instance[sel] = movers.instance[th2[closer]]
            normal[sel] = nrm2[closer]
        return _Hits(t, kind, instance, normal)

    def _trace(self, t_wc, dirs, movers, cond: Condition, mover_rays, pixel_angle=None) -> _Hits:
        """The rays' hits; through bare crowns, their branches as voxels, or with
        ``pixel_angle`` (radians per pixel) as limbs (:mod:`geoseg.synth.bare_crowns`)."""
        hits = self._cast_all(None, dirs, movers, mover_rays, t_wc)
        if cond.leaves_on:
            return hits
        if pixel_angle is not None and self._limbs is None:
            self._limbs = bare_crowns.CrownLimbs(self.world.trees)
        return bare_crowns.trace_crowns(
            hits,
            t_wc,
            dirs,
            lambda o, d: self._cast_all(o, d, movers),
            None if pixel_angle is None else self._limbs,
            pixel_angle,
            MAX_CROWN_PASSES,
            CROWN_STEP,
        )

    # ---- shading ---------------------------------------------------------------------------
    def _shade(
        self, hits, dirs_c, dirs_w, K, R_wc, t_wc, size, cond: Condition, time_s, var=None
    ) -> Frame:
        width, height = size
        n = len(hits.t)
        hit = hits.kind != _NO_HIT
        idx = np.nonzero(hit)[0]
        kind = hits.kind[idx]
        t = hits.t[idx]
        t32 = t.astype(np.float32)
        d = dirs_w[idx]  # (M, 3) float32 unit rays of the hit pixels
        X = d * t32[:, None]  # world hit points, float32 (~0.1 mm at 1 km)
        X += t_wc.astype(np.float32)
        normal_w = hits.normal[idx]

        labels = np.full(n, SKY, dtype=np.uint8)
        lab = SURFACE_CLASS[kind]
        albedo = np.empty((len(idx), 3), dtype=np.float32)  # every surface kind fills its rows
        emissive = np.zeros((len(idx), 3), dtype=np.float32)

        # ground: class and texture (normals: the ground mesh facets, within ~0.1 deg)
        g = np.nonzero(kind == SurfaceKind.GROUND)[0]
        if len(g):
            xy = X[g, :2]
            dist, side, s, street = self.world.street_index.query(xy)
            cls = np.full(len(g), TERRAIN, dtype=np.uint8)
            cls[dist < self._half_width + self._sidewalk] = SIDEWALK
            cls[dist < self._half_width] = ROAD
            lab[g] = cls
            lengths = self.world.street_index.street_length[np.maximum(street, 0)]
            side = np.where(np.isfinite(side), side, 1e4)
            albedo[g] = textures.ground_albedo(
                xy,
                cls,
                side,
                s,
                lengths,
                self._half_width,
                self._sidewalk,
                self.world.config.parking_width,
                (ROAD, SIDEWALK, TERRAIN),
                np.asarray(cond.ground_tint),
            )
            if var is not None:
                _vary_ground(albedo, g, cls, var)
                if var.kerb_face > 0:
                    textures.kerb_and_paving(
                        albedo,
                        g,
                        cls,
                        side,
                        s,
                        self._half_width,
                        var.kerb_face,
                        var.slab_m,
                        tone=0.6 * float(np.mean(var.walk_rgb)),
                    )
                if var.kerb_lines > 0:
                    textures.kerb_lines(
                        albedo,
                        g,
                        cls,
                        side,
                        np.maximum(street, 0),
                        self._half_width,
                        var.kerb_lines,
                        var.seed % 100003,
                    )

        f = np.nonzero(kind == SurfaceKind.FACADE)[0]
        if len(f):
            row = hits.instance[idx[f]]
            rel = X[f, :2] - self._f_p0[row]
            u = rel[:, 0] * self._f_dir[row, 0] + rel[:, 1] * self._f_dir[row, 1]
            v = X[f, 2] - self._styles.base_z[row]
            styles = self._styles if var is None else self._varied_styles(var)
            albedo[f], emissive[f] = textures.facade_albedo(u, v, row, styles, cond.window_light)
            if var is not None:
                self._vary_facades(u, v, row, f, styles, var, albedo, emissive)
        self._shade_objects(kind, X, hits.instance[idx], albedo, emissive, cond, var)

        # normals towards the camera, camera frame
        facing = (
            normal_w[:, 0] * d[:, 0] + normal_w[:, 1] * d[:, 1] + normal_w[:, 2] * d[:, 2]
        ) > 0
        normal_w[facing] *= -1.0
        normal_c = _rotate(normal_w, R_wc.T.astype(np.float32))

        # snow on up-facing surfaces
        if cond.snow > 0:
            up = np.clip((normal_w[:, 2] - 0.6) / 0.3, 0.0, 1.0).astype(np.float32)
            cover = noise.value_noise(X[:, 0] / 1.3, X[:, 1] / 1.3, seed=71)
            amount = np.where(lab == ROAD, np.clip(cover * 2.0 - 0.7, 0, 0.9), 0.8 + 0.2 * cover)
            amount = np.where(lab == VEGETATION, 0.0, amount)
            amount = (cond.snow * up * amount)[:, None]
            albedo = albedo * (1 - amount) + amount * np.float32([0.97, 0.98, 1.0])

        # light: sky ambient + sun (Lambert, optional shadow rays) + emission, then haze:
        # color = albedo * (ambient + sun) * (1 - haze) + emissive * (1 - haze) + haze * horizon
        sun = cond.sun_direction
        keep = np.exp(t32 / -np.float32(cond.haze))  # 1 - haze
        ambient = (cond.ambient_strength * keep) * (0.7 + 0.3 * normal_w[:, 2])
        light = ambient[:, None] * np.asarray(cond.ambient_color, dtype=np.float32)
        if cond.sun_strength > 0 and sun[2] > 0:
            lambert = np.clip(_rotate(normal_w, sun[None].astype(np.float32))[:, 0], 0.0, 1.0)
            if cond.shadows and (self.shadows or (var is not None and var.shadows)):
                lit = np.nonzero(lambert > 0)[0]
                origin = X[lit] + 0.03 * normal_w[lit]
                hit_s, tri_s, _, _ = self._static.cast(origin, np.broadcast_to(sun, origin.shape))
                shade = np.ones(len(lit), dtype=np.float32)
                shade[hit_s] = 0.0
                if not cond.leaves_on:  # sparse shadows of bare crowns
                    shade[hit_s[self._static.kind[tri_s] == SurfaceKind.CROWN]] = 0.7
                lambert[lit] *= shade
            direct = (cond.sun_strength * keep) * lambert
            light += direct[:, None] * np.asarray(cond.sun_color, dtype=np.float32)
        color = albedo * light
        if cond.window_light > 0 or cond.lamps_on:  # the only emitters
            glowing = np.nonzero(emissive.any(axis=1))[0]
            color[glowing] += emissive[glowing] * keep[glowing, None]
        color += (1.0 - keep)[:, None] * np.asarray(cond.sky_horizon, dtype=np.float32)

        rgb = np.empty((n, 3), dtype=np.float32)
        sky = np.nonzero(~hit)[0]
        rgb[sky] = textures.sky_color(
            dirs_w[sky],
            np.asarray(cond.sky_zenith),
            np.asarray(cond.sky_horizon),
            sun,
            np.asarray(cond.sun_color),
            cond.sun_strength if sun[2] > -0.05 else 0.0,
            cloud_cover=0.0 if var is None else var.cloud_cover,
            seed=0 if var is None else var.seed % 100003,
        )
        rgb[idx] = color
        if hits.passes is not None:  # leafless crowns: fine twigs and thin limbs
            bare_crowns.veil_crowns(rgb, hits, 0.0 if var is None else var.twig_density, cond)
        np.clip(rgb, 0.0, 1.0, out=rgb)
        rgb *= 255.0
        rgb += 0.5
        rgb_u8 = rgb.astype(np.uint8)

        labels[idx] = lab
        if var is not None and var.bare_crown_label and hits.crown is not None:
            crown = bare_crowns.labelled_crown(hits, ~hit, var.twig_density, var.crown_label_cover)
            labels[crown] = VEGETATION  # the silhouette, as real labels draw it, or its dense part
        depth = np.zeros(n, dtype=np.float32)
        depth[idx] = t32 * dirs_c[idx, 2]
        normals = np.zeros((3, n), dtype=np.float32)
        normals[:, idx] = normal_c.T  # unit: triangle normals, rotated
        return Frame(
            rgb=rgb_u8.reshape(height, width, 3),
            labels=labels.reshape(height, width),
            normals=normals.reshape(3, height, width),
            normal_valid=hit.reshape(height, width),
            depth=depth.reshape(height, width),
            instance=hits.instance.reshape(height, width).copy(),
            K=K.copy(),
            R_wc=R_wc.copy(),
            t_wc=t_wc.copy(),
            condition=cond.name,
            time_s=float(time_s),
        )

    def _varied_styles(self, var: Variation) -> textures.FacadeStyles:
        """The facade styles with a share of the facades repainted (``var.paint_share``)."""
        if var.paint_share <= 0:
            return self._styles
        rows = np.arange(len(self._styles.length))
        paint = noise.hash01(rows, seed=var.seed + 201) < var.paint_share
        colours = random_colours(rows, var.seed + 202, 0.6)
        colours = 0.12 + 0.85 * colours  # no black walls
        material = self._styles.material.copy()
        new_material = (noise.hash_u32(rows, seed=var.seed + 203) % 4).astype(np.int64)
        material[paint] = new_material[paint]
        tint = self._styles.tint.copy()
        tint[paint] = colours[paint]
        frame_rgb = self._styles.frame_rgb.copy()
        frame_rgb[paint] = random_colours(rows, var.seed + 204, 0.3)[paint]
        return dataclasses.replace(self._styles, tint=tint, material=material, frame_rgb=frame_rgb)

    def _vary_facades(self, u, v, row, f, styles, var: Variation, albedo, emissive) -> None:
        """Shop fronts, poster hoardings and drainpipes on the facade hits ``f`` (rows of
        ``albedo``)."""
        overlays = (
            (var.shopfront_share, 205, textures.shopfront_albedo),
            (var.poster_share, 211, textures.poster_albedo),  # over a shop front where both fall
        )
        for share, seed_offset, overlay_albedo in overlays:
            if share <= 0:
                continue
            s = np.nonzero(noise.hash01(row, seed=var.seed + seed_offset) < share)[0]
            if len(s):
                inside, over = overlay_albedo(u[s], v[s], row[s], styles, var.seed % 100003)
                s = s[inside]
                albedo[f[s]] = over[inside]
                emissive[f[s]] = 0.0
        if var.paint_share > 0:  # drainpipes on some repainted facades
            pipe = noise.hash01(row, seed=var.seed + 206) < 0.5 * var.paint_share
            at = 0.25 + 0.5 * noise.hash01(row, seed=var.seed + 207)
            near_end = noise.hash01(row, seed=var.seed + 208) < 0.5
            at = np.where(near_end, styles.length[row] - at, at)
            p = np.nonzero(pipe & (np.abs(u - at) < 0.06))[0]
            albedo[f[p]] = np.float32([0.2, 0.2, 0.21])

    def _shade_objects(
        self, kind, X, instance, albedo, emissive, cond: Condition, var=None
    ) -> None:
        """Albedo (and lamp emission) of roofs, trees, vehicles and street furniture."""

        def where(k: SurfaceKind) -> np.ndarray:
            return np.nonzero(kind == k)[0]

        r = where(SurfaceKind.ROOF)
        albedo[r] = textures.roof_albedo(X[r], instance[r])
        c = where(SurfaceKind.CROWN)
        if cond.leaves_on:
            albedo[c] = textures.leaf_albedo(X[c], np.asarray(cond.leaf_color, dtype=np.float32))
        else:
            albedo[c] = textures.bark_albedo(X[c]) * 0.8
        tr = where(SurfaceKind.TRUNK)
        albedo[tr] = textures.bark_albedo(X[tr])
        colours = self._vehicle_color
        if var is not None and var.vehicle_colour_share > 0:
            ids = np.arange(len(colours))
            new = noise.hash01(ids, seed=var.seed + 209) < var.vehicle_colour_share
            colours = np.where(new[:, None], random_colours(ids, var.seed + 210, 0.3), colours)
        vb = where(SurfaceKind.VEHICLE_BODY)
        albedo[vb] = colours[instance[vb]]
        vg = where(SurfaceKind.VEHICLE_GLASS)
        albedo[vg] = np.float32([0.1, 0.12, 0.15]) + 0.1 * colours[instance[vg]]
        vw = where(SurfaceKind.VEHICLE_WHEEL)
        albedo[vw] = np.float32([0.06, 0.06, 0.06])
        p = where(SurfaceKind.POLE)
        albedo[p] = pole_albedo(instance[p], len(self.world.instance_class), [0.42, 0.44, 0.46])
        pa = where(SurfaceKind.PANEL)
        albedo[pa] = textures.panel_albedo(X[pa], instance[pa])
        if var is not None and var.furniture_plain_plates:
            albedo[pa] = plate_albedo(instance[pa], len(self.world.instance_class), albedo[pa])
        if cond.lamps_on and len(pa):
            high = X[pa, 2] - self.world.terrain.height(X[pa, :2]) > 6.0
            emissive[pa[high]] = np.float32([1.0, 0.9, 0.6])
        sg = where(SurfaceKind.SHELTER_GLASS)
        albedo[sg] = np.float32([0.55, 0.62, 0.66])


def _vary_ground(albedo: np.ndarray, g: np.ndarray, cls: np.ndarray, var: Variation) -> None:
    """Road tone and marking brightness, paving colour (rows ``g`` of ``albedo``)."""
    if var.road_gain != 1.0 or var.marking_gain != 1.0 or var.road_texture != 1.0:
        r = g[cls == ROAD]
        value = albedo[r]
        marking = value[:, 0] > 0.6
        if var.road_texture != 1.0 and (~marking).any():
            tone = np.median(value[~marking], axis=0)
            value[~marking] = tone + np.float32(var.road_texture) * (value[~marking] - tone)
        value[marking] *= var.marking_gain
        value[~marking] *= var.road_gain
        albedo[r] = value
    if var.walk_rgb != (1.0, 1.0, 1.0):
        w = g[cls == SIDEWALK]
        albedo[w] *= np.asarray(var.walk_rgb, dtype=np.float32)


def _rebuild_renderer(world: World, drop: tuple[str, ...], shadows: bool) -> Renderer:
    return Renderer(world, drop=drop, shadows=shadows)


def _rotate(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """`(N, 3)` rows times `(M, 3)` matrix transposed -> `(N, M)`, without BLAS threads."""
    out = np.empty((len(v), len(R)), dtype=np.result_type(v, R))
    for i in range(len(R)):
        out[:, i] = v[:, 0] * R[i, 0] + v[:, 1] * R[i, 1] + v[:, 2] * R[i, 2]
    return out


def render(
    world: World,
    K: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    image_size: tuple[int, int] = (320, 240),
    condition: str | Condition = "summer_day",
    *,
    time_s: float = 0.0,
    drop: Sequence[str] = (),
    variation: Variation | None = None,
) -> Frame:
    """Render one frame of ``world`` (the :class:`Renderer` is cached on the world).

    Args:
        world: the city.
        K: `(3, 3)` pinhole intrinsics.
        R_wc: `(3, 3)` camera-to-world rotation (OpenCV camera frame).
        t_wc: `(3,)` camera centre, world frame.
        image_size: ``(W, H)``.
        condition: appearance condition name or object.
        time_s: world time (moving vehicles), seconds.
        drop: occluder categories to leave out (see :class:`Renderer`).
        variation: a domain-randomisation draw (:mod:`geoseg.synth.realism`), or None.

    Returns:
        The frame (see :class:`Frame` for the conventions).
    """
    if not isinstance(world, World):
        raise GeosegError(f"world: expected a World, got {type(world).__name__}")
    key = tuple(sorted({drop} if isinstance(drop, str) else set(drop)))
    renderer = world._renderers.get(key)
    if renderer is None:
        renderer = Renderer(world, drop=key)
        world._renderers[key] = renderer
    return renderer.render(K, R_wc, t_wc, image_size, condition, time_s=time_s, variation=variation)
