"""Frame sequences for the visual front end: a folder of images, or frames held in memory.

A *frame sequence* is anything with ``K`` ``(3, 3)``, ``image_size`` ``(W, H)``, ``timestamps``
``(T,)``, ``len()`` and ``seq[i] -> (timestamp, image)``, the image ``(H, W, 3)`` uint8 RGB or,
from a monochrome camera, ``(H, W)`` uint8 grayscale (:class:`FrameSequence`). Three exist:

* :class:`ImageFolder`: what a user has on disk. Layout::

      folder/                      folder/
        camera.json                  camera.json
        000000.png ...      or       rgb/000000.png ...   (what ``geoseg render`` writes)
        [timestamps.csv]             poses.csv            (frame, timestamp, ...)

  Images (``.png``, ``.jpg``, ``.jpeg``, any case) sit in ``folder/rgb/`` when that folder holds
  any, else directly in ``folder``; they are sorted by name and read lazily (one channel: a
  monochrome camera, read as grayscale). ``camera.json`` holds ``K`` (3x3) and ``image_size``
  ``[W, H]`` (or ``width`` and ``height``; optionally ``fps``). Timestamps come from the first
  source found: a ``timestamps.csv`` (``image,timestamp`` or ``frame,timestamp``, one row per
  image), the ``poses.csv`` of a render folder, or ``fps`` (``t = index / fps``). Every problem
  (no or unreadable images, sizes that differ from ``camera.json``, a bad ``camera.json``, no
  timestamps, timestamps not strictly increasing or not one per image) is a
  :class:`~slam_bridge.errors.SlamError` naming the file.
* :class:`slam_bridge.frontend.kitti.KittiSequence`: a KITTI odometry sequence as it is on
  disk (``image_0/`` or ``image_2/``, ``calib.txt``, ``times.txt``).
* :class:`FrameList`: frames already in memory (or made on demand by a callable), for programs
  that render or decode frames themselves, and for tests.
"""

from __future__ import annotations

import csv
import json
import logging
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = ["FrameSequence", "ImageFolder", "FrameList", "check_intrinsics", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class FrameSequence(Protocol):
    """What the visual front end reads (module docstring).

    Attributes:
        K: ``(3, 3)`` intrinsics.
        image_size: ``(W, H)``.
        timestamps: ``(T,)`` seconds, strictly increasing.
    """

    K: np.ndarray
    image_size: tuple[int, int]
    timestamps: np.ndarray

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> tuple[float, np.ndarray]: ...


def check_intrinsics(K: object, source: str) -> np.ndarray:
    """A valid pinhole calibration, or a :class:`SlamError` naming ``source``.

    Args:
        K: anything array-like, expected ``(3, 3)`` upper triangular with last row ``(0, 0, 1)``,
            finite, with positive focal lengths.
        source: what to name in the message (a file, an argument).

    Returns:
        ``(3, 3)`` float64.
    """
    try:  # a contiguous copy: OpenCV misreads a strided view (a block of a 3x4 projection)
        K = np.array(K, dtype=np.float64, order="C")
    except (TypeError, ValueError):
        raise SlamError(f"{source}: K: expected a 3x3 matrix of numbers, got {K!r}") from None
    if K.shape != (3, 3):
        raise SlamError(f"{source}: K: expected shape (3, 3), got {K.shape}")
    if not np.isfinite(K).all():
        raise SlamError(f"{source}: K: contains NaN or infinite values")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0 or K[2, 0] != 0:
        raise SlamError(
            f"{source}: K: expected an upper-triangular calibration with last row (0, 0, 1), "
            f"got {K.tolist()}"
        )
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise SlamError(
            f"{source}: K: expected positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}"
        )
    return K


def _check_size(value: object, source: str) -> tuple[int, int]:
    ok = (
        isinstance(value, list | tuple)
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
    )
    if not ok:
        raise SlamError(
            f"{source}: image_size: expected [W, H], two positive integers, got {value!r}"
        )
    return int(value[0]), int(value[1])


def _check_timestamps(t: np.ndarray, source: str) -> np.ndarray:
    if not np.isfinite(t).all():
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise SlamError(f"{source}: timestamp of frame {bad} is not a finite number ({t[bad]})")
    if t.size > 1 and not np.all(np.diff(t) > 0):
        bad = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise SlamError(
            f"{source}: timestamps must increase strictly; frame {bad} has {t[bad]} after "
            f"{t[bad - 1]}"
        )
    return t


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            header = [h.strip() for h in (reader.fieldnames or [])]
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise SlamError(f"{path}: cannot read the timestamps ({err})") from None
    rows = [{(k or "").strip(): (v or "").strip() for k, v in r.items()} for r in rows]
    return header, rows


class ImageFolder:
    """A folder of images read lazily (module docstring).

    Args:
        folder: the folder (images inside, or in its ``rgb/`` subfolder).
        camera: path of the ``camera.json`` (default ``folder/camera.json``).
        timestamps: path of a timestamps CSV (default: ``folder/timestamps.csv`` if present,
            else ``folder/poses.csv``, else ``fps`` from ``camera.json``).

    Attributes:
        folder: the folder given.
        image_dir: where the images are.
        paths: the image files, sorted by name.
        names: their file names.
        K: ``(3, 3)`` intrinsics.
        image_size: ``(W, H)``.
        timestamps: ``(T,)`` seconds.
        timestamp_source: the file the timestamps came from (or ``camera.json fps``).
        grayscale: the images have one channel (frames are ``(H, W)``).

    Raises:
        SlamError: see the module docstring.
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        camera: str | Path | None = None,
        timestamps: str | Path | None = None,
    ) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise SlamError(f"{self.folder}: expected a folder of images, it is not a folder")
        self.image_dir, self.paths = self._find_images()
        self.names = [p.name for p in self.paths]
        cam_path = Path(camera) if camera is not None else self.folder / "camera.json"
        self.K, self.image_size, fps = self._read_camera(cam_path)
        self.timestamps, self.timestamp_source = self._read_timestamps(
            None if timestamps is None else Path(timestamps), fps, cam_path
        )
        self.grayscale = False
        first = cv2.imread(str(self.paths[0]), cv2.IMREAD_UNCHANGED)
        self.grayscale = first is not None and first.ndim == 2
        first = self._read(0)
        logger.info(
            "%s: %d %s images %dx%d, timestamps from %s",
            self.image_dir,
            len(self),
            "grayscale" if self.grayscale else "colour",
            first.shape[1],
            first.shape[0],
            self.timestamp_source,
        )

    # ------------------------------------------------------------------------------ layout
    def _find_images(self) -> tuple[Path, list[Path]]:
        def images(d: Path) -> list[Path]:
            if not d.is_dir():
                return []
            return sorted(
                p for p in d.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
            )

        for d in (self.folder / "rgb", self.folder):
            found = images(d)
            if found:
                return d, found
        raise SlamError(
            f"{self.folder}: no images ({', '.join(IMAGE_SUFFIXES)}) in the folder or in its "
            "rgb/ subfolder"
        )

    def _read_camera(self, path: Path) -> tuple[np.ndarray, tuple[int, int], float | None]:
        if not path.is_file():
            raise SlamError(
                f"{path}: camera file not found (expected camera.json with K and image_size, "
                "or pass camera=PATH)"
            )
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, ValueError) as err:
            raise SlamError(f"{path}: cannot read the camera file as JSON ({err})") from None
        if not isinstance(data, dict):
            raise SlamError(f"{path}: expected a JSON object with K and image_size")
        if "image_size" not in data and {"width", "height"} <= data.keys():
            data["image_size"] = [data["width"], data["height"]]
        for key in ("K", "image_size"):
            if key not in data:
                raise SlamError(
                    f"{path}: missing {key!r} (expected K 3x3 and image_size [W, H] or width "
                    "and height)"
                )
        K = check_intrinsics(data["K"], str(path))
        size = _check_size(data["image_size"], str(path))
        fps = data.get("fps")
        if fps is not None:
            if isinstance(fps, bool) or not isinstance(fps, int | float) or not fps > 0:
                raise SlamError(f"{path}: fps: expected a number > 0 or null, got {fps!r}")
            if not np.isfinite(fps):
                raise SlamError(f"{path}: fps: expected a finite number, got {fps!r}")
        return K, size, None if fps is None else float(fps)

    def _read_timestamps(
        self, path: Path | None, fps: float | None, cam_path: Path
    ) -> tuple[np.ndarray, str]:
        if path is None:
            for candidate in (self.folder / "timestamps.csv", self.folder / "poses.csv"):
                if candidate.is_file():
                    path = candidate
                    break
        elif not path.is_file():
            raise SlamError(f"{path}: timestamps file not found")
        if path is not None:
            return _check_timestamps(self._timestamps_from_csv(path), str(path)), str(path)
        if fps is None:
            raise SlamError(
                f"{self.folder}: no timestamps: expected timestamps.csv (image,timestamp or "
                f"frame,timestamp), poses.csv, or fps in {cam_path}"
            )
        return np.arange(len(self.paths)) / fps, f"{cam_path} fps={fps:g}"

    def _timestamps_from_csv(self, path: Path) -> np.ndarray:
        header, rows = _read_csv(path)
        if "timestamp" not in header or not ({"image", "frame"} & set(header)):
            raise SlamError(
                f"{path}: expected columns image,timestamp or frame,timestamp, got {header}"
            )
        if len(rows) != len(self.paths):
            raise SlamError(
                f"{path}: {len(rows)} rows for {len(self.paths)} images in {self.image_dir} "
                "(expected one row per image)"
            )
        if "image" in header:
            index = {n: i for i, n in enumerate(self.names)}
            index.update({p.stem: i for i, p in enumerate(self.paths)})
            keys, column = [r["image"] for r in rows], "image"
        else:
            stems = [p.stem for p in self.paths]
            if all(s.isdigit() for s in stems):
                index = {int(s): i for i, s in enumerate(stems)}
            else:
                index = {i: i for i in range(len(stems))}
            keys, column = [], "frame"
            for r, row in enumerate(rows):
                try:
                    keys.append(int(float(row["frame"])))
                except ValueError:
                    raise SlamError(
                        f"{path}: row {r + 2}: frame {row['frame']!r} is not an integer"
                    ) from None
        t = np.full(len(self.paths), np.nan)
        seen = np.zeros(len(self.paths), dtype=bool)
        for r, (key, row) in enumerate(zip(keys, rows)):
            i = index.get(key)
            if i is None:
                raise SlamError(
                    f"{path}: row {r + 2}: {column} {key!r} matches no image in {self.image_dir}"
                )
            if seen[i]:
                raise SlamError(f"{path}: row {r + 2}: image {self.names[i]} has a second row")
            seen[i] = True
            try:
                t[i] = float(row["timestamp"])
            except ValueError:
                raise SlamError(
                    f"{path}: row {r + 2}: timestamp {row['timestamp']!r} is not a number"
                ) from None
        return t

    # ------------------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self.paths)

    def _read(self, index: int) -> np.ndarray:
        path = self.paths[index]
        flag = cv2.IMREAD_GRAYSCALE if self.grayscale else cv2.IMREAD_COLOR
        image = cv2.imread(str(path), flag)
        if image is None:
            raise SlamError(f"{path}: cannot read the image (missing, corrupt or not an image)")
        W, H = self.image_size
        if image.shape[:2] != (H, W):
            raise SlamError(
                f"{path}: image is {image.shape[1]}x{image.shape[0]}, expected {W}x{H} "
                f"(image_size of the camera file and of the first image)"
            )
        return image if self.grayscale else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def check_sizes(self) -> None:
        """Every image has the camera's size (read from the files' headers, not decoded).

        Raises:
            SlamError: naming the first image of another size, or one that is not an image.
        """
        from PIL import Image, UnidentifiedImageError

        W, H = self.image_size
        for path in self.paths:
            try:
                with Image.open(path) as im:
                    size = im.size
            except (OSError, UnidentifiedImageError):
                raise SlamError(
                    f"{path}: cannot read the image (missing, corrupt or not an image)"
                ) from None
            if size != (W, H):
                raise SlamError(
                    f"{path}: image is {size[0]}x{size[1]}, expected {W}x{H} (image_size of "
                    "the camera file and of the first image)"
                )

    def __getitem__(self, index: int) -> tuple[float, np.ndarray]:
        """``(timestamp, image)`` of frame ``index`` (read from disk now): ``(H, W, 3)`` RGB,
        or ``(H, W)`` for a grayscale folder."""
        index = _check_index(index, len(self))
        return float(self.timestamps[index]), self._read(index)

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:
        for i in range(len(self)):
            yield self[i]


class FrameList:
    """Frames in memory, or produced on demand by ``frames(index)``.

    Args:
        K: ``(3, 3)`` intrinsics.
        image_size: ``(W, H)``.
        timestamps: ``(T,)`` seconds, strictly increasing.
        frames: a sequence of ``T`` images, ``(H, W, 3)`` uint8 RGB or ``(H, W)`` uint8
            grayscale, or a callable ``index -> image``.
        names: optional frame names (default ``000000`` ...).

    Raises:
        SlamError: bad K, size, timestamps; an image of the wrong shape or type (when read).
    """

    def __init__(
        self,
        K: np.ndarray,
        image_size: tuple[int, int],
        timestamps: np.ndarray,
        frames: Sequence[np.ndarray] | Callable[[int], np.ndarray],
        names: Sequence[str] | None = None,
    ) -> None:
        self.K = check_intrinsics(K, "K")
        self.image_size = _check_size(list(image_size), "FrameList")
        self.timestamps = _check_timestamps(
            np.asarray(timestamps, dtype=np.float64).reshape(-1), "timestamps"
        )
        if not callable(frames) and len(frames) != self.timestamps.size:
            raise SlamError(
                f"frames: expected {self.timestamps.size} images (one per timestamp), "
                f"got {len(frames)}"
            )
        self._frames = frames
        self.names = list(names) if names is not None else [f"{i:06d}" for i in range(len(self))]

    def __len__(self) -> int:
        return int(self.timestamps.size)

    def __getitem__(self, index: int) -> tuple[float, np.ndarray]:
        """``(timestamp, image (H, W, 3) or (H, W) uint8)`` of frame ``index``."""
        index = _check_index(index, len(self))
        image = self._frames(index) if callable(self._frames) else self._frames[index]
        image = np.asarray(image)
        W, H = self.image_size
        if image.shape not in ((H, W, 3), (H, W)) or image.dtype != np.uint8:
            raise SlamError(
                f"frame {index}: expected an (H, W, 3) = ({H}, {W}, 3) or ({H}, {W}) uint8 "
                f"image, got {image.shape} {image.dtype}"
            )
        return float(self.timestamps[index]), image

    def __iter__(self) -> Iterator[tuple[float, np.ndarray]]:
        for i in range(len(self)):
            yield self[i]


def _check_index(index: int, n: int) -> int:
    if isinstance(index, bool) or not isinstance(index, int | np.integer):
        raise SlamError(f"index: expected an integer, got {index!r}")
    i = int(index) + (n if index < 0 else 0)
    if not 0 <= i < n:
        raise SlamError(f"index: {index} is outside the {n} frames")
    return i
