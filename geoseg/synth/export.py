"""The render stage: a synthetic sequence and its GIS products, written to a directory.

:func:`render_sequence` is a stage with a path contract (docs/architecture.md): it takes a world
config and a request, writes everything under ``out_dir``, returns ``out_dir``, and skips the
work when ``out_dir/meta.json`` records the very same request (``overwrite=True`` redoes it).
``meta.json`` is written last, so a directory without it is an unfinished render. Every file is
written atomically (a full disk leaves no partial frame or mesh). ``out_dir`` must be empty or
an earlier render (:func:`geoseg.output_dir.prepare_output_dir`); a folder holding other files
is refused unless ``allow_other_files``, and files the render did not write are never deleted.

Layout of ``out_dir`` (copied into the ``README.txt`` written there)::

    rgb/NNNNNN.png           RGB image, 8-bit
    labels/NNNNNN.png        class ids (geoseg.classes, 0..7), 8-bit single channel
    labels_color/NNNNNN.png  class ids coloured with geoseg.classes.PALETTE
    geometry/NNNNNN.npz      depth (H, W) float32 z-depth in metres (0 on sky), normals (3, H, W)
                             float16 unit vectors in the camera frame (0 where invalid),
                             normal_valid (H, W) bool, instance (H, W) int32 (-1 on sky)
    poses.csv                per frame: timestamp, camera pose (t_wc, quaternion, R row-major),
                             vehicle position, heading and speed
    camera.json              K (3x3), image size, rig, fps, condition, camera height, GPS antenna
                             (the vehicle reference point the GPS log measures) in the camera frame
    gis/buildings_model.ply  the erroneous GIS building model (extruded footprints, trimesh)
    gis/facades.csv          one plane per facade: n . X = d (+ true facade correspondence)
    gis/buildings_model.json buildings, status (present/missing/extra), correspondence
    gis/buildings_true.ply   the true buildings (ground truth), same mesh format
    gis/dem.csv, dem.geojson road DEM segments (world frame / WGS84)
    gis/gps.csv              1 Hz GPS log, world frame and WGS84, with dropouts
    gis/odometry.csv         wheel odometry at the frame rate
    preview.png              contact sheet (RGB, labels, depth, normals of a few frames)
    map.png                  top-down map: buildings, GIS model, DEM, trajectory, GPS
    meta.json                the request, the configs, versions, the file list
"""

from __future__ import annotations

import dataclasses
import json
import logging
import platform
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from geoseg.atomic import atomic_imwrite, atomic_output, atomic_write
from geoseg.classes import CLASS_NAMES, colorize
from geoseg.config import to_dict
from geoseg.errors import ConfigError, GeosegError
from geoseg.output_dir import prepare_output_dir, read_marker, record_outputs, remove_outputs
from geoseg.synth.buildings import (
    BuildingErrorConfig,
    build_building_model,
    extrude_footprints,
    write_mesh,
)
from geoseg.synth.dem import DemConfig, build_dem
from geoseg.synth.georef import Georeference
from geoseg.synth.gps import GpsConfig, simulate_gps
from geoseg.synth.odometry import OdometryConfig, simulate_odometry
from geoseg.synth.tables import write_table

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
PRODUCER = "render"
# Smallest rendered image side (the networks need one layer-21 cell: geoseg.infer.MIN_IMAGE_SIDE).
MIN_IMAGE_SIDE = 8
MAX_IMAGE_SIDE = 8192
# Frame rates a rig can have, Hz, and the longest drive a sequence may ask for, metres.
FPS_RANGE = (0.01, 1000.0)
MAX_DRIVE_M = 1e6


def check_fps(fps: float, name: str = "fps") -> float:
    """``fps`` as a float, or GeosegError unless it lies in :data:`FPS_RANGE`."""
    lo, hi = FPS_RANGE
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not lo <= fps <= hi:
        raise GeosegError(f"{name}: expected a frame rate in [{lo:g}, {hi:g}] Hz, got {fps!r}")
    return float(fps)


@dataclass
class GisConfig:
    """Error models of the GIS products and the georeference.

    Attributes:
        georef: where the world origin lies on Earth.
        buildings: building-model error model.
        dem: road-DEM error model.
        gps: GPS error model.
        odometry: wheel-odometry error model.
        mesh_format: ``ply`` or ``obj`` for the building meshes.
    """

    georef: Georeference = field(default_factory=Georeference)
    buildings: BuildingErrorConfig = field(default_factory=BuildingErrorConfig)
    dem: DemConfig = field(default_factory=DemConfig)
    gps: GpsConfig = field(default_factory=GpsConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    mesh_format: Literal["ply", "obj"] = "ply"


@dataclass
class GisProducts:
    """The GIS products of one world and one drive."""

    building_model: Any
    dem: Any
    gps: Any
    odometry: Any


def make_gis_products(world: Any, trajectory: Any, config: GisConfig, *, seed: int) -> GisProducts:
    """Building model, DEM (world-level) and GPS, odometry (drive-level), all seeded.

    Args:
        world: a :class:`geoseg.synth.world.World`.
        trajectory: a :class:`geoseg.synth.trajectory.Trajectory`.
        config: error models.
        seed: seed of the errors (the building model and DEM depend on it and the world only,
            so two drives with the same seed see the same GIS).
    """
    return GisProducts(
        building_model=build_building_model(
            world.buildings, config.buildings, seed=seed, streets=world.streets
        ),
        dem=build_dem(
            [s.centerline for s in world.streets], world.terrain_height, config.dem, seed=seed
        ),
        gps=simulate_gps(
            trajectory.timestamps,
            trajectory.vehicle_xyz,
            config.gps,
            seed=seed,
            georef=config.georef,
        ),
        odometry=simulate_odometry(
            trajectory.timestamps,
            trajectory.speed,
            trajectory.vehicle_heading,
            config.odometry,
            seed=seed,
        ),
    )


def ensure_writable(out_dir: str | Path) -> Path:
    """Create ``out_dir`` (and parents) and check a file can be written there.

    Raises:
        GeosegError: naming the directory, when it cannot be created or written.
    """
    from geoseg.output_dir import ensure_writable_dir

    return ensure_writable_dir(out_dir)


def drive_frames(
    world: Any,
    frames: int,
    *,
    rig: str = "car",
    fps: float = 10.0,
    seed: int = 0,
    image_size: tuple[int, int] = (320, 240),
    speed_mps: float | None = None,
) -> Any:
    """A drive of exactly ``frames`` frames (the route is lengthened until it has enough).

    Returns:
        A :class:`geoseg.synth.trajectory.Trajectory` with ``frames`` frames.
    """
    from geoseg.synth.trajectory import RIG_DEFAULTS, drive

    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise GeosegError(f"frames: expected an integer >= 1, got {frames!r}")
    check_fps(fps)
    cruise = speed_mps or RIG_DEFAULTS.get(rig, {"speed": 11.0})["speed"]
    length = max(10.0, 1.2 * cruise * frames / fps + 5.0)
    if length > MAX_DRIVE_M:
        raise GeosegError(
            f"frames, fps: {frames} frames at {fps:g} fps is a drive of {length / 1000:.3g} km, "
            f"longer than {MAX_DRIVE_M / 1000:g} km; use fewer frames or a higher frame rate"
        )
    for _ in range(6):
        traj = drive(
            world,
            rig=rig,
            length_m=length,
            speed_mps=speed_mps,
            fps=fps,
            seed=seed,
            image_size=image_size,
        )
        if len(traj) >= frames:
            return _first_frames(traj, frames)
        length *= 1.5
    raise GeosegError(f"frames: could not drive {frames} frames in this world")


def _first_frames(traj: Any, n: int) -> Any:
    sliced = {}
    for f in dataclasses.fields(traj):
        value = getattr(traj, f.name)
        if isinstance(value, np.ndarray) and f.name != "K" and value.shape[:1] == (len(traj),):
            value = value[:n]
        sliced[f.name] = value
    return type(traj)(**sliced)


MAX_WORKERS = 64  # rendering processes: more would only queue for the cores
RenderFn = Callable[[np.ndarray, np.ndarray, np.ndarray, float], Any]


def default_renderer(world: Any, condition: str, image_size: tuple[int, int]) -> RenderFn:
    """``fn(K, R_wc, t_wc, time_s) -> Frame`` through :func:`geoseg.synth.renderer.render`
    (which caches one renderer per world, so sequences of one world share it)."""
    from geoseg.synth.renderer import render

    def fn(K: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray, time_s: float) -> Any:
        return render(world, K, R_wc, t_wc, image_size, condition, time_s=time_s)

    return fn


def render_sequence(
    config: Any,
    out_dir: str | Path,
    frames: int = 30,
    condition: str = "summer_day",
    rig: str = "car",
    *,
    image_size: tuple[int, int] = (320, 240),
    fps: float = 10.0,
    seed: int | None = None,
    gis: GisConfig | None = None,
    world: Any = None,
    overwrite: bool = False,
    allow_other_files: bool = False,
    progress: bool = True,
    preview_frames: int = 6,
    render_fn: RenderFn | None = None,
    workers: int = 1,
) -> Path:
    """Render a drive through a synthetic city and write it with its GIS products.

    Args:
        config: the :class:`geoseg.synth.world.WorldConfig`.
        out_dir: output directory (created; must be writable).
        frames: number of frames, >= 1.
        condition: appearance condition (:data:`geoseg.synth.conditions.CONDITIONS`).
        rig: ``car`` or ``tram``.
        image_size: ``(W, H)`` pixels.
        fps: frame rate, Hz.
        seed: seed of the route and of the GIS errors (default: ``config.seed``).
        gis: GIS error models (defaults when None).
        world: the world built from ``config``, to save rebuilding it (it must match).
        overwrite: redo the work even when ``out_dir`` holds this very request.
        allow_other_files: write into an ``out_dir`` that holds files no render wrote (they
            are kept, unless a file of the same name is written).
        progress: show a tqdm progress bar.
        preview_frames: frames shown in ``preview.png``.
        render_fn: ``fn(K, R_wc, t_wc, time_s) -> Frame``, to replace the default renderer.
        workers: processes that render and write the frames (each builds its own renderer of
            ``world``; the files are the same as with 1). Only with the default renderer. They
            are started by ``spawn``, which imports the calling script again: a script of your
            own must guard its entry point with ``if __name__ == "__main__":``.

    Returns:
        ``out_dir``.

    Raises:
        GeosegError: unwritable ``out_dir`` or one holding other files (checked before any
            rendering), bad arguments; a failed write (full disk) names the file.
    """
    from tqdm import tqdm

    gis = gis or GisConfig()
    seed = int(config.seed if seed is None else seed)
    _check_arguments(condition, rig, frames, fps, workers, render_fn, image_size)
    legacy = _legacy_render_files(Path(out_dir))
    out_dir = prepare_output_dir(
        out_dir,
        producer=PRODUCER,
        overwrite=allow_other_files,
        adopt=lambda folder: legacy is not None,
    )
    if legacy:
        record_outputs(out_dir, legacy)
    request = {
        "format_version": FORMAT_VERSION,
        "world": to_dict(config),
        "gis": to_dict(gis),
        "frames": frames,
        "condition": condition,
        "rig": rig,
        "image_size": [int(image_size[0]), int(image_size[1])],
        "fps": float(fps),
        "seed": seed,
    }
    meta_path = out_dir / "meta.json"
    if not overwrite and _same_request(meta_path, request):
        logger.info("%s already holds this render; skipping (overwrite=True redoes it)", out_dir)
        return out_dir

    if world is None:
        from geoseg.synth.world import build_world

        world = build_world(config)
    elif getattr(world, "config", config) != config:
        raise GeosegError("world: it was built from another config than the one given")
    traj = drive_frames(world, frames, rig=rig, fps=fps, seed=seed, image_size=image_size)
    products = make_gis_products(world, traj, gis, seed=seed)
    render = render_fn or default_renderer(world, condition, tuple(image_size))

    remove_outputs(out_dir, ["meta.json"])  # unfinished until the new meta.json is written
    for sub in ("rgb", "labels", "labels_color", "geometry", "gis"):
        (out_dir / sub).mkdir(exist_ok=True)
    _remove_stale_frames(out_dir, frames)
    record_outputs(out_dir, [f for i in range(frames) for f in frame_files(i)])
    preview_idx = set(
        np.unique(np.linspace(0, frames - 1, min(preview_frames, frames)).round())
        .astype(int)
        .tolist()
    )
    bar = tqdm(total=frames, desc=f"render {rig}/{condition}", unit="frame", disable=not progress)
    jobs = [
        (i, traj.K, traj.R_wc[i], traj.t_wc[i], float(traj.timestamps[i]), i in preview_idx)
        for i in range(frames)
    ]
    preview_rows = []
    if workers == 1:
        for job in jobs:
            tiles = _render_and_write(out_dir, render, *job)
            preview_rows += [tiles] if tiles is not None else []
            bar.update()
    else:
        processes = min(workers, frames)
        preview_rows = _render_in_processes(
            out_dir, world, condition, image_size, jobs, processes, bar
        )
    bar.close()

    files = write_sequence_products(out_dir, world, traj, products, gis, condition=condition)
    _write_pictures(out_dir, preview_rows, sorted(preview_idx), world, traj, products, request)
    atomic_write(out_dir / "README.txt", readme_text(request), fsync=False)
    files += ["preview.png", "map.png", "README.txt"]
    record_outputs(out_dir, files + ["meta.json"])
    meta = _meta(request, files, world, products)
    atomic_write(meta_path, json.dumps(meta, indent=1))
    logger.info("wrote %d frames and GIS products to %s", frames, out_dir)
    return out_dir


def _check_arguments(
    condition: str,
    rig: str,
    frames: Any,
    fps: float,
    workers: Any,
    render_fn: RenderFn | None,
    image_size: Any,
) -> None:
    """The checks of :func:`render_sequence`'s arguments, before any work."""
    from geoseg.synth.conditions import get_condition

    get_condition(condition)  # unknown names fail before any work
    if rig not in ("car", "tram"):
        raise GeosegError(f"rig: expected 'car' or 'tram', got {rig!r}")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise GeosegError(f"frames: expected an integer >= 1, got {frames!r}")
    check_fps(fps)
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_WORKERS:
        raise GeosegError(f"workers: expected an integer in [1, {MAX_WORKERS}], got {workers!r}")
    if workers > 1 and render_fn is not None:
        raise GeosegError("workers: a render_fn of your own renders in this process only")
    if len(image_size) != 2 or not all(
        isinstance(v, int | np.integer) and not isinstance(v, bool) for v in image_size
    ):
        raise GeosegError(f"image_size: expected (W, H) integers, got {image_size!r}")
    parse_size(f"{image_size[0]}x{image_size[1]}")  # the same bounds as --size


def _write_pictures(
    out_dir: Path,
    preview_rows: list,
    preview_idx: list[int],
    world: Any,
    traj: Any,
    products: Any,
    request: dict[str, Any],
) -> None:
    """``preview.png`` (the preview frames' tiles) and ``map.png`` (world, GIS products,
    trajectory, GPS)."""
    rig, condition, frames = request["rig"], request["condition"], request["frames"]
    image_size, seed = request["image_size"], request["seed"]
    from geoseg.synth.maps import contact_sheet, plot_map

    contact_sheet(
        preview_rows,
        out_dir / "preview.png",
        row_labels=[f"frame {i}" for i in preview_idx],
        col_labels=["rgb", "labels", "depth", "normals"],
        title=f"{rig} / {condition}, {frames} frames {image_size[0]}x{image_size[1]}",
    )
    plot_map(
        out_dir / "map.png",
        true_footprints=[b.footprint for b in world.buildings],
        building_model=products.building_model,
        dem=products.dem,
        streets=world.streets,
        tracks={rig: traj.vehicle_xyz[:, :2]},
        gps={rig: products.gps},
        title=f"seed {seed}: world, GIS model, DEM, trajectory, GPS",
    )


def _meta(request: dict[str, Any], files: list[str], world: Any, products: Any) -> dict[str, Any]:
    """The render's ``meta.json``: the request, the files, a summary of the GIS products."""
    meta = {
        "request": request,
        "frames_written": request["frames"],
        "classes": list(CLASS_NAMES),
        "conventions": CONVENTIONS,
        "files": sorted(files) + ["rgb/", "labels/", "labels_color/", "geometry/"],
        "gis_summary": {
            "buildings_true": len(world.buildings),
            "buildings_missing": list(products.building_model.missing_ids),
            "buildings_extra": list(products.building_model.extra_ids),
            "facade_planes": len(products.building_model.planes),
            "dem_segments": len(products.dem),
            "gps_fixes": len(products.gps),
            "gps_valid": int(products.gps.valid.sum()),
            "odometry_scale_error": products.odometry.scale,
        },
        "versions": _versions(),
    }
    return meta


def _render_and_write(out_dir: Path, render: RenderFn, index, K, R_wc, t_wc, time_s, preview):
    """Render frame ``index``, write its files; its contact-sheet row when ``preview``."""
    frame = render(K, R_wc, t_wc, time_s)
    write_frame(out_dir, index, frame)
    return preview_tiles(frame) if preview else None


_worker_render: RenderFn | None = None  # a render process's renderer (_start_render_process)


def _start_render_process(world: Any, condition: str, image_size: tuple[int, int]) -> None:
    global _worker_render
    _worker_render = default_renderer(world, condition, image_size)


def _render_job(out_dir: Path, job: tuple) -> Any:
    return _render_and_write(out_dir, _worker_render, *job)


def _render_in_processes(out_dir, world, condition, image_size, jobs, workers, bar) -> list:
    """The frames of ``jobs`` rendered and written by ``workers`` processes (``spawn``: the
    caller may hold threads that ``fork`` would copy mid-lock); the contact-sheet rows in
    frame order."""
    import functools
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    rows = []
    with ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_start_render_process,
        initargs=(world, condition, tuple(image_size)),
    ) as pool:
        for tiles in pool.map(functools.partial(_render_job, out_dir), jobs, chunksize=4):
            rows += [tiles] if tiles is not None else []
            bar.update()
    return rows


def frame_files(index: int) -> list[str]:
    """The files of frame ``index`` in a render directory (relative paths)."""
    name = f"{index:06d}"
    return [
        f"rgb/{name}.png",
        f"labels/{name}.png",
        f"labels_color/{name}.png",
        f"geometry/{name}.npz",
    ]


def write_frame(out_dir: Path, index: int, frame: Any) -> None:
    """Write one frame's PNGs (``rgb``, ``labels``, ``labels_color``) and ``geometry`` npz, each
    atomically."""
    rgb, labels, labels_color, geometry = (out_dir / f for f in frame_files(index))
    label_ids = np.asarray(frame.labels).astype(np.uint8)
    atomic_imwrite(rgb, np.asarray(frame.rgb)[..., ::-1])
    atomic_imwrite(labels, label_ids)
    atomic_imwrite(labels_color, colorize(label_ids)[..., ::-1])
    with atomic_output(geometry, fsync=False) as handle:
        np.savez_compressed(
            handle,
            depth=np.asarray(frame.depth, dtype=np.float32),
            normals=np.asarray(frame.normals, dtype=np.float16),
            normal_valid=np.asarray(frame.normal_valid, dtype=bool),
            instance=np.asarray(frame.instance, dtype=np.int32),
        )


def preview_tiles(frame: Any) -> list[np.ndarray]:
    """The contact-sheet row of a frame: RGB, coloured labels, depth, normals, `(H, W, 3)` each."""
    from geoseg.synth.maps import depth_to_rgb, normals_to_rgb

    return [
        np.asarray(frame.rgb),
        colorize(np.asarray(frame.labels)),
        depth_to_rgb(frame.depth),
        normals_to_rgb(frame.normals, frame.normal_valid),
    ]


def write_sequence_products(
    out_dir: Path, world: Any, traj: Any, products: GisProducts, gis: GisConfig, *, condition: str
) -> list[str]:
    """Write poses, camera and GIS files; returns their paths relative to ``out_dir``."""
    write_poses_csv(out_dir / "poses.csv", traj)
    camera = {
        "K": np.asarray(traj.K).tolist(),
        "image_size": list(traj.image_size),
        "rig": traj.rig,
        "condition": condition,
        "fps": float(1.0 / np.median(np.diff(traj.timestamps))) if len(traj) > 1 else None,
        "convention": "OpenCV camera (x right, y down, z forward); X_w = R_wc X_c + t_wc",
        # the rig: where the GPS (vehicle reference point on the road) lies in the camera frame
        "camera_height_m": float((traj.R_wc[0].T @ (traj.vehicle_xyz[0] - traj.t_wc[0]))[1]),
        "gps_antenna_c": (traj.R_wc[0].T @ (traj.vehicle_xyz[0] - traj.t_wc[0])).round(6).tolist(),
    }
    atomic_write(out_dir / "camera.json", json.dumps(camera, indent=1), fsync=False)
    gis_dir = out_dir / "gis"
    written = products.building_model.write(gis_dir, mesh_format=gis.mesh_format)
    true_mesh = extrude_footprints(
        [b.footprint for b in world.buildings],
        [b.base_z for b in world.buildings],
        [b.height for b in world.buildings],
        building_ids=[b.id for b in world.buildings],
    )
    true_path = gis_dir / f"buildings_true.{gis.mesh_format}"
    write_mesh(true_mesh, true_path, gis.mesh_format)
    written.update(products.dem.write(gis_dir, gis.georef))
    written["gps"] = products.gps.write_csv(gis_dir / "gps.csv")
    written["odometry"] = products.odometry.write_csv(gis_dir / "odometry.csv")
    atomic_write(
        gis_dir / "georeference.json", json.dumps(to_dict(gis.georef), indent=1), fsync=False
    )
    paths = [*written.values(), true_path, gis_dir / "georeference.json"]
    return ["poses.csv", "camera.json"] + [str(Path(p).relative_to(out_dir)) for p in paths]


POSES_HEADER = (
    "frame,timestamp,tx,ty,tz,qw,qx,qy,qz,r00,r01,r02,r10,r11,r12,r20,r21,r22,"
    "vehicle_x,vehicle_y,vehicle_z,vehicle_heading,speed"
)


def write_poses_csv(path: Path, traj: Any) -> Path:
    """Ground-truth poses: ``X_w = R_wc X_c + t_wc`` with t_wc = (tx, ty, tz), the rotation as a
    unit quaternion (qw, qx, qy, qz; scalar first, qw >= 0) and as R_wc row-major (r00..r22)."""
    from scipy.spatial.transform import Rotation

    n = len(traj)
    quat = Rotation.from_matrix(traj.R_wc).as_quat()  # (x, y, z, w)
    quat = np.column_stack([quat[:, 3], quat[:, :3]])
    quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)
    table = np.column_stack(
        [
            np.arange(n),
            traj.timestamps,
            traj.t_wc,
            quat,
            np.asarray(traj.R_wc).reshape(n, 9),
            traj.vehicle_xyz,
            traj.vehicle_heading,
            traj.speed,
        ]
    )
    fmt = ["%d", "%.6f"] + ["%.6f"] * 3 + ["%.9f"] * 13 + ["%.6f"] * 5
    return write_table(path, table, fmt, POSES_HEADER)


CONVENTIONS = {
    "world_frame": "metric, right-handed, x east, y north, z up (metres)",
    "camera_frame": "OpenCV: x right, y down, z forward",
    "poses": "camera-to-world: X_w = R_wc X_c + t_wc; quaternion (qw, qx, qy, qz) scalar first",
    "heading": "radians, counter-clockwise from +x (east)",
    "depth": "geometry/*.npz 'depth' float32 (H, W): z-depth in metres along the optical axis "
    "(not the ray length); 0 on sky pixels",
    "normals": "geometry/*.npz 'normals' float16 (3, H, W) unit vectors in the camera frame; "
    "'normal_valid' (H, W) bool",
    "instance": "geometry/*.npz 'instance' int32 (H, W): 0..F-1 the row of the true world's "
    "facade table (gis/facades.csv column true_facade_id refers to it), then roofs, ground, "
    "trees, vehicles, objects (see geoseg.synth.world)",
    "labels": "labels/*.png 8-bit class ids in the order of 'classes'",
    "gis_truth_columns": "columns named true_* and bias_* are ground truth, not given to the SLAM",
    "wgs84": "gis/georeference.json: the world origin's WGS84 position; world axes are the local "
    "East-North-Up axes there (geoseg.synth.georef)",
}


def readme_text(request: dict[str, Any]) -> str:
    """The ``README.txt`` of a render directory."""
    doc = __doc__ or ""
    layout = doc[doc.index("Layout of") :]
    lines = [
        "geoseg synthetic sequence",
        "=========================",
        "",
        f"rig {request['rig']}, condition {request['condition']}, {request['frames']} frames "
        f"{request['image_size'][0]}x{request['image_size'][1]} at {request['fps']} fps, "
        f"seed {request['seed']}.",
        "",
        layout.strip(),
        "",
        "Conventions:",
        *(f"  {k}: {v}" for k, v in CONVENTIONS.items()),
        "",
        "CSV columns:",
        f"  poses.csv: {POSES_HEADER}",
    ]
    from geoseg.synth.buildings import FacadePlanes
    from geoseg.synth.dem import DemModel
    from geoseg.synth.gps import GpsLog
    from geoseg.synth.odometry import OdometryLog

    lines += [
        f"  gis/facades.csv: {FacadePlanes.CSV_HEADER}",
        f"  gis/dem.csv: {DemModel.CSV_HEADER}",
        f"  gis/gps.csv: {GpsLog.CSV_HEADER}",
        f"  gis/odometry.csv: {OdometryLog.CSV_HEADER}",
        "",
        "Load a frame's geometry: np.load('geometry/000000.npz') -> depth, normals, "
        "normal_valid, instance.",
        "",
    ]
    return "\n".join(lines)


def _remove_stale_frames(out_dir: Path, frames: int) -> None:
    """Delete frame files of an earlier, longer render (``NNNNNN.png|npz`` with index >=
    ``frames``) that a render recorded writing; any other file is kept."""
    stale = [
        f
        for sub in ("rgb", "labels", "labels_color", "geometry")
        for f in (out_dir / sub).glob("[0-9][0-9][0-9][0-9][0-9][0-9].*")
        if f.suffix in (".png", ".npz") and int(f.stem) >= frames
    ]
    removed = remove_outputs(out_dir, stale)
    if removed:
        logger.info("removed %d frame files of an earlier render from %s", len(removed), out_dir)


def _legacy_render_files(out_dir: Path) -> list[str] | None:
    """The files of a render written before output markers existed (its ``meta.json`` lists
    them), or None when ``out_dir`` is not such a render."""
    meta = out_dir / "meta.json"
    if read_marker(out_dir) is not None or not meta.is_file():
        return None
    try:
        doc = json.loads(meta.read_text())
        listed = [f for f in doc["files"] if not f.endswith("/")]
        frames = int(doc["frames_written"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not isinstance(doc.get("request"), dict):
        return None
    return listed + [f for i in range(frames) for f in frame_files(i)] + ["meta.json"]


def _same_request(meta_path: Path, request: dict[str, Any]) -> bool:
    if not meta_path.is_file():
        return False
    try:
        old = json.loads(meta_path.read_text()).get("request")
    except (OSError, ValueError):
        return False
    return old == json.loads(json.dumps(request))


def _versions() -> dict[str, str]:
    import geoseg

    return {
        "geoseg": geoseg.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(W, H)``; raises :class:`ConfigError` naming the text."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"size: expected WxH like 320x240, got {text!r}") from None
    if not (MIN_IMAGE_SIDE <= w <= MAX_IMAGE_SIDE and MIN_IMAGE_SIDE <= h <= MAX_IMAGE_SIDE):
        raise ConfigError(
            f"size: expected W and H in [{MIN_IMAGE_SIDE}, {MAX_IMAGE_SIDE}] pixels (what the "
            f"networks can use), got {text!r}"
        )
    return w, h
