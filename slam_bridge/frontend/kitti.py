"""A KITTI odometry sequence as it is on disk, read as a frame sequence.

Layout (one sequence folder of the KITTI odometry benchmark, or a clip cut from one)::

    sequence/
      image_0/000000.png ...   left grayscale camera (image_1: right grayscale,
      image_2/000000.png ...   image_2 / image_3: colour), PNG or JPEG
      calib.txt                lines "P0: 12 numbers" ... (3x4 projection matrices, row-major)
      times.txt                one time per frame, seconds
      [poses.txt]              ground truth: 12 numbers per frame, row-major 3x4 [R | t]
                               camera-to-world, world = the camera of frame 0

The intrinsics are the left 3x3 block of the camera's ``P`` line (rectified images: no
distortion). ``poses.txt`` is never read by the SLAM: it is in the first camera's frame (x right,
y down, z forward), not a map frame, and serves only for evaluation
(:func:`read_kitti_poses`, :mod:`slam_bridge.experiments.simulated_logs`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam_bridge.errors import SlamError
from slam_bridge.frontend.frames import IMAGE_SUFFIXES, ImageFolder, check_intrinsics

__all__ = [
    "KITTI_CAMERA_HEIGHT_M",
    "KittiSequence",
    "is_kitti_sequence",
    "read_kitti_calib",
    "read_kitti_poses",
]

#: height of the KITTI rig's cameras above the road, metres (Geiger et al., IJRR 2013, fig. 3)
KITTI_CAMERA_HEIGHT_M = 1.65

#: image folders tried in order when no camera is named: grayscale left, colour left
CAMERA_FOLDERS = ("image_0", "image_2")


def is_kitti_sequence(folder: str | Path) -> bool:
    """The folder has a ``calib.txt`` and one of the KITTI image folders."""
    folder = Path(folder)
    return (folder / "calib.txt").is_file() and any(
        (folder / f"image_{i}").is_dir() for i in range(4)
    )


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """The projection matrices of a KITTI ``calib.txt``.

    Returns:
        ``{"P0": (3, 4), ...}`` float64, one per line ``NAME: 12 numbers``.

    Raises:
        SlamError: unreadable file, a line that is not 12 numbers.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise SlamError(f"{path}: cannot read the calibration ({err})") from None
    out = {}
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        name, _, values = line.partition(":")
        try:
            numbers = np.array([float(v) for v in values.split()])
        except ValueError:
            raise SlamError(f"{path}: line {n}: {line.strip()!r} is not NAME: 12 numbers") from None
        if numbers.size != 12:
            raise SlamError(
                f"{path}: line {n}: expected 12 numbers after {name!r}, got {numbers.size}"
            )
        out[name.strip()] = numbers.reshape(3, 4)
    return out


def read_kitti_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth poses of a KITTI ``poses.txt``.

    Returns:
        ``(R_wc (T, 3, 3), t_wc (T, 3))``: camera-to-world, world = the first camera's frame.

    Raises:
        SlamError: unreadable file, a line that is not 12 finite numbers.
    """
    path = Path(path)
    try:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
        values = np.array(rows, dtype=np.float64)
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise SlamError(f"{path}: expected 12 numbers per line ({err})") from None
    if values.ndim != 2 or values.shape[1] != 12 or not np.isfinite(values).all():
        raise SlamError(f"{path}: expected 12 finite numbers per line, got shape {values.shape}")
    P = values.reshape(-1, 3, 4)
    return P[:, :, :3].copy(), P[:, :, 3].copy()


class KittiSequence(ImageFolder):
    """A KITTI odometry sequence folder (module docstring) as an
    :class:`~slam_bridge.frontend.frames.ImageFolder`.

    Args:
        folder: the sequence folder.
        camera_index: which camera, 0-3 (default: ``image_0`` when present, else ``image_2``).
        timestamps: a timestamps CSV instead of ``times.txt`` (as for an ImageFolder).

    Attributes:
        camera_index: the camera read.
        poses_path: ``poses.txt`` when the folder has one (evaluation only), else None.

    Raises:
        SlamError: no image folder, no ``P`` line for the camera, a ``times.txt`` whose lines do
            not match the images, and every error of an ImageFolder.
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        camera_index: int | None = None,
        timestamps: str | Path | None = None,
    ) -> None:
        folder = Path(folder)
        if camera_index is None:
            found = [i for i, name in enumerate(CAMERA_FOLDERS) if (folder / name).is_dir()]
            camera_index = (0, 2)[found[0]] if found else 0
        if camera_index not in range(4):
            raise SlamError(f"camera_index: expected 0-3, got {camera_index!r}")
        self.camera_index = int(camera_index)
        poses = folder / "poses.txt"
        self.poses_path = poses if poses.is_file() else None
        super().__init__(folder, camera=folder / "calib.txt", timestamps=timestamps)

    def _find_images(self) -> tuple[Path, list[Path]]:
        d = self.folder / f"image_{self.camera_index}"
        found = (
            sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
            if d.is_dir()
            else []
        )
        if not found:
            raise SlamError(f"{d}: no images ({', '.join(IMAGE_SUFFIXES)})")
        return d, found

    def _read_camera(self, path: Path) -> tuple[np.ndarray, tuple[int, int], float | None]:
        import cv2

        name = f"P{self.camera_index}"
        calib = read_kitti_calib(path)
        if name not in calib:
            raise SlamError(
                f"{path}: no {name}: line (the projection of image_{self.camera_index})"
            )
        K = check_intrinsics(calib[name][:, :3], f"{path} {name}")
        first = cv2.imread(str(self.paths[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise SlamError(f"{self.paths[0]}: cannot read the image")
        return K, (int(first.shape[1]), int(first.shape[0])), None

    def _read_timestamps(
        self, path: Path | None, fps: float | None, cam_path: Path
    ) -> tuple[np.ndarray, str]:
        if path is not None:
            return super()._read_timestamps(path, fps, cam_path)
        times = self.folder / "times.txt"
        if not times.is_file():
            raise SlamError(f"{times}: not found (KITTI: one time per frame, seconds)")
        try:
            t = np.array([float(v) for v in times.read_text().split()], dtype=np.float64)
        except (OSError, ValueError, UnicodeDecodeError) as err:
            raise SlamError(f"{times}: expected one number per line ({err})") from None
        if t.size != len(self.paths):
            raise SlamError(
                f"{times}: {t.size} times for {len(self.paths)} images in {self.image_dir} "
                "(expected one per image)"
            )
        from slam_bridge.frontend.frames import _check_timestamps

        return _check_timestamps(t, str(times)), str(times)
