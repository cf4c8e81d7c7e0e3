"""``geoseg slam run``: the SLAM on a folder of images, with GPS, odometry and DEM when given.

Example (a rendered sequence is one such folder)::

    geoseg render --out out/drive --frames 300 --size 640x480
    geoseg slam run out/drive --out out/drive_slam --gps out/drive/gis/gps.csv \\
        --odometry out/drive/gis/odometry.csv --dem out/drive/gis/dem.csv

``FRAMES_DIR`` holds the images (PNG/JPEG, directly or in ``rgb/``, sorted by name) and a
``camera.json`` (``K``, ``image_size``; optionally ``fps``, ``camera_height_m``,
``gps_antenna_c``); timestamps come from ``timestamps.csv``, ``poses.csv`` or ``fps``. The run
is :func:`slam_bridge.image_slam.run_image_slam`; its outputs are described there (trajectory
CSV with WGS84 positions, map points PLY, per-keyframe log, top-down plot, summary).
"""

from __future__ import annotations

import argparse
from pathlib import Path

DEFAULT_CONFIG = Path("configs/slam_images.yaml")


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    run_p = sub.add_parser("run", help="run the SLAM on a folder of images")
    run_p.add_argument("frames", type=Path, help="folder of images with its camera.json")
    run_p.add_argument("--out", type=Path, required=True, help="output folder")
    run_p.add_argument("--gps", type=Path, help="GPS log CSV (timestamp, x, y or lat/lon)")
    run_p.add_argument("--odometry", type=Path, help="wheel odometry CSV (timestamp, speed_mps)")
    run_p.add_argument("--dem", type=Path, help="road DEM CSV (x0, y0, z0, x1, y1, z1)")
    run_p.add_argument("--camera", type=Path, help="camera.json (default: FRAMES/camera.json)")
    run_p.add_argument("--timestamps", type=Path, help="timestamps CSV (image, timestamp)")
    run_p.add_argument("--georeference", type=Path, help="JSON of the world origin in WGS84")
    run_p.add_argument(
        "--method", choices=("ba", "dpc", "mpc"), default=None,
        help="k-BA window: plain (ba) or hybrid BA / pose graph (dpc, mpc); default from config",
    )  # fmt: skip
    run_p.add_argument(
        "--config", type=Path, default=None,
        help=f"settings YAML (default: the repository's {DEFAULT_CONFIG}, else built-in defaults)",
    )  # fmt: skip
    run_p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a setting, e.g. slam.window.l=30 (repeatable)",
    )  # fmt: skip
    run_p.add_argument(
        "--overwrite", action="store_true", help="write into a folder of other files"
    )
    run_p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import json

    from geoseg.config import default_config_file, load_config
    from slam_bridge.image_slam import ImageSlamConfig, load_inputs, run_image_slam

    source = args.config or default_config_file(DEFAULT_CONFIG.name)
    overrides = list(args.overrides) + ([f"method={args.method}"] if args.method else [])
    cfg = load_config(ImageSlamConfig, source, overrides=overrides)
    inputs = load_inputs(
        args.frames,
        camera=args.camera,
        timestamps=args.timestamps,
        gps=args.gps,
        odometry=args.odometry,
        dem=args.dem,
        georeference=args.georeference,
    )
    out = run_image_slam(
        inputs, args.out, cfg, overwrite=args.overwrite, progress=not args.no_progress
    )
    s = json.loads((out / "summary.json").read_text())
    print(
        f"{s['keyframes']} keyframes of {s['frames']} frames, {s['tracking_failures']} tracking "
        f"failure(s), {s['frames_per_second']:.1f} frames/s, "
        f"{'georeferenced' if s['georeferenced'] else 'not georeferenced (no GPS)'}"
    )
    if "translation_error_m" in s:
        line = (
            f"against poses.csv: {s['translation_error_m']:.2f} m horizontal, "
            f"{s['rotation_error_deg']:.2f} deg"
        )
        if "gps_error_m" in s:
            line += f" (GPS fixes: {s['gps_error_m']:.2f} m)"
        print(line)
    for name in ("trajectory.csv", "map_points.ply", "keyframes.csv", "trajectory.png"):
        print(f"  {name:15s} {out / name}")
    return 0
