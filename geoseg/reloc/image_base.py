"""A georeferenced image base on disk: images, their poses, cached embeddings (thesis §5.1).

Layout of a base directory::

    BASE_DIR/
      poses.csv          one row per image: image, timestamp, tx, ty, tz, r00 .. r22
      camera.json        optional intrinsics: {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]} or
                         {"fx": ..., "fy": ..., "cx": ..., "cy": ...}, and the image size
                         they hold for: "image_size": [W, H] (or "width", "height")
      <images>           PNG/JPEG/... files, anywhere under BASE_DIR (sub-folders allowed)
      cache/             written by ImageBase.embeddings: embeddings_<name>.npz

``poses.csv`` (header required, any order, extra columns ignored): ``image`` relative to
``BASE_DIR`` (POSIX separators), ``timestamp`` (seconds, may be empty), the camera centre
``t_wc`` (metres, world frame) and the camera-to-world rotation ``R_wc`` row by row, optional
``lat, lon`` (kept for display). :func:`load_image_base` validates everything up front and raises
:class:`~geoseg.errors.GeosegError` naming the problem. Intrinsics hold for one image size:
every base image must have the size ``camera.json`` gives, and :func:`check_image_size` is the
guard wherever an image meets a camera matrix (a resized image with the original ``K`` gives
confidently wrong poses).

Embeddings are injected: ``embed_fn(images) -> (B, D)`` maps ``B`` RGB uint8 ``(H, W, 3)``
images to their embeddings; an optional ``name`` attribute enables the on-disk cache. Provided
here: :class:`ThumbnailEmbedder` (a grey thumbnail: a **placeholder, not the learned
embedding**, for tests; it finds near-duplicates only), :func:`raw_layer21_embedder` (the
§5.1.1 baseline), :class:`HeadEmbedder` (the learned embedding of eq. 5.1) and
:func:`layer21_features` (image -> ``(C, h, w)`` features, for the relative-pose head and
:class:`geoseg.data.pairs.TripletDataset`).
"""

from __future__ import annotations

import csv
import json
import logging
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoseg.atomic import atomic_output
from geoseg.errors import GeosegError, check_finite, check_shape
from geoseg.reloc.retrieval import RetrievalIndex

logger = logging.getLogger(__name__)

__all__ = [
    "CAMERA_FILE",
    "HeadEmbedder",
    "IMAGE_EXTENSIONS",
    "ImageBase",
    "Layer21Embedder",
    "POSES_FILE",
    "POSE_COLUMNS",
    "ThumbnailEmbedder",
    "check_image_size",
    "layer21_features",
    "load_camera",
    "load_image_base",
    "raw_layer21_embedder",
    "read_camera",
    "read_rgb",
    "write_poses_csv",
]

POSES_FILE = "poses.csv"
CAMERA_FILE = "camera.json"
CACHE_DIR = "cache"
ROTATION_COLUMNS = tuple(f"r{i}{j}" for i in range(3) for j in range(3))
POSE_COLUMNS = ("image", "timestamp", "tx", "ty", "tz", *ROTATION_COLUMNS)
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".webp")
_ROTATION_TOL = 1e-3

EmbedFn = Callable[[Sequence[np.ndarray]], Any]


# ============================================================================ files


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as RGB uint8 ``(H, W, 3)``.

    Raises:
        GeosegError: missing or unreadable file (naming it).
    """
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise GeosegError(f"{path}: missing or unreadable image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def write_poses_csv(
    path: str | os.PathLike,
    images: Sequence[str],
    R_wc: Any,
    t_wc: Any,
    *,
    timestamps: Any = None,
    latlon: Any = None,
) -> Path:
    """Write a ``poses.csv`` (see the module docstring for the columns).

    Args:
        path: output file (parent directories created).
        images: ``M`` image paths relative to the base directory.
        R_wc: ``(M, 3, 3)`` camera-to-world rotations.
        t_wc: ``(M, 3)`` camera centres (world frame, metres).
        timestamps: ``(M,)`` seconds, or None (empty column).
        latlon: ``(M, 2)`` WGS84 degrees, or None (no ``lat, lon`` columns).

    Returns:
        The written path.
    """
    m = len(images)
    R = np.asarray(R_wc, dtype=np.float64)
    t = np.asarray(t_wc, dtype=np.float64)
    check_shape("R_wc", R, (m, 3, 3))
    check_shape("t_wc", t, (m, 3))
    ts = None if timestamps is None else np.asarray(timestamps, dtype=np.float64)
    if ts is not None:
        check_shape("timestamps", ts, (m,))
    ll = None if latlon is None else np.asarray(latlon, dtype=np.float64)
    if ll is not None:
        check_shape("latlon", ll, (m, 2))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = list(POSE_COLUMNS) + (["lat", "lon"] if ll is not None else [])
    with atomic_output(path, "w") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for i, name in enumerate(images):
            row = [str(name), "" if ts is None else repr(float(ts[i]))]
            row += [repr(float(v)) for v in t[i]] + [repr(float(v)) for v in R[i].ravel()]
            if ll is not None:
                row += [repr(float(v)) for v in ll[i]]
            writer.writerow(row)
    return path


def load_camera(path: str | os.PathLike) -> np.ndarray:
    """Read intrinsics from a ``camera.json`` (``{"K": 3x3}`` or ``fx, fy, cx, cy``).

    Returns:
        ``(3, 3)`` float64 ``K``.
    """
    return read_camera(path)[0]


def read_camera(path: str | os.PathLike) -> tuple[np.ndarray, tuple[int, int] | None]:
    """Read a ``camera.json``: intrinsics and the image size they hold for.

    Returns:
        ``(K (3, 3) float64, (W, H) or None)``: the size from ``"image_size": [W, H]`` or
        ``"width"``/``"height"`` when given.

    Raises:
        GeosegError: unreadable file, bad intrinsics, a bad size, or a principal point outside
            the image.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise GeosegError(f"{path}: unreadable camera file ({err})") from None
    if not isinstance(data, dict):
        raise GeosegError(f"{path}: expected a JSON object, got {type(data).__name__}")
    try:
        if "K" in data:
            K = np.asarray(data["K"], dtype=np.float64)
        else:
            K = np.array(
                [
                    [float(data["fx"]), 0.0, float(data["cx"])],
                    [0.0, float(data["fy"]), float(data["cy"])],
                    [0.0, 0.0, 1.0],
                ]
            )
    except (KeyError, TypeError, ValueError) as err:
        raise GeosegError(
            f"{path}: expected {{'K': [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]}} or "
            f"{{'fx', 'fy', 'cx', 'cy'}} ({type(err).__name__}: {err})"
        ) from None
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise GeosegError(f"{path}: invalid intrinsics {K.tolist()}")
    raw = data.get("image_size")
    if raw is None and ("width" in data or "height" in data):
        raw = [data.get("width"), data.get("height")]
    size = None
    if raw is not None:
        if (
            not isinstance(raw, list | tuple)
            or len(raw) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in raw)
        ):
            raise GeosegError(f"{path}: image_size: expected [W, H] positive integers, got {raw!r}")
        size = (int(raw[0]), int(raw[1]))
        if not (0 <= K[0, 2] <= size[0] and 0 <= K[1, 2] <= size[1]):
            raise GeosegError(
                f"{path}: principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the "
                f"{size[0]}x{size[1]} image the file declares"
            )
    return K, size


def check_image_size(
    name: str, image: np.ndarray, size: tuple[int, int] | None, source: str
) -> None:
    """Raise unless an `(H, W, ...)` ``image`` is ``size = (W, H)`` pixels (None: no check).

    Args:
        name: the image, for the message (e.g. ``"query q.png"``).
        image: the image array.
        size: the size the intrinsics hold for.
        source: where that size comes from (e.g. ``"BASE/camera.json"``).

    Raises:
        GeosegError: naming both sizes and what to do.
    """
    if size is None:
        return
    h, w = np.asarray(image).shape[:2]
    if (w, h) != tuple(size):
        raise GeosegError(
            f"{name}: {w}x{h} pixels, but the intrinsics ({source}) hold for {size[0]}x{size[1]} "
            "images: resize it to that size (or crop it back), or give intrinsics for its size"
        )


def _fmt_names(names: Sequence[str], limit: int = 5) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _image_files(root: Path) -> list[str]:
    """Image files under ``root`` (relative POSIX paths), skipping hidden and cache folders."""
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = Path(dirpath).relative_to(root)
        dirnames[:] = sorted(
            d
            for d in dirnames
            if not d.startswith(".") and not (rel_dir == Path(".") and d == CACHE_DIR)
        )
        for fn in sorted(filenames):
            if not fn.startswith(".") and fn.lower().endswith(IMAGE_EXTENSIONS):
                out.append((rel_dir / fn).as_posix())
    return out


def _number(value: str | None, where: str, column: str, *, allow_empty: bool = False) -> float:
    text = (value or "").strip()
    if not text:
        if allow_empty:
            return float("nan")
        raise GeosegError(f"{where}: column {column!r} is empty")
    try:
        x = float(text)
    except ValueError:
        raise GeosegError(f"{where}: column {column!r} is not a number ({text!r})") from None
    if not np.isfinite(x):
        raise GeosegError(f"{where}: column {column!r} is not finite ({text!r})")
    return x


# ============================================================================ the base


@dataclass
class ImageBase:
    """A loaded georeferenced image base (see :func:`load_image_base`).

    Attributes:
        root: the base directory.
        images: ``M`` image paths relative to ``root``.
        timestamps: ``(M,)`` float64 seconds (NaN when not given).
        R_wc: ``(M, 3, 3)`` float64 camera-to-world rotations.
        t_wc: ``(M, 3)`` float64 camera centres in the world frame (metres).
        latlon: ``(M, 2)`` float64 WGS84 degrees, or None.
        K: ``(3, 3)`` intrinsics from ``camera.json``, or None.
        image_size: ``(W, H)`` the intrinsics hold for (``camera.json``), or None; every base
            image is checked against it when loaded.
    """

    root: Path
    images: list[str]
    timestamps: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    latlon: np.ndarray | None = None
    K: np.ndarray | None = None
    image_size: tuple[int, int] | None = None

    def __len__(self) -> int:
        return len(self.images)

    @property
    def positions(self) -> np.ndarray:
        """``(M, 2)`` horizontal positions (``tx, ty``) used by the GPS window."""
        return self.t_wc[:, :2]

    def path(self, i: int) -> Path:
        """Absolute path of image ``i``."""
        return self.root / self.images[i]

    def load_image(self, i: int) -> np.ndarray:
        """Image ``i`` as RGB uint8 ``(H, W, 3)``.

        Raises:
            GeosegError: unreadable, or not of the size ``camera.json`` declares.
        """
        image = read_rgb(self.path(i))
        check_image_size(f"base image {self.images[i]}", image, self.image_size, CAMERA_FILE)
        return image

    def fingerprints(self) -> np.ndarray:
        """``(M, 2)`` int64 (size in bytes, mtime in ns) of each image file."""
        out = np.empty((len(self), 2), dtype=np.int64)
        for i in range(len(self)):
            st = self.path(i).stat()
            out[i] = (st.st_size, st.st_mtime_ns)
        return out

    def cache_path(self, name: str) -> Path:
        """The ``.npz`` cache file of the embedding called ``name``."""
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "embedding"
        return self.root / CACHE_DIR / f"embeddings_{safe}.npz"

    def _read_cache(self, path: Path, fingerprints: np.ndarray) -> tuple[np.ndarray | None, bool]:
        """``(embeddings or None, whether the file may be (over)written)``: a missing or stale
        cache is rewritten; a file that is not a readable cache is someone else's and kept."""
        if not path.is_file():
            return None, True
        try:
            with np.load(path, allow_pickle=False) as z:
                images = [str(s) for s in z["images"]]
                fp = z["fingerprints"]
                emb = z["embeddings"]
        except Exception as err:  # never fatal: recomputed, and the file is left alone
            logger.warning("%s: not a readable embedding cache (%s); recomputing", path, err)
            return None, False
        if images != self.images or fp.shape != fingerprints.shape or (fp != fingerprints).any():
            logger.info("%s: stale embedding cache (images changed); recomputing", path)
            return None, True
        if emb.ndim != 2 or emb.shape[0] != len(self) or not np.isfinite(emb).all():
            return None, True
        return emb, True

    def _write_cache(self, path: Path, emb: np.ndarray, fingerprints: np.ndarray) -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_output(path, fsync=False) as handle:
                np.savez(
                    handle,
                    embeddings=emb,
                    images=np.asarray(self.images, dtype=str),
                    fingerprints=fingerprints,
                )
        except OSError as err:
            logger.warning("%s: could not write the embedding cache (%s)", path, err)

    def embeddings(
        self, embed_fn: EmbedFn, *, batch_size: int = 16, cache: bool = True
    ) -> np.ndarray:
        """Embed every base image (or read them from the cache).

        Args:
            embed_fn: ``embed_fn(images) -> (B, D)``, ``images`` a list of RGB uint8
                ``(H, W, 3)`` arrays; its ``name`` attribute (if any) keys the cache.
            batch_size: images per ``embed_fn`` call.
            cache: read/write ``cache/embeddings_<name>.npz`` (only when ``embed_fn.name``
                exists); the cache is invalidated when any image file changes.

        Returns:
            ``(M, D)`` float64 embeddings.

        Raises:
            GeosegError: ``embed_fn`` returns a wrong shape, NaN, or embeddings of different
                sizes for different images (naming the images).
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise GeosegError(f"batch_size: expected an int >= 1, got {batch_size!r}")
        name = getattr(embed_fn, "name", None)
        fingerprints = self.fingerprints()
        cpath = self.cache_path(str(name)) if (cache and name) else None
        if cpath is not None:
            emb, writable = self._read_cache(cpath, fingerprints)
            if emb is not None:
                logger.info("embeddings of %d base images read from %s", len(self), cpath)
                return emb
            cpath = cpath if writable else None
        from tqdm import tqdm

        chunks: list[np.ndarray] = []
        starts = range(0, len(self), batch_size)
        for s in tqdm(starts, desc="embedding base images", unit="batch", disable=None):
            names = self.images[s : s + batch_size]
            batch = [self.load_image(i) for i in range(s, s + len(names))]
            try:
                out = _as_embeddings(embed_fn(batch), len(batch))
            except GeosegError as err:
                for name, image in zip(names, batch):  # name the image that fails
                    try:
                        _as_embeddings(embed_fn([image]), 1)
                    except GeosegError as one:
                        raise GeosegError(f"base image {name}: {one}") from None
                raise GeosegError(f"base images {_fmt_names(names)}: {err}") from None
            if chunks and out.shape[1] != chunks[0].shape[1]:
                raise GeosegError(
                    f"base images {_fmt_names(names)}: embedding size {out.shape[1]} differs "
                    f"from {chunks[0].shape[1]} for {self.images[0]} (feature maps of "
                    "mismatched sizes: images of different sizes?)"
                )
            chunks.append(out)
        emb = np.concatenate(chunks, axis=0)
        if cpath is not None:
            self._write_cache(cpath, emb, fingerprints)
        return emb

    def build_index(
        self, embed_fn: EmbedFn, *, batch_size: int = 16, cache: bool = True
    ) -> RetrievalIndex:
        """A :class:`~geoseg.reloc.retrieval.RetrievalIndex` over the base's embeddings and poses.

        Args:
            embed_fn, batch_size, cache: see :meth:`embeddings`.

        Returns:
            The index, with ``R_wc``, ``t_wc`` (so positions ``t_wc[:, :2]`` for the GPS window).
        """
        emb = self.embeddings(embed_fn, batch_size=batch_size, cache=cache)
        return RetrievalIndex(emb, R_wc=self.R_wc, t_wc=self.t_wc)


def _as_embeddings(out: Any, b: int) -> np.ndarray:
    """Validate an ``embed_fn`` output as a finite ``(b, D)`` float64 array."""
    if hasattr(out, "detach"):
        out = out.detach().cpu().numpy()
    arr = np.asarray(out, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] != b or arr.shape[1] == 0:
        raise GeosegError(f"embed_fn: expected an output of shape ({b}, D), got {arr.shape}")
    check_finite("embed_fn output", arr)
    return arr


def load_image_base(root: str | os.PathLike, *, rotation_tol: float = _ROTATION_TOL) -> ImageBase:
    """Load and validate a georeferenced image base directory.

    Args:
        root: the base directory (see the module docstring for its layout).
        rotation_tol: tolerance on ``|R^T R - I|`` (max entry) and ``|det R - 1|``.

    Returns:
        :class:`ImageBase`.

    Raises:
        GeosegError: not a directory; ``poses.csv`` missing, without the required columns or
            with bad values (the message names the row and column); rows whose image file is
            missing; image files without a row in ``poses.csv``; an empty base.
    """
    root = Path(root)
    if not root.is_dir():
        raise GeosegError(f"{root}: the image base is not a directory")
    poses_path = root / POSES_FILE
    files = _image_files(root)
    if not poses_path.is_file():
        if files:
            raise GeosegError(
                f"{root}: {POSES_FILE} is missing: base images without poses ({_fmt_names(files)})"
            )
        raise GeosegError(f"{root}: empty image base (no {POSES_FILE}, no images)")
    try:
        with poses_path.open(newline="") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in (reader.fieldnames or [])]
            reader.fieldnames = header
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise GeosegError(f"{poses_path}: unreadable ({err})") from None
    missing_cols = [c for c in POSE_COLUMNS if c not in header]
    if missing_cols and "frame" in header:  # a `geoseg render` output, not yet a base
        raise GeosegError(
            f"{root}: a geoseg render output, not an image base; make one with "
            f"`geoseg base build {root} --out BASE`"
        )
    if missing_cols:
        raise GeosegError(
            f"{poses_path}: missing column(s) {missing_cols}; expected "
            f"{', '.join(POSE_COLUMNS)} (optionally lat, lon)"
        )
    has_ll = "lat" in header and "lon" in header
    if ("lat" in header) != ("lon" in header):
        raise GeosegError(f"{poses_path}: give both 'lat' and 'lon' columns, or neither")
    if not rows:
        raise GeosegError(f"{root}: empty image base ({POSES_FILE} has no rows)")
    names: list[str] = []
    seen: dict[str, int] = {}
    ts = np.empty(len(rows))
    t = np.empty((len(rows), 3))
    R = np.empty((len(rows), 3, 3))
    ll = np.empty((len(rows), 2)) if has_ll else None
    for i, row in enumerate(rows):
        where = f"{poses_path} row {i + 2}"
        name = (row.get("image") or "").strip().replace("\\", "/")
        if not name:
            raise GeosegError(f"{where}: column 'image' is empty")
        if name in seen:
            raise GeosegError(f"{where}: image {name!r} already listed at row {seen[name] + 2}")
        seen[name] = i
        names.append(name)
        ts[i] = _number(row.get("timestamp"), where, "timestamp", allow_empty=True)
        t[i] = [_number(row.get(c), where, c) for c in ("tx", "ty", "tz")]
        R[i] = np.reshape([_number(row.get(c), where, c) for c in ROTATION_COLUMNS], (3, 3))
        if ll is not None:
            ll[i] = [_number(row.get(c), where, c) for c in ("lat", "lon")]
        err = max(
            float(np.abs(R[i].T @ R[i] - np.eye(3)).max()), abs(float(np.linalg.det(R[i])) - 1.0)
        )
        if err > rotation_tol:
            raise GeosegError(
                f"{where} ({name}): r00..r22 is not a rotation matrix (error {err:.3g})"
            )
    missing = [n for n in names if not (root / n).is_file()]
    if missing:
        raise GeosegError(
            f"{poses_path}: {len(missing)} listed image(s) not found under {root}: "
            f"{_fmt_names(missing)}"
        )
    listed = set(names)
    orphans = [f for f in files if f not in listed]
    if orphans:
        raise GeosegError(
            f"{root}: {len(orphans)} base image(s) without poses in {POSES_FILE}: "
            f"{_fmt_names(orphans)}"
        )
    K, size = read_camera(root / CAMERA_FILE) if (root / CAMERA_FILE).is_file() else (None, None)
    logger.info("image base %s: %d georeferenced images", root, len(names))
    return ImageBase(
        root=root, images=names, timestamps=ts, R_wc=R, t_wc=t, latlon=ll, K=K, image_size=size
    )


# ============================================================================ embedders


class ThumbnailEmbedder:
    """Placeholder embedding (NOT the learned one): a normalised grey thumbnail.

    Each image is converted to grey, area-averaged to ``size = (w, h)`` cells (pure NumPy:
    exact block means over a ``w x h`` grid), made zero-mean and scaled to unit L2 norm, and
    flattened to ``D = w * h``. It needs no weights, so ``geoseg localize --embedding thumbnail`` runs end to end
    before the networks are trained; it finds near-duplicates, not the same place in another
    season. The thesis's raw layer-21 matching (:func:`raw_layer21_embedder`) and the learned
    head (:class:`HeadEmbedder`) replace it once a model is available.

    Args:
        size: thumbnail ``(w, h)``, each >= 1; images must be at least this large.
    """

    def __init__(self, size: tuple[int, int] = (32, 24)) -> None:
        if len(size) != 2 or any(isinstance(s, bool) or int(s) != s or s < 1 for s in size):
            raise GeosegError(f"size: expected (w, h) ints >= 1, got {size!r}")
        self.size = (int(size[0]), int(size[1]))
        self.name = f"thumbnail{self.size[0]}x{self.size[1]}"

    def embed_one(self, image: Any) -> np.ndarray:
        """``(H, W, 3)`` RGB or ``(H, W)`` grey uint8 -> ``(w * h,)`` float64."""
        img = np.asarray(image)
        if img.ndim == 3 and img.shape[2] == 3:
            g = img.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
        elif img.ndim == 2:
            g = img.astype(np.float64)
        else:
            raise GeosegError(f"image: expected (H, W, 3) or (H, W), got {img.shape}")
        w, h = self.size
        H, W = g.shape
        if H < h or W < w:
            raise GeosegError(f"image: {W}x{H} pixels is smaller than the {w}x{h} thumbnail")
        rows = (np.arange(h) * H) // h
        cols = (np.arange(w) * W) // w
        sums = np.add.reduceat(np.add.reduceat(g, rows, axis=0), cols, axis=1)
        counts = np.diff(np.r_[rows, H])[:, None] * np.diff(np.r_[cols, W])[None, :]
        v = (sums / counts).ravel()
        v = v - v.mean()
        norm = np.linalg.norm(v)
        return v / norm if norm > 1e-12 else v

    def __call__(self, images: Sequence[Any]) -> np.ndarray:
        """``B`` images -> ``(B, w * h)`` float64."""
        return np.stack([self.embed_one(im) for im in images])


def _features_of(result: Any) -> Any:
    feats = (
        result.get("features") if isinstance(result, dict) else getattr(result, "features", None)
    )
    if feats is None:
        raise GeosegError(
            "the model exposes no layer-21 'features' output (use an ENet/joint model)"
        )
    if hasattr(feats, "detach"):
        feats = feats.detach().cpu().numpy()
    feats = np.asarray(feats, dtype=np.float32)
    if feats.ndim == 3:
        feats = feats[None]
    if feats.ndim != 4:
        raise GeosegError(f"features: expected (B, C, h, w), got {feats.shape}")
    return feats


def layer21_features(model: Callable[[np.ndarray], Any]) -> Callable[[np.ndarray], np.ndarray]:
    """Adapter: image -> its layer-21 feature map.

    Args:
        model: anything called on an RGB uint8 batch ``(1, H, W, 3)`` that returns an object
            with a ``features`` attribute or key ``(1, C, h, w)`` (e.g.
            :class:`geoseg.infer.Segmenter`).

    Returns:
        ``fn(image (H, W, 3) uint8) -> (C, h, w)`` float32.
    """

    def fn(image: np.ndarray) -> np.ndarray:
        return _features_of(model(np.asarray(image)[None]))[0]

    return fn


class Layer21Embedder:
    """The §5.1.1 baseline: flattened (optionally pooled) raw layer-21 features.

    Args:
        model: see :func:`layer21_features`.
        output_size: adaptive average pooling to ``(h', w')`` before flattening (then
            ``D = C h' w'`` whatever the image size); None flattens the full map (the thesis;
            all images must then give feature maps of the same size).
        normalize: L2-normalise the vectors.
        name: cache key (default: from ``model.source`` when it exists; None disables caching).
    """

    def __init__(
        self,
        model: Callable[[np.ndarray], Any],
        *,
        output_size: tuple[int, int] | None = None,
        normalize: bool = False,
        name: str | None = None,
    ) -> None:
        if output_size is not None:
            if len(output_size) != 2 or any(int(v) < 1 for v in output_size):
                raise GeosegError(f"output_size: expected (h', w') >= 1, got {output_size!r}")
            output_size = (int(output_size[0]), int(output_size[1]))
        self.features = layer21_features(model)
        self.output_size = output_size
        self.normalize = normalize
        self.feature_shape: tuple[int, ...] | None = None
        source = getattr(model, "source", None)
        if name is None and source is not None:
            st = Path(source).stat() if Path(source).is_file() else None
            tag = f"-{st.st_size}-{st.st_mtime_ns}" if st else ""
            pool = "full" if output_size is None else f"{output_size[0]}x{output_size[1]}"
            name = f"layer21-{Path(source).stem}{tag}-{pool}{'-l2' if normalize else ''}"
        self.name = name

    def __call__(self, images: Sequence[Any]) -> np.ndarray:
        """``B`` RGB images -> ``(B, D)`` float64."""
        import torch
        import torch.nn.functional as F

        out = []
        for image in images:
            f = self.features(image)
            if self.output_size is None:
                if self.feature_shape is None:
                    self.feature_shape = tuple(f.shape)
                elif tuple(f.shape) != self.feature_shape:
                    raise GeosegError(
                        f"feature maps of mismatched sizes: {tuple(f.shape)} vs "
                        f"{self.feature_shape} (images of different sizes; pool the features "
                        "to a fixed size)"
                    )
            x = torch.from_numpy(np.ascontiguousarray(f))[None]
            if self.output_size is not None:  # same pooling as RawFeatureEmbedder(output_size=)
                x = F.adaptive_avg_pool2d(x, self.output_size)
            v = x.flatten().double().numpy()
            if self.normalize:
                v = v / max(float(np.linalg.norm(v)), 1e-12)
            out.append(v)
        return np.stack(out)


def raw_layer21_embedder(
    model: Callable[[np.ndarray], Any],
    *,
    output_size: tuple[int, int] | None = None,
    normalize: bool = False,
    name: str | None = None,
) -> Layer21Embedder:
    """Build the raw layer-21 embedding (§5.1.1) over ``model``; see :class:`Layer21Embedder`."""
    return Layer21Embedder(model, output_size=output_size, normalize=normalize, name=name)


class HeadEmbedder:
    """Learned embedding: layer-21 features through an embedding head (eq. 5.1, fig. 5.5).

    Args:
        model: see :func:`layer21_features`.
        head: a torch module mapping ``(1, C, h, w)`` features to ``{"embedding": (1, D)}``
            (e.g. :class:`geoseg.models.reloc.RelocHead`), put in eval mode here.
        name: cache key, or None (no caching).
    """

    def __init__(self, model: Callable[[np.ndarray], Any], head: Any, *, name: str | None = None):
        self.features = layer21_features(model)
        self.head = head.eval()
        self.name = name

    def __call__(self, images: Sequence[Any]) -> np.ndarray:
        """``B`` RGB images -> ``(B, D)`` float64."""
        import torch

        out = []
        param = next(iter(self.head.parameters()), None)
        device = param.device if param is not None else torch.device("cpu")
        for image in images:
            f = torch.from_numpy(np.ascontiguousarray(self.features(image)))[None].to(device)
            with torch.no_grad():
                res = self.head(f)
            emb = res["embedding"] if isinstance(res, dict) else res
            out.append(emb[0].double().cpu().numpy())
        return np.stack(out)
