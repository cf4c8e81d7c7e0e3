"""World points and their keyframe observations for the chapter-3 experiment (thesis §3.7).

The thesis's synthetic sequence gives the SLAM the 2D tracks of scene points; here they come
from the synthetic city of :mod:`geoseg.synth`:

1. **Sampling** (:func:`sample_landmarks`): points are drawn uniformly on the surfaces of the
   static scene mesh (``World.parts``: facades, ground, i.e. road, road markings and sidewalks,
   trunks, parked vehicles, poles, panels, shelters), area-weighted per surface kind with a
   density in points per square metre, and only on triangles within ``corridor_m`` of the
   trajectory. Roofs and tree crowns are not sampled (not trackable corners) but still occlude.
   Each point is pushed ``offset_m`` along its triangle's normal (towards the side it faces) so
   that the ray cast does not hit its own surface first.
2. **Visibility** (:func:`visible_observations`): a point is observed by keyframe ``k`` iff it
   projects inside the image with depth in ``[min_depth_m, max_depth_m]`` and the first hit of
   the ray from the optical centre ``t_wc[k]`` towards it lies no closer than ``|X - t_wc| -
   tol_m`` (the occlusion test is an embree ray cast through the same scene mesh the renderer
   uses, all candidate (keyframe, point) pairs in one batched call). Moving vehicles are not in
   the scene (their positions depend on time): documented simplification.
3. **Measurement** (:func:`simulate_observations`): ``uv = pi(K R_wc^T (X_w - t_wc)) + e``, ``e ~
   N(0, noise_px^2 I)``; a share ``outlier_share`` of the observations is replaced by a pixel
   drawn uniformly in the image (gross mismatches), flagged in ``is_outlier`` (ground truth,
   never given to the SLAM).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from trimesh.ray.ray_pyembree import RayMeshIntersector

from geoseg.errors import check_finite, check_shape
from slam_bridge.errors import SlamError
from slam_bridge.geometry.camera import project

logger = logging.getLogger(__name__)

__all__ = [
    "LandmarkConfig",
    "Landmarks",
    "Observations",
    "SceneCaster",
    "sample_landmarks",
    "visible_observations",
    "simulate_observations",
]

#: surface kinds (``geoseg.synth.world.SurfaceKind`` values) sampled by default, with names
KIND_NAMES = {
    0: "ground",
    1: "facade",
    3: "trunk",
    5: "vehicle_body",
    7: "vehicle_wheel",
    8: "pole",
    9: "panel",
    10: "shelter_glass",
}


@dataclass
class LandmarkConfig:
    """Landmark sampling and measurement model.

    Attributes:
        facade_density: points per m^2 on facades.
        ground_density: points per m^2 on the ground (road, markings, sidewalks, terrain).
        object_density: points per m^2 on trunks, vehicles, poles, panels, shelters.
        corridor_m: only triangles whose centroid lies within this horizontal distance of the
            trajectory are sampled.
        offset_m: points are moved this far off their surface, along the triangle normal.
        min_depth_m: nearest visible depth (z in the camera frame).
        max_depth_m: farthest visible depth.
        tol_m: occlusion tolerance of the ray cast (metres before the point).
        noise_px: standard deviation of the pixel noise (per axis).
        outlier_share: share of observations replaced by a random pixel.
        border_px: observations closer than this to the image border are dropped.
    """

    facade_density: float = 0.25
    ground_density: float = 0.08
    object_density: float = 0.3
    corridor_m: float = 60.0
    offset_m: float = 0.02
    min_depth_m: float = 1.0
    max_depth_m: float = 50.0
    tol_m: float = 0.05
    noise_px: float = 1.0
    outlier_share: float = 0.03
    border_px: float = 2.0

    def __post_init__(self) -> None:
        for name in ("corridor_m", "max_depth_m", "tol_m", "min_depth_m"):
            if not getattr(self, name) > 0:
                raise SlamError(f"{name}: expected > 0, got {getattr(self, name)}")
        for name in ("facade_density", "ground_density", "object_density", "noise_px"):
            if getattr(self, name) < 0:
                raise SlamError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.outlier_share < 1.0:
            raise SlamError(f"outlier_share: expected a share in [0, 1), got {self.outlier_share}")
        if self.max_depth_m <= self.min_depth_m:
            raise SlamError("max_depth_m must exceed min_depth_m")


@dataclass
class Landmarks:
    """``P`` world points.

    Attributes:
        X_w: ``(P, 3)`` positions in the world frame (metres).
        kind: ``(P,)`` uint8 surface kind of each point (``geoseg.synth.world.SurfaceKind``).
        normal_w: ``(P, 3)`` unit normal of the surface it lies on (world frame).
    """

    X_w: np.ndarray
    kind: np.ndarray
    normal_w: np.ndarray

    def __len__(self) -> int:
        return int(self.X_w.shape[0])


@dataclass
class Observations:
    """``M`` keyframe observations, sorted by keyframe then point.

    Attributes:
        keyframe: ``(M,)`` int64 keyframe index (row of the pose arrays given).
        point: ``(M,)`` int64 landmark index.
        uv: ``(M, 2)`` measured pixels.
        uv_true: ``(M, 2)`` noise-free projections (ground truth).
        is_outlier: ``(M,)`` bool, the measurement is a gross mismatch (ground truth).
    """

    keyframe: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    uv_true: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    is_outlier: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def __len__(self) -> int:
        return int(self.keyframe.shape[0])


class SceneCaster:
    """First-hit ray casting through a triangle mesh (trimesh + embree).

    Args:
        vertices: ``(V, 3)`` world vertices.
        faces: ``(F, 3)`` vertex indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        check_shape("vertices", vertices, (None, 3))
        check_shape("faces", faces, (None, 3))
        if faces.shape[0] == 0:
            raise SlamError("SceneCaster: the scene has no triangle")
        mesh = trimesh.Trimesh(vertices, faces, process=False, validate=False)
        self._intersector = RayMeshIntersector(mesh)
        tri = vertices[faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self._normal = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        self._offset = np.einsum("fi,fi->f", self._normal, tri[:, 0])

    @classmethod
    def from_world(cls, world) -> SceneCaster:
        """The static scene of a :class:`geoseg.synth.World` (all its ``parts``)."""
        from geoseg.synth.world import concat_parts

        part = concat_parts(world.parts)
        return cls(part.vertices, part.faces)

    def first_hit(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance to the first surface along each ray (``inf`` when nothing is hit).

        Args:
            origins: ``(N, 3)`` ray origins.
            directions: ``(N, 3)`` unit directions.

        Returns:
            ``(N,)`` ray parameters ``s`` of the first hit (``origin + s * direction``).
        """
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        out = np.full(origins.shape[0], np.inf)
        if origins.shape[0] == 0:
            return out
        tri = np.asarray(self._intersector.intersects_first(origins, directions), dtype=np.int64)
        hit = np.flatnonzero(tri >= 0)
        th = tri[hit]
        nrm = self._normal[th]
        nd = np.einsum("mi,mi->m", nrm, directions[hit])
        num = self._offset[th] - np.einsum("mi,mi->m", nrm, origins[hit])
        safe = np.abs(nd) > 1e-12
        out[hit] = np.where(safe, num / np.where(safe, nd, 1.0), 0.0)
        return out


def sample_landmarks(
    world,
    path_xy: np.ndarray,
    config: LandmarkConfig | None = None,
    *,
    seed: int = 0,
) -> Landmarks:
    """Sample points on the static scene near a trajectory (module docstring, step 1).

    Args:
        world: a :class:`geoseg.synth.World`.
        path_xy: ``(T, 2)`` horizontal trajectory positions (the sampling corridor).
        config: densities and corridor.
        seed: random seed.

    Returns:
        :class:`Landmarks`.
    """
    from geoseg.synth.world import concat_parts

    cfg = config or LandmarkConfig()
    path_xy = np.asarray(path_xy, dtype=np.float64)
    check_shape("path_xy", path_xy, (None, 2))
    check_finite("path_xy", path_xy)
    if path_xy.shape[0] == 0:
        raise SlamError("path_xy: empty trajectory")
    rng = np.random.default_rng([int(seed), 0x1A4D])
    part = concat_parts(world.parts)
    tri = part.vertices[part.faces]  # (F, 3, 3)
    kind = part.kind.astype(np.int64)
    density = np.zeros(kind.size)
    density[kind == 0] = cfg.ground_density
    density[kind == 1] = cfg.facade_density
    objects = np.isin(kind, [k for k in KIND_NAMES if k not in (0, 1)])
    density[objects] = cfg.object_density
    centroid = tri.mean(axis=1)
    d, _ = cKDTree(path_xy).query(centroid[:, :2], distance_upper_bound=cfg.corridor_m)
    density[~np.isfinite(d)] = 0.0
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(area2, 1e-300)[:, None]
    counts = rng.poisson(density * 0.5 * area2)
    f = np.repeat(np.arange(kind.size), counts)
    # uniform barycentric sampling
    a, b = rng.random(f.size), rng.random(f.size)
    flip = a + b > 1.0
    a[flip], b[flip] = 1.0 - a[flip], 1.0 - b[flip]
    T = tri[f]
    X = T[:, 0] + a[:, None] * (T[:, 1] - T[:, 0]) + b[:, None] * (T[:, 2] - T[:, 0])
    n = normal[f]
    # orient each normal towards the nearest trajectory position (the side the SLAM sees)
    _, near = cKDTree(path_xy).query(X[:, :2])
    to_path = np.concatenate([path_xy[near], X[:, 2:3] + 1.5], axis=1) - X
    n = np.where((np.einsum("mi,mi->m", n, to_path) < 0)[:, None], -n, n)
    if kind.size and np.any(kind[f] == 0):  # ground faces up
        g = kind[f] == 0
        n[g] = np.where((n[g, 2] < 0)[:, None], -n[g], n[g])
    X = X + cfg.offset_m * n
    logger.info(
        "landmarks: %d points (%s)",
        X.shape[0],
        ", ".join(
            f"{KIND_NAMES.get(k, k)} {int(np.sum(kind[f] == k))}" for k in np.unique(kind[f])
        ),
    )
    return Landmarks(X_w=X, kind=kind[f].astype(np.uint8), normal_w=n)


def visible_observations(
    caster: SceneCaster,
    landmarks: Landmarks,
    K: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    image_size: tuple[int, int],
    config: LandmarkConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which landmarks each keyframe sees (module docstring, step 2).

    Args:
        caster: the scene's :class:`SceneCaster`.
        landmarks: the points.
        K: ``(3, 3)`` intrinsics.
        R_wc: ``(C, 3, 3)`` true keyframe rotations.
        t_wc: ``(C, 3)`` true optical centres.
        image_size: ``(W, H)`` pixels.
        config: depth range, tolerance, border.

    Returns:
        ``keyframe (M,)``, ``point (M,)``, ``uv_true (M, 2)``: the visible pairs, sorted by
        keyframe then point, and their noise-free projections.
    """
    cfg = config or LandmarkConfig()
    R_wc = np.asarray(R_wc, dtype=np.float64)
    t_wc = np.asarray(t_wc, dtype=np.float64)
    check_shape("R_wc", R_wc, (None, 3, 3))
    check_shape("t_wc", t_wc, (R_wc.shape[0], 3))
    W, H = image_size
    X = landmarks.X_w
    # candidate pairs: points within max range of each camera centre (one batched query)
    near = cKDTree(X).query_ball_point(t_wc, r=cfg.max_depth_m * 1.5)
    counts = np.array([len(c) for c in near], dtype=np.int64)
    cams = np.repeat(np.arange(t_wc.shape[0]), counts)
    pts = np.concatenate([np.asarray(c, dtype=np.int64) for c in near]) if cams.size else cams
    uv, z, front = project(K, R_wc[cams], t_wc[cams], X[pts])
    b = cfg.border_px
    ok = (
        front
        & (z >= cfg.min_depth_m)
        & (z <= cfg.max_depth_m)
        & (uv[:, 0] >= b - 0.5)
        & (uv[:, 0] <= W - 0.5 - b)
        & (uv[:, 1] >= b - 0.5)
        & (uv[:, 1] <= H - 0.5 - b)
    )
    # facing test: a point on a surface seen from behind is hidden by that surface
    cams, pts, uv = cams[ok], pts[ok], uv[ok]
    ray = X[pts] - t_wc[cams]
    dist = np.linalg.norm(ray, axis=1)
    dirs = ray / dist[:, None]
    facing = np.einsum("mi,mi->m", landmarks.normal_w[pts], dirs) < 0.0
    cams, pts, uv, dirs, dist = cams[facing], pts[facing], uv[facing], dirs[facing], dist[facing]
    s = caster.first_hit(t_wc[cams], dirs)
    vis = s >= dist - cfg.tol_m
    order = np.lexsort((pts[vis], cams[vis]))
    logger.debug(
        "visibility: %d candidate pairs, %d visible (%.1f per keyframe)",
        ok.sum(),
        vis.sum(),
        vis.sum() / max(t_wc.shape[0], 1),
    )
    return cams[vis][order], pts[vis][order], uv[vis][order]


def simulate_observations(
    keyframe: np.ndarray,
    point: np.ndarray,
    uv_true: np.ndarray,
    image_size: tuple[int, int],
    config: LandmarkConfig | None = None,
    *,
    seed: int = 0,
) -> Observations:
    """Noisy measurements with gross outliers (module docstring, step 3).

    Args:
        keyframe: ``(M,)`` keyframe index of each visible pair.
        point: ``(M,)`` landmark index.
        uv_true: ``(M, 2)`` noise-free projections.
        image_size: ``(W, H)``.
        config: noise and outlier share.
        seed: random seed.

    Returns:
        :class:`Observations`.
    """
    cfg = config or LandmarkConfig()
    uv_true = np.asarray(uv_true, dtype=np.float64)
    check_shape("uv_true", uv_true, (len(keyframe), 2))
    rng = np.random.default_rng([int(seed), 0x0B5])
    M = uv_true.shape[0]
    uv = uv_true + rng.normal(0.0, cfg.noise_px, size=(M, 2)) if cfg.noise_px > 0 else uv_true
    uv = uv.copy()
    out = rng.random(M) < cfg.outlier_share
    W, H = image_size
    uv[out] = rng.random((int(out.sum()), 2)) * [W - 1, H - 1]
    return Observations(
        keyframe=np.asarray(keyframe, dtype=np.int64),
        point=np.asarray(point, dtype=np.int64),
        uv=uv,
        uv_true=uv_true.copy(),
        is_outlier=out,
    )
