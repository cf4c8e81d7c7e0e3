"""The COLMAP peer of the image-SLAM benchmark: incremental SfM through ``pycolmap``.

What a user with a calibrated camera and a GPS would do with COLMAP on a drive's keyframes:

1. :func:`reconstruct`: write the images (``work_dir/images/000000.png``, ... in time order),
   extract SIFT features (COLMAP defaults) with one shared ``PINHOLE`` camera holding the known
   ``K``, match them sequentially (each image with its ``overlap`` successors, no loop
   detection: no vocabulary tree offline), run COLMAP's incremental mapper with the
   intrinsics held fixed, keep the largest model. Poses come back camera-to-world
   (``R_wc``, ``t_wc``, OpenCV camera frame, as COLMAP's) in COLMAP's arbitrary frame.
2. :func:`align_to_gps`: the least-squares similarity that maps the registered optical centres
   onto the GPS targets (:func:`slam_bridge.slam.initialization.fit_similarity`, with the
   cameras' mean ``-y`` axis pinned to the world's ``+z``, as our SLAM georeferences), applied
   to every registered pose. Plain least squares by default; ``max_error_m`` makes it robust
   (RANSAC, like COLMAP's ``model_aligner --alignment_max_error``), so that one image that
   COLMAP registered wildly does not drag the whole trajectory.
3. :func:`colmap_peer`: both, timed, as a :class:`ColmapResult`.

Typical use in a benchmark::

    res = colmap_peer(rgb_frames, K, tmp / "colmap", targets_w)  # targets (N, 3), NaN: no fix
    ok = res.registered
    err_t = np.linalg.norm(res.t_wc[ok] - gt_t_wc[ok], axis=1)
    print(res.wall_seconds, res.seconds, ok.mean())
    # another alignment of the same reconstruction, without rerunning COLMAP:
    robust = align_to_gps(res.raw.R_wc, res.raw.t_wc, targets_w, max_error_m=5.0)

Determinism: COLMAP's random generators are seeded (``seed``) and, by default, every stage
runs on one thread (``threads=1``), which makes two runs give identical poses; more threads
are faster but COLMAP's multi-threaded stages are not guaranteed to repeat bit for bit.

Needs the ``bench`` extra (``pip install geoseg[bench]``) for ``pycolmap``.
"""

import contextlib
import logging
import shutil
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geoseg.errors import check_finite, check_positive, check_shape
from slam_bridge.errors import SlamError
from slam_bridge.slam.initialization import fit_similarity

logger = logging.getLogger(__name__)

__all__ = [
    "ColmapReconstruction",
    "ColmapResult",
    "GpsAlignment",
    "align_to_gps",
    "colmap_peer",
    "reconstruct",
]

IMAGE_DIR = "images"
DATABASE = "database.db"
SPARSE_DIR = "sparse"


def _pycolmap():
    try:
        import pycolmap
    except ImportError as err:  # an optional extra
        raise SlamError(
            "the COLMAP peer needs pycolmap: pip install geoseg[bench] (or pip install pycolmap)"
        ) from err
    return pycolmap


@dataclass
class ColmapReconstruction:
    """COLMAP's poses of a sequence, in COLMAP's own frame (arbitrary similarity).

    Attributes:
        R_wc: ``(N, 3, 3)`` camera-to-world rotations (OpenCV camera frame), NaN where the
            image is not registered.
        t_wc: ``(N, 3)`` optical centres, NaN where not registered.
        registered: ``(N,)`` bool, the image is in the model used.
        num_models: models COLMAP produced (the largest one is used).
        num_points: 3D points of the model used.
        seconds: per stage: ``write`` (PNG files), ``extract``, ``match``, ``map``.
        wall_seconds: ``extract + match + map`` (``time.perf_counter``, one process).
        model_dir: the folder of the model used (COLMAP's binary format).
        options: the COLMAP options used (``name -> value``), for the record.
    """

    R_wc: np.ndarray
    t_wc: np.ndarray
    registered: np.ndarray
    num_models: int
    num_points: int
    seconds: dict[str, float]
    wall_seconds: float
    model_dir: Path
    options: dict = field(default_factory=dict)


@dataclass
class GpsAlignment:
    """Poses mapped by a similarity ``X_world = s R X_colmap + T``.

    Attributes:
        R_wc: ``(N, 3, 3)`` aligned camera-to-world rotations (``R @ R_wc``), NaN rows kept.
        t_wc: ``(N, 3)`` aligned optical centres (``s R t_wc + T``), NaN rows kept.
        s: scale.
        R: ``(3, 3)`` rotation.
        T: ``(3,)`` translation.
        used: ``(N,)`` bool, the poses that entered the fit (registered, with a target, and
            within ``max_error_m`` when the fit is robust).
        rms_m: root mean square distance of the fitted centres to their targets, metres.
    """

    R_wc: np.ndarray
    t_wc: np.ndarray
    s: float
    R: np.ndarray
    T: np.ndarray
    used: np.ndarray
    rms_m: float


@dataclass
class ColmapResult:
    """The peer's output: GPS-aligned poses and what it cost.

    Attributes:
        R_wc: ``(N, 3, 3)`` camera-to-world rotations in the GPS-aligned world frame, NaN
            where not registered.
        t_wc: ``(N, 3)`` optical centres, same frame, NaN where not registered.
        registered: ``(N,)`` bool.
        num_models: models COLMAP produced (the largest one is used).
        num_points: 3D points of the model used.
        wall_seconds: extraction + matching + mapping (not the PNG writing nor the alignment),
            one process, ``time.perf_counter``.
        seconds: per stage: ``write``, ``extract``, ``match``, ``map``, ``align``.
        alignment: the similarity and its fit residual.
        raw: COLMAP's poses before the alignment (to realign them without rerunning COLMAP).
    """

    R_wc: np.ndarray
    t_wc: np.ndarray
    registered: np.ndarray
    num_models: int
    num_points: int
    wall_seconds: float
    seconds: dict[str, float]
    alignment: GpsAlignment
    raw: ColmapReconstruction


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    check_shape("K", K, (3, 3))
    check_finite("K", K)
    if not (K[0, 0] > 0 and K[1, 1] > 0) or K[0, 1] != 0 or not np.allclose(K[2], [0, 0, 1]):
        raise SlamError(
            f"K: expected a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
            f"got {K.tolist()}"
        )
    return K


def _stage_images(images: Sequence, image_dir: Path) -> list[str]:
    """Write arrays as PNG (or copy files) to ``image_dir`` under names sorting in time order.

    Returns:
        The ``N`` file names, in the order of ``images``.
    """
    import cv2

    image_dir.mkdir(parents=True, exist_ok=True)
    names, size = [], None
    for i, img in enumerate(images):
        if isinstance(img, str | Path):
            src = Path(img)
            if not src.is_file():
                raise SlamError(f"images[{i}]: no such file {src}")
            name = f"{i:06d}{src.suffix.lower()}"
            shutil.copyfile(src, image_dir / name)
        else:
            arr = np.asarray(img)
            check_shape(f"images[{i}]", arr, (None, None, 3))
            if arr.dtype != np.uint8:
                raise SlamError(f"images[{i}]: expected uint8 RGB, got {arr.dtype}")
            hw = arr.shape[:2]
            if size is not None and hw != size:
                raise SlamError(f"images[{i}]: size {hw} differs from the first image's {size}")
            size = hw
            name = f"{i:06d}.png"
            if not cv2.imwrite(str(image_dir / name), np.ascontiguousarray(arr[..., ::-1])):
                raise SlamError(f"images[{i}]: could not write {image_dir / name}")
        names.append(name)
    return names


@contextlib.contextmanager
def _colmap_log_level(pycolmap, level: int) -> Iterator[None]:
    """COLMAP's (glog) minimum log level for the duration of the block."""
    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = level
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


@contextlib.contextmanager
def _colmap_stage(stage: str) -> Iterator[None]:
    """COLMAP's failed checks (``ValueError``/``RuntimeError``) as a :class:`SlamError`."""
    try:
        yield
    except (RuntimeError, ValueError) as err:
        raise SlamError(f"COLMAP {stage} failed: {err}") from err


def reconstruct(
    images: Sequence[np.ndarray] | Sequence[str | Path],
    K: np.ndarray,
    work_dir: str | Path,
    *,
    overlap: int = 10,
    threads: int = 1,
    seed: int = 0,
    colmap_log: bool = False,
) -> ColmapReconstruction:
    """COLMAP incremental SfM of an image sequence with known, fixed pinhole intrinsics.

    Args:
        images: ``N`` images in time order: ``(H, W, 3)`` uint8 RGB arrays (written as PNG to
            ``work_dir/images``) or image files (copied there, renamed in order).
        K: ``(3, 3)`` pinhole intrinsics shared by all images (OpenCV pixel convention,
            centre of the top-left pixel at ``(0, 0)``; COLMAP's ``+0.5`` is added here), no
            distortion. Kept fixed during mapping.
        work_dir: COLMAP's folder: ``images/``, ``database.db``, ``sparse/`` (a database and a
            ``sparse/`` left there by an earlier run are replaced).
        overlap: sequential matching: each image is matched with its ``overlap`` successors
            (COLMAP's quadratic overlap adds ``2^k`` successors too, its default).
        threads: threads of every stage (1: deterministic and kind to a shared machine).
        seed: COLMAP's random seed (RANSAC, mapper).
        colmap_log: let COLMAP log at INFO (default: warnings and errors only).

    Returns:
        The poses of the largest model, in COLMAP's frame, with timings.

    Raises:
        SlamError: bad inputs, or COLMAP reconstructed no model.
    """
    pycolmap = _pycolmap()
    K = _check_K(K)
    if isinstance(overlap, bool) or not isinstance(overlap, int) or overlap < 1:
        raise SlamError(f"overlap: expected an int >= 1, got {overlap!r}")
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise SlamError(f"threads: expected an int >= 1, got {threads!r}")
    if len(images) < 2:
        raise SlamError(f"images: expected at least 2 images, got {len(images)}")
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    database, sparse = work / DATABASE, work / SPARSE_DIR
    database.unlink(missing_ok=True)
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir()
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    names = _stage_images(images, work / IMAGE_DIR)
    seconds["write"] = time.perf_counter() - t0
    n = len(names)

    # one PINHOLE camera, COLMAP's pixel convention (top-left pixel centre at (0.5, 0.5))
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
    reader.camera_params = ",".join(repr(float(v)) for v in (fx, fy, cx, cy))
    extraction = pycolmap.FeatureExtractionOptions()  # SIFT, COLMAP defaults
    extraction.num_threads = threads
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = overlap
    pairing.loop_detection = False
    pairing.num_threads = threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    mapping = pycolmap.IncrementalPipelineOptions()  # defaults, intrinsics fixed
    mapping.num_threads = threads
    mapping.random_seed = seed
    mapping.ba_refine_focal_length = False
    mapping.ba_refine_principal_point = False
    mapping.ba_refine_extra_params = False
    options = {
        "camera": f"PINHOLE {reader.camera_params}",
        "sift_max_num_features": extraction.sift.max_num_features,
        "overlap": overlap,
        "quadratic_overlap": pairing.quadratic_overlap,
        "loop_detection": False,
        "threads": threads,
        "seed": seed,
        "refine_intrinsics": False,
        "multiple_models": mapping.multiple_models,
    }
    pycolmap.set_random_seed(seed)

    with _colmap_log_level(pycolmap, 0 if colmap_log else 1):
        t0 = time.perf_counter()
        with _colmap_stage("feature extraction"):
            pycolmap.extract_features(
                database,
                work / IMAGE_DIR,
                image_names=names,
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
        t1 = time.perf_counter()
        with _colmap_stage("sequential matching"):
            pycolmap.match_sequential(
                database,
                matching_options=matching,
                pairing_options=pairing,
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        t2 = time.perf_counter()
        with _colmap_stage("incremental mapping"):
            models = pycolmap.incremental_mapping(
                database, work / IMAGE_DIR, sparse, options=mapping
            )
        t3 = time.perf_counter()
    seconds.update(extract=t1 - t0, match=t2 - t1, map=t3 - t2)
    wall = t3 - t0
    logger.info(
        "COLMAP: %d images, %d model(s), extract %.2f s, match %.2f s, map %.2f s",
        n,
        len(models),
        *(seconds[k] for k in ("extract", "match", "map")),
    )
    if len(models) == 0:
        raise SlamError(
            f"COLMAP registered no model from {n} images (too few verified matches to start: "
            f"check the overlap between images and the intrinsics)"
        )
    key = max(models, key=lambda k: (models[k].num_reg_images(), models[k].num_points3D()))
    rec = models[key]

    index = {name: i for i, name in enumerate(names)}
    R_wc = np.full((n, 3, 3), np.nan)
    t_wc = np.full((n, 3), np.nan)
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        i = index[image.name]
        cam_from_world = image.cam_from_world()  # world -> camera: X_c = R_cw X_w + t_cw
        R_cw = np.asarray(cam_from_world.rotation.matrix(), dtype=np.float64)
        t_cw = np.asarray(cam_from_world.translation, dtype=np.float64).reshape(3)
        R_wc[i] = R_cw.T
        t_wc[i] = -R_cw.T @ t_cw
    registered = np.isfinite(t_wc[:, 0])
    logger.info(
        "COLMAP: the largest model registers %d/%d images, %d points",
        int(registered.sum()),
        n,
        rec.num_points3D(),
    )
    return ColmapReconstruction(
        R_wc=R_wc,
        t_wc=t_wc,
        registered=registered,
        num_models=len(models),
        num_points=int(rec.num_points3D()),
        seconds=seconds,
        wall_seconds=wall,
        model_dir=sparse / str(key),
        options=options,
    )


def align_to_gps(
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    targets_w: np.ndarray,
    *,
    up_axis: bool = True,
    up_weight: float = 1.0,
    antenna_c: np.ndarray | None = None,
    max_error_m: float | None = None,
    min_targets: int = 3,
    ransac_trials: int = 200,
) -> GpsAlignment:
    """Map poses onto GPS targets by the least-squares similarity of their optical centres.

    The similarity ``(s, R, T)`` minimises ``sum |s R t_wc[i] + T - targets_w[i]|^2`` over the
    poses that are finite and have a finite target (:func:`fit_similarity`); with ``up_axis``
    the mean ``-y`` axis of all finite poses (a level vehicle camera's up) is also pulled onto
    the world's ``+z`` (weight ``up_weight``), which pins the roll of a straight drive, as our
    SLAM's georeferencing does. Every finite pose is then mapped: ``R_wc' = R R_wc``,
    ``t_wc' = s R t_wc + T``.

    With ``max_error_m`` the fit is robust, like COLMAP's ``model_aligner
    --alignment_max_error``: a RANSAC over triples of centres (deterministic) keeps the largest
    set within ``max_error_m`` of their targets, then the least-squares fit is refined on that
    set until it stops changing; poses outside it (e.g. an image COLMAP registered wildly) are
    still mapped but not fitted.

    Args:
        R_wc: ``(N, 3, 3)`` camera-to-world rotations, NaN rows for missing poses.
        t_wc: ``(N, 3)`` optical centres, NaN rows for missing poses.
        targets_w: ``(N, 3)`` world positions of the optical centres (GPS fixes, z from a DEM
            plus the camera height), NaN rows where there is no fix.
        up_axis: pin the cameras' mean ``-y`` axis to ``+z``.
        up_weight: its weight against the positions (see :func:`fit_similarity`).
        antenna_c: ``(3,)`` the GPS antenna in the camera frame when the targets' xy are the
            antenna's (their z stays the camera's, as in the SLAM's start-up); None: the
            targets are the optical centres.
        max_error_m: inlier distance of the robust fit, metres; None: plain least squares over
            all poses with a target.
        min_targets: fewest poses with a target (inliers, when robust) the fit accepts.
        ransac_trials: triples drawn by the robust fit.

    Returns:
        The aligned poses, the similarity, the poses fitted and their residual.

    Raises:
        SlamError: bad shapes, fewer than ``min_targets`` registered poses with a target (or
            inliers), or a degenerate configuration (all centres at one point).
    """
    R_wc = np.asarray(R_wc, dtype=np.float64)
    t_wc = np.asarray(t_wc, dtype=np.float64)
    targets_w = np.asarray(targets_w, dtype=np.float64)
    check_shape("R_wc", R_wc, (None, 3, 3))
    n = R_wc.shape[0]
    check_shape("t_wc", t_wc, (n, 3))
    check_shape("targets_w", targets_w, (n, 3))
    if isinstance(min_targets, bool) or not isinstance(min_targets, int) or min_targets < 2:
        raise SlamError(f"min_targets: expected an int >= 2, got {min_targets!r}")
    if max_error_m is not None:
        check_positive("max_error_m", max_error_m)
    posed = np.isfinite(t_wc).all(axis=1) & np.isfinite(R_wc).all(axis=(1, 2))
    candidates = posed & np.isfinite(targets_w).all(axis=1)
    if candidates.sum() < min_targets:
        raise SlamError(
            f"align_to_gps: {int(candidates.sum())} registered pose(s) with a GPS target "
            f"({int(posed.sum())} registered, {int(np.isfinite(targets_w).all(axis=1).sum())} "
            f"targets), at least {min_targets} needed"
        )
    up_src = -np.mean(R_wc[posed][:, :, 1], axis=0) if up_axis else None
    if up_src is not None and np.linalg.norm(up_src) < 1e-9:
        raise SlamError("align_to_gps: the cameras' -y axes cancel out (no up direction)")
    offset_c = None
    if antenna_c is not None:
        offset_c = np.asarray(antenna_c, dtype=np.float64)
        check_shape("antenna_c", offset_c, (3,))
        check_finite("antenna_c", offset_c)

    def offsets(R: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """``(len(idx), 3)`` antenna minus optical centre, world xy (z: the camera's)."""
        out = np.zeros((idx.size, 3))
        if offset_c is not None:
            out[:, :2] = np.einsum("ij,kjl,l->ki", R, R_wc[idx], offset_c)[:, :2]
        return out

    def fit(idx: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        s, R, T = fit_similarity(t_wc[idx], targets_w[idx], up_src=up_src, up_weight=up_weight)
        for _ in range(0 if offset_c is None else 50):  # the offset depends on the rotation
            R_old = R
            s, R, T = fit_similarity(
                t_wc[idx], targets_w[idx] - offsets(R, idx), up_src=up_src, up_weight=up_weight
            )
            if np.abs(R - R_old).max() < 1e-13:
                break
        return s, R, T

    cand = np.flatnonzero(candidates)

    def residuals(s: float, R: np.ndarray, T: np.ndarray) -> np.ndarray:
        """``(len(cand),)`` distances of the mapped antennas to their targets."""
        mapped = s * t_wc[cand] @ R.T + T + offsets(R, cand)
        return np.linalg.norm(mapped - targets_w[cand], axis=1)

    if max_error_m is None:
        fitted = cand
        s, R, T = fit(fitted)
    else:
        rng = np.random.default_rng(0)
        best, best_score = None, None
        for _ in range(ransac_trials):
            sample = np.sort(rng.choice(cand, size=3, replace=False))
            try:
                model = fit(sample)
            except SlamError:  # coincident centres
                continue
            r = residuals(*model)
            score = (int(np.sum(r < max_error_m)), -float(np.sum(np.minimum(r, max_error_m))))
            if best_score is None or score > best_score:
                best, best_score = r < max_error_m, score
        inliers = cand[best] if best is not None else cand[:0]
        for _ in range(20):  # refine on the inliers until the set stops changing
            if inliers.size < min_targets:
                raise SlamError(
                    f"align_to_gps: {inliers.size} of {cand.size} registered poses with a "
                    f"GPS target lie within max_error_m={max_error_m} m of a similarity, at "
                    f"least {min_targets} needed"
                )
            s, R, T = fit(inliers)
            fitted = inliers
            new = cand[residuals(s, R, T) < max_error_m]
            if np.array_equal(new, inliers):
                break
            inliers = new
    used = np.zeros(n, dtype=bool)
    used[fitted] = True
    R_out = np.full_like(R_wc, np.nan)
    t_out = np.full_like(t_wc, np.nan)
    R_out[posed] = R @ R_wc[posed]
    t_out[posed] = s * t_wc[posed] @ R.T + T
    r = residuals(s, R, T)[np.isin(cand, fitted)]
    rms = float(np.sqrt(np.mean(r**2)))
    return GpsAlignment(R_wc=R_out, t_wc=t_out, s=s, R=R, T=T, used=used, rms_m=rms)


def colmap_peer(
    images: Sequence[np.ndarray] | Sequence[str | Path],
    K: np.ndarray,
    work_dir: str | Path,
    targets_w: np.ndarray,
    *,
    up_axis: bool = True,
    antenna_c: np.ndarray | None = None,
    max_error_m: float | None = None,
    overlap: int = 10,
    threads: int = 1,
    seed: int = 0,
    colmap_log: bool = False,
) -> ColmapResult:
    """COLMAP's incremental SfM of a sequence, aligned to the GPS as a user would.

    :func:`reconstruct` then :func:`align_to_gps` (see them for the arguments).

    Args:
        images: ``N`` images in time order, ``(H, W, 3)`` uint8 RGB arrays or files.
        K: ``(3, 3)`` shared pinhole intrinsics, held fixed.
        work_dir: COLMAP's folder.
        targets_w: ``(N, 3)`` GPS targets of the optical centres, NaN rows where no fix.
        up_axis: pin the cameras' mean ``-y`` axis to the world's ``+z`` in the alignment.
        antenna_c: ``(3,)`` GPS antenna in the camera frame (None: at the optical centre).
        max_error_m: robust alignment's inlier distance, metres (None: plain least squares).
        overlap: sequential matching overlap.
        threads: threads of every COLMAP stage.
        seed: COLMAP's random seed.
        colmap_log: let COLMAP log at INFO.

    Returns:
        The aligned poses (NaN where not registered), model figures and timings.

    Raises:
        SlamError: bad inputs, no model, or fewer than 3 registered images with a target.
    """
    targets_w = np.asarray(targets_w, dtype=np.float64)
    check_shape("targets_w", targets_w, (len(images), 3))
    rec = reconstruct(
        images, K, work_dir, overlap=overlap, threads=threads, seed=seed, colmap_log=colmap_log
    )
    t0 = time.perf_counter()
    aligned = align_to_gps(
        rec.R_wc,
        rec.t_wc,
        targets_w,
        up_axis=up_axis,
        antenna_c=antenna_c,
        max_error_m=max_error_m,
    )
    seconds = dict(rec.seconds, align=time.perf_counter() - t0)
    logger.info("COLMAP aligned to %d GPS targets: rms %.3f m", aligned.used.sum(), aligned.rms_m)
    return ColmapResult(
        R_wc=aligned.R_wc,
        t_wc=aligned.t_wc,
        registered=rec.registered,
        num_models=rec.num_models,
        num_points=rec.num_points,
        wall_seconds=rec.wall_seconds,
        seconds=seconds,
        alignment=aligned,
        raw=rec,
    )
