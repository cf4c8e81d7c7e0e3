"""Build a georeferenced image base from a folder of geotagged images (thesis §5.1).

:func:`build_image_base` reads one of three sources and writes an image base (the layout of
:mod:`geoseg.reloc.image_base`: the images, ``poses.csv``, optionally ``camera.json``):

* a ``geoseg render`` output folder (``rgb/NNNNNN.png``, ``poses.csv`` with a ``frame``
  column, ``camera.json``): the rendered poses are the base poses;
* a folder that is already an image base (``poses.csv`` with an ``image`` column and the full
  rotation ``r00..r22``): re-written as is;
* a folder of images with a positions file (``positions``): a CSV with columns ``image, x, y``
  and optionally ``z``, ``heading_deg``, ``timestamp``. ``x, y`` are metres in a projected
  frame (x east, y north: e.g. UTM or Lambert-93, the frame the queries' GPS will use), ``z``
  the ground height (default 0). The camera is taken level, ``camera_height_m`` above ``z``,
  looking along ``heading_deg`` (degrees counter-clockwise from the x axis, i.e. from east) or,
  without it, along the track: the direction from the previous to the next image's position
  (rows in driving order). This suits a forward-looking vehicle camera.

The images are copied into the base (hard links when the file system allows), so that a base
is one self-contained folder. :func:`geoseg.reloc.localizer.Localizer.from_base` then computes and
caches the embeddings (``BASE/cache/``); ``geoseg base build`` does both.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from geoseg.errors import GeosegError, check_positive
from geoseg.reloc.image_base import (
    CAMERA_FILE,
    POSES_FILE,
    load_image_base,
    read_camera,
    write_poses_csv,
)

logger = logging.getLogger(__name__)

__all__ = ["build_image_base", "level_camera_rotations", "read_source"]

# Columns that mark a poses.csv written by `geoseg render` (geoseg.synth.export).
_RENDER_COLUMNS = ("frame", "timestamp", "tx", "ty", "tz", "r00", "r22")


def level_camera_rotations(heading_rad: Any) -> np.ndarray:
    """Camera-to-world rotations of a level camera looking along each heading.

    Args:
        heading_rad: ``(N,)`` radians counter-clockwise from the world x axis (east).

    Returns:
        ``(N, 3, 3)`` ``R_wc`` whose columns are the camera axes in the world frame (OpenCV:
        x right, y down, z forward; world z up).
    """
    h = np.asarray(heading_rad, dtype=np.float64).reshape(-1)
    c, s, z = np.cos(h), np.sin(h), np.zeros_like(h)
    x_c = np.stack([s, -c, z], axis=1)  # right of the direction of travel
    y_c = np.stack([z, z, -np.ones_like(h)], axis=1)  # down
    z_c = np.stack([c, s, z], axis=1)  # forward
    return np.stack([x_c, y_c, z_c], axis=2)


def _track_headings(xy: np.ndarray) -> np.ndarray:
    """``(N,)`` headings of a track from its ``(N, 2)`` positions: central differences, one
    sided at the ends; an image with no movement around it takes its neighbour's heading."""
    n = len(xy)
    if n < 2:
        raise GeosegError("positions: a heading from the track needs at least 2 images")
    nxt = np.r_[xy[1:], xy[-1:]]
    prv = np.r_[xy[:1], xy[:-1]]
    d = nxt - prv
    moving = np.linalg.norm(d, axis=1) > 1e-6
    if not moving.any():
        raise GeosegError("positions: all images at one place: give heading_deg")
    idx = np.where(moving, np.arange(n), -1)
    idx = np.maximum.accumulate(idx)  # carry the last moving heading forward ...
    first = int(np.argmax(moving))
    idx[idx < 0] = first  # ... and the first one back
    return np.arctan2(d[idx, 1], d[idx, 0])


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in (reader.fieldnames or [])]
            reader.fieldnames = header
            return header, list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise GeosegError(f"{path}: unreadable ({err})") from None


def _number(row: dict[str, str], col: str, where: str, default: float | None = None) -> float:
    text = (row.get(col) or "").strip()
    if not text and default is not None:
        return default
    try:
        v = float(text)
    except ValueError:
        raise GeosegError(f"{where}: column {col!r} is not a number ({text!r})") from None
    if not math.isfinite(v):
        raise GeosegError(f"{where}: column {col!r} is not finite")
    return v


def read_source(
    src: str | os.PathLike,
    *,
    positions: str | os.PathLike | None = None,
    camera_height_m: float = 1.5,
) -> dict[str, Any]:
    """Read a source folder (module docstring) as base images and poses.

    Args:
        src: the folder of images.
        positions: a positions CSV (``image, x, y[, z, heading_deg, timestamp]``), or None
            for a render output or an existing base.
        camera_height_m: camera above ``z`` for a positions file.

    Returns:
        ``{"files": [M source paths], "names": [M names in the base], "R_wc": (M, 3, 3),
        "t_wc": (M, 3), "timestamps": (M,) (NaN when unknown), "camera": Path or None,
        "kind": "render" | "base" | "positions"}``.

    Raises:
        GeosegError: not a folder, no known layout, missing images or bad values (naming the
            file and row).
    """
    src = Path(src)
    if not src.is_dir():
        raise GeosegError(f"{src}: not a folder")
    camera = src / CAMERA_FILE if (src / CAMERA_FILE).is_file() else None
    if positions is not None:
        check_positive("camera_height_m", camera_height_m, strict=False)
        return _from_positions(src, Path(positions), camera_height_m, camera)
    poses = src / POSES_FILE
    if not poses.is_file():
        raise GeosegError(
            f"{src}: no {POSES_FILE}: give a positions file (image, x, y) for a folder of images"
        )
    header, _ = _read_csv(poses)
    if "image" in header:
        base = load_image_base(src)
        return {
            "files": [base.path(i) for i in range(len(base))],
            "names": list(base.images),
            "R_wc": base.R_wc,
            "t_wc": base.t_wc,
            "timestamps": base.timestamps,
            "camera": camera,
            "kind": "base",
        }
    if all(c in header for c in _RENDER_COLUMNS):
        return _from_render(src, poses, camera)
    raise GeosegError(
        f"{poses}: neither an image base (an 'image' column) nor a geoseg render output (a "
        f"'frame' column); for other folders give a positions file (image, x, y)"
    )


def _from_render(src: Path, poses: Path, camera: Path | None) -> dict[str, Any]:
    _, rows = _read_csv(poses)
    if not rows:
        raise GeosegError(f"{poses}: no rows")
    files, names, t, R, ts = [], [], [], [], []
    for k, row in enumerate(rows):
        where = f"{poses} row {k + 2}"
        frame = int(_number(row, "frame", where))
        name = f"rgb/{frame:06d}.png"
        if not (src / name).is_file():
            raise GeosegError(f"{where}: image {src / name} not found")
        files.append(src / name)
        names.append(name)
        ts.append(_number(row, "timestamp", where))
        t.append([_number(row, c, where) for c in ("tx", "ty", "tz")])
        R.append([_number(row, f"r{i}{j}", where) for i in range(3) for j in range(3)])
    return {
        "files": files,
        "names": names,
        "R_wc": np.asarray(R).reshape(-1, 3, 3),
        "t_wc": np.asarray(t),
        "timestamps": np.asarray(ts),
        "camera": camera,
        "kind": "render",
    }


def _from_positions(src: Path, path: Path, height: float, camera: Path | None) -> dict[str, Any]:
    if not path.is_file():
        raise GeosegError(f"positions: {path}: no such file")
    header, rows = _read_csv(path)
    missing = [c for c in ("image", "x", "y") if c not in header]
    if missing:
        raise GeosegError(f"{path}: missing column(s) {missing}; expected image, x, y")
    if not rows:
        raise GeosegError(f"{path}: no rows")
    files, names, xyz, heading, ts = [], [], [], [], []
    seen: set[str] = set()
    for k, row in enumerate(rows):
        where = f"{path} row {k + 2}"
        name = (row.get("image") or "").strip().replace("\\", "/")
        if not name:
            raise GeosegError(f"{where}: column 'image' is empty")
        if name in seen:
            raise GeosegError(f"{where}: image {name!r} is listed twice")
        seen.add(name)
        if not (src / name).is_file():
            raise GeosegError(f"{where}: image {src / name} not found")
        files.append(src / name)
        names.append(name)
        xyz.append(
            [_number(row, "x", where), _number(row, "y", where), _number(row, "z", where, 0.0)]
        )
        if "heading_deg" in header:
            heading.append(math.radians(_number(row, "heading_deg", where)))
        ts.append(_number(row, "timestamp", where, math.nan) if "timestamp" in header else math.nan)
    t = np.asarray(xyz)
    h = np.asarray(heading) if heading else _track_headings(t[:, :2])
    t[:, 2] += height
    return {
        "files": files,
        "names": names,
        "R_wc": level_camera_rotations(h),
        "t_wc": t,
        "timestamps": np.asarray(ts),
        "camera": camera,
        "kind": "positions",
    }


def _copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def build_image_base(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    positions: str | os.PathLike | None = None,
    camera_height_m: float = 1.5,
    overwrite: bool = False,
) -> Path:
    """Write an image base for the images of ``src`` into ``out`` (module docstring).

    Args:
        src: the source folder.
        out: the base folder: empty, new, or an earlier base build (``overwrite`` for others).
        positions: a positions CSV for a plain folder of images.
        camera_height_m: camera above the positions' ``z``.
        overwrite: write into a folder holding files no base build wrote (they are kept).

    Returns:
        ``out``, loadable by :func:`geoseg.reloc.image_base.load_image_base`.
    """
    from geoseg.output_dir import prepare_output_dir, record_outputs

    out = Path(out)
    if out.resolve() == Path(src).resolve():
        raise GeosegError(f"--out: {out} is the source folder; give a new folder for the base")
    source = read_source(src, positions=positions, camera_height_m=camera_height_m)
    out = prepare_output_dir(out, producer="base", overwrite=overwrite)
    written = [POSES_FILE, *source["names"]]
    if source["camera"] is not None:
        written.append(CAMERA_FILE)
    record_outputs(out, written)
    for file, name in zip(source["files"], source["names"]):
        _copy(Path(file), out / name)
    ts = source["timestamps"]
    write_poses_csv(
        out / POSES_FILE,
        source["names"],
        source["R_wc"],
        source["t_wc"],
        timestamps=ts if np.isfinite(ts).all() else None,
    )
    if source["camera"] is not None:
        K, size = read_camera(source["camera"])
        camera: dict[str, Any] = {"K": K.tolist()}
        if size is not None:
            camera["image_size"] = list(size)
        (out / CAMERA_FILE).write_text(json.dumps(camera, indent=1) + "\n")
    logger.info(
        "image base %s: %d images from %s (%s)", out, len(source["names"]), src, source["kind"]
    )
    return out
