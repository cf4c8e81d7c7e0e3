"""An image base's triangulated points, and a query localised on them by PnP.

The relative-pose heads (and the essential matrix) give the direction from a base image to a
query, not its distance. Along a street the base cameras and the query are nearly collinear, so
the rays of several matches are nearly parallel and leave the position along the street open:
the localiser then falls back on its best match's position, metres off. The base's poses are
known, though, so the points two neighbouring base images both see can be triangulated in the
world frame: metric and georeferenced. A query whose keypoints match those points is localised
by PnP (RANSAC, then Levenberg-Marquardt on the inliers): its full pose, to centimetres when
enough points agree — the classical structure-based relocalisation that the learned retrieval
narrows down to a few base images.

* :func:`build_structure`: SIFT keypoints of every base image, matched with its neighbours
  (base images close by and looking the same way), triangulated with the known poses and kept
  when they reproject, lie in front of both cameras and were seen with enough parallax; cached
  under ``BASE/cache/`` like the embeddings.
* :class:`StructureLocator`: a query's keypoints matched with the points of a few candidate base
  images (the retrieval's matches), PnP, and the gate (:attr:`StructureConfig.min_inliers`)
  that separates a pose from a guess.

Repeated facades (rows of identical windows) give matches that agree with a pose shifted by a
window's width; the inlier gate is what keeps those out (chosen on the tuning drives of
``bench/splits.py``'s ``RELOC_SLAM_TUNING_SEEDS``: at 60 inliers no fix was off by more than
0.2 m there).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from geoseg.atomic import atomic_output
from geoseg.errors import GeosegError, check_positive, check_shape

logger = logging.getLogger(__name__)

__all__ = [
    "BaseStructure",
    "StructureConfig",
    "StructureLocator",
    "StructurePose",
    "build_structure",
]

#: bump when the cached arrays change meaning
CACHE_VERSION = 1


@dataclass(frozen=True)
class StructureConfig:
    """How the base's points are triangulated and a query is localised on them.

    Attributes:
        max_features: SIFT keypoints per image.
        ratio: Lowe's ratio test between the best and second-best descriptor distances.
        neighbour_max_m: base images at most this far apart are matched and triangulated.
        neighbour_max_deg: ... and whose optical axes differ by at most this angle.
        neighbours: at most this many neighbours per base image (the nearest).
        min_parallax_deg: a point seen under a smaller angle is too poorly placed in depth.
        max_depth_m: farther points are dropped (their depth is the least certain).
        triangulation_px: largest reprojection error of a kept point in either image.
        pnp_px: RANSAC's inlier threshold for the query's reprojection.
        min_inliers: a query pose with fewer RANSAC inliers is not trusted.
    """

    max_features: int = 3000
    ratio: float = 0.8
    neighbour_max_m: float = 10.0
    neighbour_max_deg: float = 30.0
    neighbours: int = 2
    min_parallax_deg: float = 1.5
    max_depth_m: float = 60.0
    triangulation_px: float = 2.0
    pnp_px: float = 3.0
    min_inliers: int = 60

    def __post_init__(self) -> None:
        for name in ("max_features", "neighbours", "min_inliers"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise GeosegError(f"{name}: expected an int >= 1, got {value!r}")
        for name in (
            "neighbour_max_m", "neighbour_max_deg", "min_parallax_deg", "max_depth_m",
            "triangulation_px", "pnp_px",
        ):  # fmt: skip
            check_positive(name, getattr(self, name))
        if not 0 < self.ratio < 1:
            raise GeosegError(f"ratio: expected a number in (0, 1), got {self.ratio!r}")

    def cache_key(self) -> np.ndarray:
        """The settings the cached points depend on, as numbers."""
        return np.array(
            [
                self.max_features, self.ratio, self.neighbour_max_m, self.neighbour_max_deg,
                self.neighbours, self.min_parallax_deg, self.max_depth_m, self.triangulation_px,
            ],
            dtype=np.float64,
        )  # fmt: skip


@dataclass
class BaseStructure:
    """The triangulated keypoints of every base image.

    Attributes:
        image: ``(N,)`` int base image index of each point's keypoint.
        uv: ``(N, 2)`` keypoint pixel in that image.
        xyz: ``(N, 3)`` the point in the world frame, metres.
        descriptors: ``(N, 128)`` float32 SIFT descriptors of the keypoints.
    """

    image: np.ndarray
    uv: np.ndarray
    xyz: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return int(self.image.size)

    def points_per_image(self, images: int) -> np.ndarray:
        """``(images,)`` how many points each base image holds."""
        return np.bincount(self.image, minlength=images)


def _sift(max_features: int):
    import cv2

    return cv2.SIFT_create(nfeatures=int(max_features))


def _grey(image: Any) -> np.ndarray:
    """An RGB ``(H, W, 3)`` or grey ``(H, W)`` image as uint8 grey."""
    import cv2

    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    elif image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2:
        raise GeosegError(f"image: expected (H, W) or (H, W, 3), got shape {image.shape}")
    return np.ascontiguousarray(image, dtype=np.uint8)


def detect(image: Any, detector) -> tuple[np.ndarray, np.ndarray]:
    """``(uv (N, 2) float64, descriptors (N, 128) float32)`` of one image."""
    keypoints, desc = detector.detectAndCompute(_grey(image), None)
    uv = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
    if desc is None:
        desc = np.zeros((0, 128), dtype=np.float32)
    return uv, np.asarray(desc, dtype=np.float32)


def ratio_matches(query: np.ndarray, train: np.ndarray, ratio: float) -> np.ndarray:
    """``(M, 2)`` (query row, train row) pairs passing Lowe's ratio test (L2 distance)."""
    import cv2

    if len(query) == 0 or len(train) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, train, k=2)
    pairs = [
        (a.queryIdx, a.trainIdx) for a, b in (m for m in knn if len(m) == 2)
        if a.distance < ratio * b.distance
    ]  # fmt: skip
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def _projection(K: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray) -> np.ndarray:
    """``(3, 4)`` ``K [R_cw | t_cw]``."""
    R_cw = R_wc.T
    return K @ np.hstack([R_cw, (-R_cw @ t_wc)[:, None]])


def _reprojection_px(
    K, R_wc, t_wc, xyz: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(depth (N,), pixel error (N,))`` of world points ``xyz`` against ``uv`` in one camera."""
    xc = (xyz - t_wc) @ R_wc
    proj = xc @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        px = proj[:, :2] / proj[:, 2:3]
    return xc[:, 2], np.linalg.norm(px - uv, axis=1)


def neighbour_pairs(
    R_wc: np.ndarray, t_wc: np.ndarray, cfg: StructureConfig
) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, of base images close enough and looking the same way.

    Args:
        R_wc: ``(M, 3, 3)`` camera-to-world rotations.
        t_wc: ``(M, 3)`` camera centres.
        cfg: the distance and angle limits, and the number of neighbours per image.
    """
    axes = R_wc[:, :, 2]
    pairs: set[tuple[int, int]] = set()
    for i in range(len(t_wc)):
        dist = np.linalg.norm(t_wc - t_wc[i], axis=1)
        angle = np.degrees(np.arccos(np.clip(axes @ axes[i], -1.0, 1.0)))
        ok = (dist > 1e-3) & (dist <= cfg.neighbour_max_m) & (angle <= cfg.neighbour_max_deg)
        for j in np.flatnonzero(ok)[np.argsort(dist[ok])][: cfg.neighbours]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _triangulate(base, K, cfg, i, j, feats) -> list[tuple[int, int, np.ndarray]]:
    """``(image, keypoint row, xyz)`` of the points base images ``i`` and ``j`` both see."""
    import cv2

    (uv_i, d_i), (uv_j, d_j) = feats[i], feats[j]
    m = ratio_matches(d_i, d_j, cfg.ratio)
    if len(m) < 8:
        return []
    a, b = uv_i[m[:, 0]], uv_j[m[:, 1]]
    Ri, ti, Rj, tj = base.R_wc[i], base.t_wc[i], base.R_wc[j], base.t_wc[j]
    X = cv2.triangulatePoints(_projection(K, Ri, ti), _projection(K, Rj, tj), a.T, b.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        xyz = (X[:3] / X[3]).T
    depth_i, err_i = _reprojection_px(K, Ri, ti, xyz, a)
    depth_j, err_j = _reprojection_px(K, Rj, tj, xyz, b)
    ray_i, ray_j = xyz - ti, xyz - tj
    cos = (ray_i * ray_j).sum(1) / (np.linalg.norm(ray_i, axis=1) * np.linalg.norm(ray_j, axis=1))
    parallax = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    ok = (
        np.isfinite(xyz).all(axis=1)
        & (depth_i > 0.5) & (depth_j > 0.5)
        & (depth_i < cfg.max_depth_m) & (depth_j < cfg.max_depth_m)
        & (err_i < cfg.triangulation_px) & (err_j < cfg.triangulation_px)
        & (parallax > cfg.min_parallax_deg)
    )  # fmt: skip
    out = []
    for (ri, rj), x, keep in zip(m, xyz, ok):
        if keep:
            out.append((i, int(ri), x))
            out.append((j, int(rj), x))
    return out


def _cache_path(base) -> Any:
    from geoseg.reloc.image_base import CACHE_DIR

    return base.root / CACHE_DIR / "structure_sift.npz"


def _read_cache(base, cfg: StructureConfig) -> BaseStructure | None:
    path = _cache_path(base)
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            same = (
                int(z["version"]) == CACHE_VERSION
                and [str(s) for s in z["images"]] == list(base.images)
                and np.array_equal(z["fingerprints"], base.fingerprints())
                and np.array_equal(z["settings"], cfg.cache_key())
            )
            if not same:
                logger.info("%s: stale structure cache; triangulating again", path)
                return None
            return BaseStructure(z["image"], z["uv"], z["xyz"], z["descriptors"])
    except Exception as err:  # never fatal: recomputed
        logger.warning("%s: not a readable structure cache (%s); triangulating again", path, err)
        return None


def _write_cache(base, cfg: StructureConfig, structure: BaseStructure) -> None:
    path = _cache_path(base)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path, fsync=False) as handle:
            np.savez(
                handle, version=CACHE_VERSION, images=np.asarray(base.images, dtype=str),
                fingerprints=base.fingerprints(), settings=cfg.cache_key(), image=structure.image,
                uv=structure.uv, xyz=structure.xyz, descriptors=structure.descriptors,
            )  # fmt: skip
    except OSError as err:
        logger.warning("%s: could not write the structure cache (%s)", path, err)


def build_structure(
    base, config: StructureConfig | None = None, *, cache: bool = True
) -> BaseStructure:
    """Triangulate the points neighbouring base images see (or read them from the cache).

    Args:
        base: an :class:`~geoseg.reloc.image_base.ImageBase` with its ``camera.json`` (``K``).
        config: :class:`StructureConfig`.
        cache: read/write ``BASE/cache/structure_sift.npz`` (stale when an image or a setting
            changes).

    Returns:
        The :class:`BaseStructure`; a point seen by several pairs is kept once per image.

    Raises:
        GeosegError: the base has no intrinsics, or no pair of its images gave a point.
    """
    cfg = config or StructureConfig()
    if base.K is None:
        raise GeosegError(
            f"{base.root}: the base has no camera.json: its points cannot be triangulated "
            "without the intrinsics"
        )
    if cache:
        cached = _read_cache(base, cfg)
        if cached is not None:
            return cached
    detector = _sift(cfg.max_features)
    feats = [detect(base.load_image(i), detector) for i in range(len(base))]
    rows: dict[tuple[int, int], np.ndarray] = {}
    for i, j in neighbour_pairs(base.R_wc, base.t_wc, cfg):
        for image, row, xyz in _triangulate(base, base.K, cfg, i, j, feats):
            rows.setdefault((image, row), xyz)  # the nearest pair's point first
    if not rows:
        raise GeosegError(
            f"{base.root}: no base images close enough to triangulate (neighbours within "
            f"{cfg.neighbour_max_m:g} m looking within {cfg.neighbour_max_deg:g} deg)"
        )
    keys = sorted(rows)
    image = np.array([k[0] for k in keys], dtype=np.int64)
    uv = np.stack([feats[i][0][r] for i, r in keys])
    descriptors = np.stack([feats[i][1][r] for i, r in keys])
    structure = BaseStructure(image, uv, np.stack([rows[k] for k in keys]), descriptors)
    logger.info(
        "image base %s: %d triangulated points (%.0f per image)",
        base.root, len(structure), len(structure) / len(base),
    )  # fmt: skip
    if cache:
        _write_cache(base, cfg, structure)
    return structure


@dataclass
class StructurePose:
    """A query's pose from the base's points, or why there is none.

    Attributes:
        ok: a pose passed the inlier gate.
        R_wc: ``(3, 3)`` camera-to-world rotation (None when not ``ok``).
        t_wc: ``(3,)`` camera centre in the world frame, metres (None when not ``ok``).
        n_matches: 2D-3D matches tried.
        n_inliers: RANSAC inliers of the best pose.
        rms_px: reprojection rms of the inliers after refinement.
        reason: why there is no pose ("" when ``ok``).
    """

    ok: bool
    R_wc: np.ndarray | None
    t_wc: np.ndarray | None
    n_matches: int
    n_inliers: int = 0
    rms_px: float = float("nan")
    reason: str = ""


class StructureLocator:
    """A query's pose from its matches with the points of a few base images (PnP).

    Args:
        structure: the base's :class:`BaseStructure`.
        K: ``(3, 3)`` the queries' intrinsics (they may differ from the base's).
        config: :class:`StructureConfig` (its ``ratio``, ``pnp_px`` and ``min_inliers``).
    """

    def __init__(self, structure: BaseStructure, K: Any, config: StructureConfig | None = None):
        self.structure = structure
        self.K = np.asarray(K, dtype=np.float64)
        check_shape("K", self.K, (3, 3))
        self.config = config or StructureConfig()
        self._detector = _sift(self.config.max_features)

    def locate(self, query: Any, candidates: Sequence[int]) -> StructurePose:
        """Localise ``query`` (RGB ``(H, W, 3)`` or grey ``(H, W)``) on the points of the base
        images ``candidates`` (their indices, e.g. the retrieval's matches)."""
        import cv2

        cfg = self.config
        uv_q, d_q = detect(query, self._detector)
        s = self.structure
        obj, img = [], []
        for i in dict.fromkeys(int(c) for c in candidates):  # unique, in order
            rows = np.flatnonzero(s.image == i)
            for q, t in ratio_matches(d_q, s.descriptors[rows], cfg.ratio):
                obj.append(s.xyz[rows[t]])
                img.append(uv_q[q])
        n = len(obj)
        if n < max(6, cfg.min_inliers):
            return StructurePose(False, None, None, n, reason=f"{n} 2D-3D matches")
        obj_a, img_a = np.asarray(obj), np.asarray(img)
        try:
            found, rvec, tvec, inliers = cv2.solvePnPRansac(
                obj_a, img_a, self.K, None, reprojectionError=cfg.pnp_px,
                iterationsCount=1000, confidence=0.999, flags=cv2.SOLVEPNP_EPNP,
            )  # fmt: skip
        except cv2.error as err:  # degenerate point sets (all on one line, ...)
            return StructurePose(False, None, None, n, reason=f"PnP failed: {err.err}")
        n_in = 0 if inliers is None else len(inliers)
        if not found or n_in < cfg.min_inliers:
            return StructurePose(
                False, None, None, n, n_in, reason=f"{n_in} PnP inliers < {cfg.min_inliers}"
            )
        inl = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj_a[inl], img_a[inl], self.K, None, rvec, tvec)
        R_cw = cv2.Rodrigues(rvec)[0]
        R_wc, t_wc = R_cw.T, -R_cw.T @ tvec.ravel()
        _, err = _reprojection_px(self.K, R_wc, t_wc, obj_a[inl], img_a[inl])
        return StructurePose(True, R_wc, t_wc, n, n_in, float(np.sqrt(np.mean(err**2))))
