"""``geoseg slam run``: the SLAM on a folder of images, with GPS, odometry, DEM and building
constraints when given.

Example (a rendered sequence is one such folder)::

    geoseg render --out out/drive --frames 300 --size 640x480
    geoseg slam run out/drive --out out/drive_slam --gps out/drive/gis/gps.csv \\
        --odometry out/drive/gis/odometry.csv --dem out/drive/gis/dem.csv \\
        --buildings out/drive/gis/facades.csv

With ``--buildings`` (a facade table, the columns of ``gis/facades.csv``) the network bridge
runs beside the SLAM (thesis chapter 4): by default the shipped joint network labels the
keyframes, eq. 4.14 associates the building points with the facades, and the fusion pulls them
onto their planes (:mod:`slam_bridge.bridge`). ``--association dirichlet`` uses the naive CNN +
Dirichlet filter instead; ``raycast`` the chapter-2 baseline (no network; needs the model's
mesh, ``--buildings-mesh``, by default ``buildings_model.ply`` beside the table).
``--colour-transfer REF`` maps each keyframe's colours onto a reference's before the network
sees it (thesis §4.3.2: Reinhard's transfer, :mod:`geoseg.colour_transfer`), for a camera whose
colours or exposure differ from the training images': ``card`` takes the training images'
statistics from the network's model card, a path those of an image or the typical image of a
folder (or a JSON file of statistics); each keyframe is mapped from its own statistics, as
``geoseg infer --colour-transfer image`` maps each image (``--colour-means-only`` as there).
``--gps-bias estimate`` (with ``--buildings`` and ``--gps``) estimates the GPS's slowly varying
bias from the facades and removes it from the fixes (:mod:`slam_bridge.bridge.gps_bias`).

``geoseg slam refine RUN`` adjusts a finished run's map (its ``map.npz``) once more, all
keyframes together, constrained to the building model, the DEM, the GPS and the odometry: the
thesis's pseudo ground truth for a drive without truth (§3.7;
:func:`slam_bridge.system.refine.refine_run`, docs/refine.md). ``geoseg slam-eval run --run RUN
--reference RUN_refined`` then measures a run against it.

``FRAMES_DIR`` holds the images (PNG/JPEG, directly or in ``rgb/``, sorted by name) and a
``camera.json`` (``K``, ``image_size``; optionally ``fps``, ``camera_height_m``,
``gps_antenna_c``); timestamps come from ``timestamps.csv``, ``poses.csv`` or ``fps``. The run
is :func:`slam_bridge.system.image_slam.run_image_slam`; its outputs are described there (trajectory
CSV with WGS84 positions, map points PLY, per-keyframe log, top-down plot, summary).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

DEFAULT_CONFIG = Path("configs/slam_images.yaml")
#: exit code of a run whose status is ``failed`` (its outputs are written all the same)
EXIT_FAILED = 3


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    run_p = sub.add_parser("run", help="run the SLAM on a folder of images")
    run_p.add_argument("frames", type=Path, help="folder of images with its camera.json")
    run_p.add_argument("--out", type=Path, required=True, help="output folder")
    run_p.add_argument("--gps", type=Path, help="GPS log CSV (timestamp, x, y or lat/lon)")
    run_p.add_argument("--odometry", type=Path, help="wheel odometry CSV (timestamp, speed_mps)")
    run_p.add_argument("--dem", type=Path, help="road DEM CSV (x0, y0, z0, x1, y1, z1)")
    run_p.add_argument(
        "--base", type=Path,
        help="image base (geoseg base build) in the GPS's frame: frames localised against it "
        "give position fixes that start, constrain and recover the run (with or without --gps)",
    )  # fmt: skip
    run_p.add_argument(
        "--buildings", type=Path,
        help="building model's facade table CSV (x0, y0, x1, y1, z_min, z_max, nx, ny, nz, d): "
        "building constraints chosen by the network bridge",
    )  # fmt: skip
    run_p.add_argument(
        "--association", choices=("bayes", "dirichlet", "raycast"), default=None,
        help="how points are given facades: bayes (joint network + eq. 4.14), dirichlet "
        "(naive CNN + Dirichlet filter), raycast (baseline); default from config (bayes)",
    )  # fmt: skip
    run_p.add_argument(
        "--network", type=Path,
        help="the association's network (.onnx/.pt file, weights folder or shipped name, e.g. "
        "normals_real for real photographs; default: the association's shipped network)",
    )  # fmt: skip
    run_p.add_argument(
        "--dirichlet", type=Path,
        help="dirichlet association: the Dirichlet filter (dirichlet.json, a `geoseg train "
        "dirichlet` run folder or shipped name, e.g. dirichlet_real; default: the one shipped "
        "for --network)",
    )  # fmt: skip
    run_p.add_argument(
        "--colour-transfer", metavar="REF",
        help="map each keyframe's colours onto a reference's before the network (Reinhard et "
        "al. 2001, thesis 4.3.2; each keyframe from its own statistics, as geoseg infer's "
        "'image' mode): 'card' (the network's training images, from its model card), an image, "
        "a folder of images or a JSON file of colour statistics; default: from config (off)",
    )  # fmt: skip
    run_p.add_argument(
        "--colour-means-only", action="store_true",
        help="with --colour-transfer: shift the colour means only (keep the keyframes' "
        "contrast and saturation) instead of matching means and standard deviations",
    )  # fmt: skip
    run_p.add_argument(
        "--buildings-mesh", type=Path,
        help="raycast: the model's mesh (default: buildings_model.ply beside --buildings)",
    )  # fmt: skip
    run_p.add_argument(
        "--gps-bias", choices=("estimate", "off"), default=None,
        help="estimate: the GPS's slowly varying bias is estimated from the building model "
        "(the facades the map points lie off) and removed from the fixes, for a receiver "
        "whose urban bias reaches metres; off: fixes used as they are; default from config "
        "(gps_bias.enabled); needs --buildings and --gps",
    )  # fmt: skip
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
    run_p.add_argument(
        "--truth", type=Path,
        help="true poses in the GPS's world frame (poses.csv columns: timestamp, tx, ty, tz, "
        "r00..r22), for evaluation only; default: the folder's own poses.csv (a render)",
    )  # fmt: skip

    ref = sub.add_parser(
        "refine",
        help="one bundle adjustment over a whole run, constrained to the building model and "
        "the DEM: a pseudo ground truth (thesis section 3.7)",
    )
    ref.add_argument("run", type=Path, help="a `geoseg slam run` output folder (its map.npz)")
    ref.add_argument("--out", type=Path, help="output folder (default: RUN_refined beside RUN)")
    ref.add_argument(
        "--buildings", type=Path,
        help="facade table CSV (gis/facades.csv; the run's own for its association)",
    )  # fmt: skip
    ref.add_argument("--dem", type=Path, help="road DEM CSV (x0, y0, z0, x1, y1, z1)")
    ref.add_argument("--gps", type=Path, help="GPS log CSV (timestamp, x, y or lat/lon)")
    ref.add_argument("--odometry", type=Path, help="wheel odometry CSV (timestamp, speed_mps)")
    ref.add_argument(
        "--association", choices=("auto", "saved", "nearest"), default=None,
        help="points on facades: saved (the run's network association), nearest (nearest "
        "facade within radius_m), auto (saved when the run has one; the default)",
    )  # fmt: skip
    ref.add_argument(
        "--method", choices=("joint", "barrier"), default=None,
        help="joint: one weighted least squares (default); barrier: the thesis's barrier "
        "fusion over the whole sequence",
    )  # fmt: skip
    ref.add_argument(
        "--truth", type=Path,
        help="true poses (poses.csv) for evaluation only: the refined and the run's errors",
    )  # fmt: skip
    ref.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a setting of slam_bridge.system.refine.RefineConfig (repeatable)",
    )  # fmt: skip
    ref.add_argument("--overwrite", action="store_true", help="write into a folder of other files")

    sim = sub.add_parser(
        "simulate-logs",
        help="GPS, odometry and DEM logs simulated from a drive's true poses (KITTI poses.txt "
        "or poses.csv)",
    )
    sim.add_argument("frames", type=Path, help="a KITTI sequence folder or a render folder")
    sim.add_argument("--out", type=Path, required=True, help="folder for the logs")
    sim.add_argument("--poses", type=Path, help="the true poses (default: FRAMES/poses.txt)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--gps-rate", type=float, default=1.0, help="fixes per second (1)")
    sim.add_argument("--gps-sigma", type=float, default=0.75, help="GPS noise per axis, m (0.75)")
    sim.add_argument(
        "--gps-bias", type=float, default=0.0,
        help="bound of the GPS's locally constant bias, m (0: none; thesis eq. 1.84)",
    )  # fmt: skip
    sim.add_argument(
        "--speed-noise", type=float, default=0.01, help="relative wheel-speed noise (0.01)"
    )
    sim.add_argument("--dem-noise", type=float, default=0.2, help="DEM vertex error, m (0.2)")
    sim.add_argument(
        "--camera-height", type=float, default=None,
        help="camera height above the road, m (default 1.65, KITTI's; 1.5 for a render)",
    )  # fmt: skip
    sim.add_argument(
        "--offset", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
        help="metres added to every world position (e.g. UTM coordinates)",
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    if args.action == "simulate-logs":
        return _simulate_logs(args)
    if args.action == "refine":
        return _refine(args)
    return _run(args)


def _simulate_logs(args: argparse.Namespace) -> int:
    from slam_bridge.experiments.simulated_logs import SimulatedLogsConfig, simulate_from_folder

    cfg = SimulatedLogsConfig(
        gps_rate_hz=args.gps_rate,
        gps_sigma_m=args.gps_sigma,
        gps_bias_max_m=args.gps_bias,
        speed_noise_rel=args.speed_noise,
        dem_noise_m=args.dem_noise,
        offset_m=tuple(args.offset),
        seed=args.seed,
        **({} if args.camera_height is None else {"camera_height_m": args.camera_height}),
    )
    out = simulate_from_folder(args.frames, args.out, cfg, poses=args.poses)
    meta = json.loads((out / "frame.json").read_text())
    print(
        f"simulated logs of {meta['source']} (seed {args.seed}; GPS fixes off by "
        f"{meta['gps_error_m_mean']:.2f} m on average):"
    )
    for name in meta["files"] + ["frame.json"]:
        print(f"  {name:13s} {out / name}")
    return 0


def _refine(args: argparse.Namespace) -> int:
    from geoseg.config import load_config
    from geoseg.errors import GeosegError
    from slam_bridge.system.refine import RefineConfig, refine_run

    if args.buildings is None and args.gps is None:
        raise GeosegError("slam refine: give --buildings or --gps (or both): the world reference")
    overrides = list(args.overrides)
    overrides += [f"method={args.method}"] if args.method else []
    overrides += [f"association={args.association}"] if args.association else []
    cfg = load_config(RefineConfig, None, overrides=overrides)
    out_dir = args.out or args.run.parent / f"{args.run.name}_refined"
    out = refine_run(
        args.run, out_dir, cfg, buildings=args.buildings, dem=args.dem, gps=args.gps,
        odometry=args.odometry, truth=args.truth, overwrite=args.overwrite,
    )  # fmt: skip
    s = json.loads((out / "summary.json").read_text())
    rows = ", ".join(
        f"{s[k]} {k.removesuffix('_rows')}"
        for k in ("gps_rows", "dem_rows", "odometry_rows", "building_rows")
        if k in s
    )
    print(
        f"refined {s['keyframes']} keyframes and {s['points']} points ({s['method']}; "
        f"{s['observations']} observations, {rows} rows); keyframes moved "
        f"{s['keyframe_shift_m_mean']:.3f} m on average, reprojection "
        f"{s['reprojection_rms_px_before']:.2f} -> {s['reprojection_rms_px']:.2f} px rms"
    )
    if "translation_error_m" in s:
        print(
            f"against {args.truth}: refined {s['translation_error_m']:.3f} m horizontal "
            f"(the run's {s['run_translation_error_m']:.3f} m)"
        )
    for name in ("trajectory.csv", "frame_poses.csv", "trajectory_tum.txt", "summary.json"):
        print(f"  {name:20s} {out / name}")
    return 0


def _run(args: argparse.Namespace) -> int:

    from geoseg.config import default_config_file, load_config
    from geoseg.errors import GeosegError
    from slam_bridge.system.image_slam import ImageSlamConfig, load_inputs, run_image_slam

    source = args.config or default_config_file(DEFAULT_CONFIG.name)
    overrides = list(args.overrides) + ([f"method={args.method}"] if args.method else [])
    if args.association:
        overrides.append(f"bridge.association={args.association}")
    if args.buildings is None and (
        args.association or args.network or args.buildings_mesh or args.dirichlet
        or args.colour_transfer or args.colour_means_only
    ):  # fmt: skip
        raise GeosegError(
            "--association, --network, --dirichlet, --buildings-mesh, --colour-transfer, "
            "--colour-means-only: need --buildings"
        )
    if args.gps_bias:
        if args.gps_bias == "estimate" and (args.buildings is None or args.gps is None):
            raise GeosegError("--gps-bias estimate: needs --buildings and --gps")
        overrides.append(f"gps_bias.enabled={str(args.gps_bias == 'estimate').lower()}")
    cfg = load_config(ImageSlamConfig, source, overrides=overrides)
    cfg = _with_colour_transfer(args, cfg)
    inputs = load_inputs(
        args.frames,
        camera=args.camera,
        timestamps=args.timestamps,
        gps=args.gps,
        odometry=args.odometry,
        dem=args.dem,
        georeference=args.georeference,
        truth=args.truth,
        base=args.base,
    )
    bridge = None if args.buildings is None else _bridge(args, cfg, inputs)
    out = run_image_slam(
        inputs, args.out, cfg, overwrite=args.overwrite, progress=not args.no_progress,
        bridge=bridge,
    )  # fmt: skip
    s = json.loads((out / "summary.json").read_text())
    print(
        f"{s['keyframes']} keyframes of {s['frames']} frames, {s['tracking_failures']} tracking "
        f"failure(s), {s['frames_per_second']:.1f} frames/s, "
        f"{'georeferenced' if s['georeferenced'] else 'not georeferenced (no GPS)'}"
    )
    if "base_fixes" in s:
        print(
            f"image base: {s['base_fixes']} fixes from {s['base_frames_localised']} localised "
            f"frames, fused at {s['base_fused_keyframes']} of {s['keyframes']} keyframes"
        )
    if "translation_error_m" in s:
        line = (
            f"against poses.csv: {s['translation_error_m']:.2f} m horizontal, "
            f"{s['rotation_error_deg']:.2f} deg"
        )
        if "gps_error_m" in s:
            line += f" (GPS fixes: {s['gps_error_m']:.2f} m)"
        print(line)
    if bridge is not None:
        print(
            f"buildings ({s['association']}): {s['associated_points']} map points on facades, "
            f"fused at {s['building_keyframes']} of {s['keyframes']} keyframes"
        )
    for name in (
        "trajectory.csv", "trajectory_tum.txt", "trajectory_kitti.txt", "frame_poses.csv",
        "map_points.ply", "keyframes.csv", "trajectory.png", "summary.json",
    ):  # fmt: skip
        print(f"  {name:20s} {out / name}")
    print(f"status: {s['status']}")
    for r in s["status_reasons"]:
        ranges = ", ".join(f"{a}-{b}" if a != b else f"{a}" for a, b in r["keyframes"])
        print(
            f"  {r['severity']}: {r['check']}: {r['detail']}"
            + (f" (keyframes {ranges})" if ranges else "")
        )
    return EXIT_FAILED if s["status"] == "failed" else 0


def _with_colour_transfer(args, cfg):
    """``cfg`` with ``--colour-transfer`` / ``--colour-means-only`` in its bridge settings (set
    here, not through ``--set``: a path may hold any character)."""
    import dataclasses

    from geoseg.errors import GeosegError

    changes = {}
    if args.colour_transfer is not None:
        changes["colour_transfer"] = args.colour_transfer
    if args.colour_means_only:
        if (args.colour_transfer or cfg.bridge.colour_transfer) is None:
            raise GeosegError("--colour-means-only: needs --colour-transfer")
        changes["colour_means_only"] = True
    if not changes:
        return cfg
    return dataclasses.replace(cfg, bridge=dataclasses.replace(cfg.bridge, **changes))


def _bridge(args, cfg, inputs):
    """The network bridge of ``--buildings`` (its inputs read and checked before the run)."""
    from geoseg.errors import GeosegError
    from slam_bridge.bridge.builder import build_bridge
    from slam_bridge.bridge.facades import Facades

    method = cfg.bridge.association
    if method == "raycast" and args.network:
        raise GeosegError("--network: the raycast association uses no network")
    if method == "raycast" and args.colour_transfer:
        raise GeosegError("--colour-transfer: the raycast association uses no network")
    if method != "raycast" and args.buildings_mesh:
        raise GeosegError("--buildings-mesh: only the raycast association uses a mesh")
    if method != "dirichlet" and args.dirichlet:
        raise GeosegError("--dirichlet: only the dirichlet association uses the filter")
    facades = Facades.read_csv(args.buildings)
    if method != "raycast":  # the first inference can take a while on a busy machine
        print(f"loading the {method} network and running it once on a blank image ...", flush=True)
    mesh = None
    if method == "raycast":
        import trimesh

        path = args.buildings_mesh or args.buildings.parent / "buildings_model.ply"
        if not path.is_file():
            raise GeosegError(f"{path}: no such mesh (raycast needs --buildings-mesh)")
        try:
            mesh = trimesh.load(path, force="mesh")
        except Exception as exc:  # trimesh raises many kinds on a file that is not a mesh
            raise GeosegError(f"{path}: not a readable mesh ({exc})") from None
        if len(mesh.faces) == 0:
            raise GeosegError(f"{path}: a mesh without faces")
    return build_bridge(
        cfg.bridge, facades, image_size=inputs.frames.image_size, mesh=mesh,
        weights=args.network, dirichlet_filter=args.dirichlet,
    )  # fmt: skip
