"""The SLAM on images: drives through the synthetic city, our online SLAM beside COLMAP.

Each drive is rendered at 640x480 (all channels; cached in ``--data``), and run through the image
SLAM as a user runs it (:func:`slam_bridge.system.image_slam.run_on_images`: visual front end, two-view
start, odometry scale, georeferencing to the GPS, barrier fusion of GPS + DEM, no ground truth)
with the render's wheel odometry and road DEM and two GPS logs at the frame rate:

* ``sigma0.75`` (the headline runs): the thesis's model of its synthetic sequence, the true
  antenna position plus ``N(0, 0.75^2)`` per axis;
* ``bias``: :func:`geoseg.synth.gps.simulate_gps`'s locally constant bias (up to 3 m) + noise +
  dropouts (a bias that GPS fusion alone cannot remove; reported beside).

Figures per drive (``<drive>/...`` in the JSON) and their means over the drives' sigma0.75 runs:
``tracking_failures``; ``bad_observation_share`` (the front end's observations whose true
reprojection error, from the rendered depth and poses, exceeds 2 px; :mod:`slam_bridge.
evaluate_tracks`); ``translation_error_m`` (mean horizontal error of the keyframes, no
alignment), ``gps_error_m`` (the fixes' mean error on the same keyframes) and their ratio
``translation_error_over_gps``; ``rotation_error_deg``; the peer, COLMAP's incremental SfM on the
same keyframes (``bench/colmap_peer.py``: SIFT, sequential matching, incremental mapping, then a
robust similarity to the GPS fixes as a user would align it): ``translation_error_over_colmap``
(over the keyframes COLMAP registered: ``colmap_registered_share``)
and ``wall_time_over_colmap`` (our whole SLAM over COLMAP's extraction + matching + mapping);
``frames_per_second`` of the whole SLAM on the pre-rendered images, with where the time goes.
The chapter-3 figures (hybrid windows DPC / MPC against ``n = 0``: ``chapter3_dpc_time_ratio``,
``..._mpc_time_ratio``, ``..._memory_ratio``, ``..._inlier_loss_max``, translation errors) come
from the chapter-3 experiment on image tracks (``configs/slam_ch3.yaml`` with ``tracks=images``:
known start poses, GPS at every keyframe), beside the same experiment on simulated tracks
(``chapter3_simulated_*``).

Usage: ``python bench/slam_images.py [--full] [--split tuning|report] [--data DIR]
[--no-colmap]``: by default one 300 m drive; ``--full`` the six drives of >= 600 m (car and tram,
light and dense occlusion, one winter and one dusk), on which the settings were chosen (the
tuning split); ``--split report`` five 300 m drives of other cities never used to choose
(``slam_images_report.json``). Prints Markdown tables and writes ``bench/results/
slam_images.json``, with the mean and standard deviation over the drives.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from geoseg.config import load_config
from slam_bridge.evaluation import metrics as ev
from slam_bridge.evaluation.tracks import RenderTruth, TrackTable, evaluate_tracks
from slam_bridge.system.image_slam import ImageSlamConfig, evaluate_run, load_inputs, run_on_images

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402
from splits import (  # noqa: E402
    SLAM_IMAGES_QUICK_DRIVES,
    SLAM_IMAGES_REPORT_DRIVES,
    SLAM_IMAGES_TUNING_DRIVES,
)

#: which data each run measures (``--split``)
SPLITS = {
    "tuning": "tuning: the drives of FULL_DRIVES (world and route seeds 1-6; QUICK_DRIVES without "
    "--full) are where the front end's and the fusion's settings were chosen",
    "report": "report: the five 300 m drives of REPORT_DRIVES (world and route seeds 11-15), never "
    "used to choose a setting",
}

logger = logging.getLogger("bench.slam_images")

#: (name, rig, world preset, condition, route seed, length in metres): bench/splits.py
FULL_DRIVES = SLAM_IMAGES_TUNING_DRIVES
QUICK_DRIVES = SLAM_IMAGES_QUICK_DRIVES
REPORT_DRIVES = SLAM_IMAGES_REPORT_DRIVES
SIGMA_B = 0.75
FPS = 10.0
SIZE = (640, 480)


def render_drive(
    data: Path, name: str, rig: str, preset: str, condition: str, seed: int, length_m: float
) -> Path:
    """Render a drive of at least ``length_m`` (skipped when already rendered)."""
    from geoseg.synth.export import drive_frames, render_sequence
    from geoseg.synth.world import WorldConfig, build_world

    out = data / name
    config = WorldConfig(seed=seed, preset=preset, blocks_x=4, blocks_y=3)
    world = build_world(config)
    guess = int(length_m / 4.0 * FPS)  # frames at 4 m/s, grown until the route is long enough
    while True:
        traj = drive_frames(world, guess, rig=rig, fps=FPS, seed=seed, image_size=SIZE)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(traj.t_wc, axis=0), axis=1))])
        if arc[-1] >= length_m:
            frames = int(np.searchsorted(arc, length_m)) + 1
            break
        guess = int(guess * 1.5)
    return render_sequence(
        config, out, frames=frames, condition=condition, rig=rig, image_size=SIZE, fps=FPS,
        seed=seed, world=world,
    )  # fmt: skip


def write_gps_logs(folder: Path, seed: int) -> dict[str, Path]:
    """The two GPS logs of a drive at the frame rate (module docstring)."""
    from geoseg.synth.gps import GpsConfig, simulate_gps
    from slam_bridge.csv_columns import read_columns

    poses = read_columns(folder / "poses.csv", ["timestamp", "vehicle_x", "vehicle_y", "vehicle_z"])
    t = poses["timestamp"]
    antenna = np.column_stack([poses["vehicle_x"], poses["vehicle_y"], poses["vehicle_z"]])
    out = {}
    for setting, cfg in (
        (
            "sigma0.75",
            GpsConfig(
                rate_hz=FPS, bias_max_m=0.0, bias_std_m=0.0, noise_std_m=SIGMA_B, dropout_share=0.0
            ),
        ),
        ("bias", GpsConfig(rate_hz=FPS)),
    ):
        log = simulate_gps(t, antenna, cfg, seed=seed + 17)
        path = folder / f"gps_{setting}.csv"
        xy = np.where(log.valid[:, None], log.xy, np.nan)
        table = np.column_stack([log.timestamps, log.valid.astype(float), xy])
        np.savetxt(
            path, table, delimiter=",", header="timestamp,valid,x,y", comments="", fmt="%.6f"
        )
        out[setting] = path
    return out


def run_drive(folder: Path, gps: Path, cfg: ImageSlamConfig):
    """One SLAM run; returns (inputs, result, tracks, wall seconds)."""
    inputs = load_inputs(
        folder, gps=gps, odometry=folder / "gis" / "odometry.csv", dem=folder / "gis" / "dem.csv"
    )
    t0 = time.perf_counter()
    result, tracks = run_on_images(inputs, cfg, progress=False)
    return inputs, result, tracks, time.perf_counter() - t0


def bad_observation_share(folder: Path, inputs, result) -> dict:
    """True reprojection errors of the map's observations (rendered depth and poses)."""
    truth = RenderTruth(folder)
    m = result.map
    frame_of = np.searchsorted(inputs.frames.timestamps, m.timestamps)
    table = TrackTable(
        m.obs_keyframe.copy(), frame_of[m.obs_keyframe], m.obs_point.copy(), m.obs_uv.copy()
    )
    all_obs = evaluate_tracks(table, m.K, truth.R_wc, truth.t_wc, truth.depth)
    used = evaluate_tracks(
        table, m.K, truth.R_wc, truth.t_wc, truth.depth, active=m.obs_active.copy()
    )
    return {
        "bad_observation_share": float(all_obs.summary["bad_share"]),
        "bad_observation_share_used": float(used.summary["bad_share"]),
        "bad_observation_share_consistency": float(
            all_obs.summary.get("bad_share_consistency", float("nan"))
        ),
        "track_length_mean_keyframes": float(all_obs.summary["track_length_mean"]),
        "observations_per_keyframe": float(m.num_observations / max(m.num_keyframes, 1)),
    }


def colmap_figures(folder: Path, inputs, result, work: Path) -> dict:
    """COLMAP on our keyframes, aligned to their GPS fixes (z: DEM + camera height); errors
    over the keyframes COLMAP registered, ours on the same keyframes beside them."""
    import importlib.util

    from slam_bridge.slam.fusion import GpsConstraints

    spec = importlib.util.spec_from_file_location("colmap_peer", ROOT / "bench" / "colmap_peer.py")
    peer = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(peer)

    m = result.map
    frame_of = np.searchsorted(inputs.frames.timestamps, m.timestamps)
    images = [inputs.frames[int(f)][1] for f in frame_of]
    gps = GpsConstraints(inputs.gps_timestamps, inputs.gps_xy, tolerance_s=0.02)
    targets = np.full((m.num_keyframes, 3), np.nan)
    for k in range(m.num_keyframes):
        fix = gps.fix_at(float(m.timestamps[k]))
        if fix is not None:
            z = inputs.dem.altitude_at(fix[None])[0] + inputs.rig.camera_height_m
            targets[k] = [fix[0], fix[1], z]
    res = peer.colmap_peer(
        images, m.K, work, targets, antenna_c=np.asarray(inputs.rig.antenna_c), max_error_m=5.0
    )
    t_true, R_true, T_true = inputs.truth
    idx = np.searchsorted(t_true, m.timestamps)
    ok = res.registered
    e_h = np.linalg.norm(res.t_wc[ok, :2] - T_true[idx][ok, :2], axis=1)
    e_r = np.degrees(ev.rotation_errors(res.R_wc[ok], R_true[idx][ok]))
    ours = ok & result.in_world
    e_ours = np.linalg.norm(m.t_wc[ours, :2] - T_true[idx][ours, :2], axis=1)
    return {
        "colmap_translation_error_m": float(e_h.mean()),
        "colmap_rotation_error_deg": float(e_r.mean()),
        "translation_error_on_colmap_keyframes_m": float(e_ours.mean()),
        "colmap_registered_share": float(ok.mean()),
        "colmap_wall_seconds": float(res.wall_seconds),
    }


def chapter3_on_images(data: Path, full: bool) -> dict:
    """The chapter-3 experiment (``configs/slam_ch3.yaml``: known start poses, GPS at every
    keyframe) on image tracks, and on simulated tracks beside it (same drive, same GPS)."""
    from slam_bridge.experiments.fusion_ch3 import ExperimentConfig, run_experiment

    keys = ["dpc_time_ratio", "mpc_time_ratio", "memory_ratio", "inlier_loss_max"]
    out = {}
    for tracks in ("images", "simulated"):
        cfg = load_config(
            ExperimentConfig, ROOT / "configs" / "slam_ch3.yaml", overrides=[f"tracks={tracks}"]
        )
        cfg = cfg if full else cfg.quick()
        folder = run_experiment(cfg, data / f"chapter3_{tracks}_{'full' if full else 'quick'}")
        summary = json.loads((folder / "fusion_ch3.json").read_text())
        tag = "chapter3" if tracks == "images" else "chapter3_simulated"
        for k in keys + [k for k in summary if k.endswith("_t_mean")]:
            if isinstance(summary.get(k), int | float):
                out[f"{tag}_{k}"] = float(summary[k])
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--full", action="store_true", help="the six drives of >= 600 m")
    parser.add_argument(
        "--data", type=Path, default=Path.home() / ".cache" / "geoseg" / "slam_images"
    )
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "slam_images.yaml")
    parser.add_argument("--no-colmap", action="store_true", help="skip the COLMAP peer")
    parser.add_argument("--no-chapter3", action="store_true", help="skip the hybrid-window runs")
    parser.add_argument(
        "--split", choices=sorted(SPLITS), default="tuning",
        help="tuning: the drives the settings were chosen on (default); report: five others",
    )  # fmt: skip
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="results file (default: "
        "bench/results/slam_images.json, slam_images_report.json for --split report)",
    )
    args = parser.parse_args(argv)
    if args.out is None:
        name = "slam_images.json" if args.split == "tuning" else "slam_images_report.json"
        args.out = ROOT / "bench" / "results" / name
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    cfg = load_config(ImageSlamConfig, args.config)
    drives = REPORT_DRIVES if args.split == "report" else FULL_DRIVES if args.full else QUICK_DRIVES
    per_drive: dict[str, dict] = {}
    for name, rig, preset, condition, seed, length in drives:
        folder = render_drive(args.data, name, rig, preset, condition, seed, length)
        gps_logs = write_gps_logs(folder, seed)
        fig: dict = {"rig": rig, "preset": preset, "condition": condition}
        for setting, path in gps_logs.items():
            inputs, result, tracks, wall = run_drive(folder, path, cfg)
            e = evaluate_run(result, inputs)
            prefix = "" if setting == "sigma0.75" else "bias_"
            frames = int(np.searchsorted(inputs.frames.timestamps, result.map.timestamps[-1])) + 1
            fig.update({f"{prefix}{k}": v for k, v in e.items()})
            fig[f"{prefix}tracking_failures"] = result.tracking_failures
            fig[f"{prefix}bridged_keyframes"] = result.bridged
            if setting != "sigma0.75":
                continue
            loop_s = sum(r.seconds for r in result.records) - tracks.timings.get("total", 0.0)
            fig.update(
                length_m=float(np.sum(np.linalg.norm(np.diff(inputs.truth[2], axis=0), axis=1))),
                frames=frames,
                keyframes=result.map.num_keyframes,
                wall_seconds=wall,
                frames_per_second=frames / wall,
                frontend_ms_per_frame=1e3 * tracks.timings.get("total", 0.0) / frames,
                loop_ms_per_keyframe=1e3 * loop_s / result.map.num_keyframes,
                kba_ms_per_keyframe=1e3 * np.mean([r.ba_seconds for r in result.records]),
                fusion_ms_per_keyframe=1e3 * np.mean([r.fusion_seconds for r in result.records]),
            )
            fig.update(bad_observation_share(folder, inputs, result))
            if not args.no_colmap:
                fig.update(colmap_figures(folder, inputs, result, args.data / f"{name}_colmap"))
                fig["translation_error_over_colmap"] = (
                    fig["translation_error_on_colmap_keyframes_m"]
                    / fig["colmap_translation_error_m"]
                )
                fig["wall_time_over_colmap"] = wall / fig["colmap_wall_seconds"]
        per_drive[name] = fig
        logger.info(
            "%s: %s", name, {k: round(v, 3) if isinstance(v, float) else v for k, v in fig.items()}
        )

    chapter3 = {} if args.no_chapter3 else chapter3_on_images(args.data, args.full)
    keys = [
        "tracking_failures", "bridged_keyframes", "bad_observation_share",
        "bad_observation_share_used",
        "bad_observation_share_consistency", "track_length_mean_keyframes",
        "translation_error_m", "gps_error_m", "translation_error_over_gps", "rotation_error_deg",
        "translation_error_over_colmap", "wall_time_over_colmap", "frames_per_second",
        "frontend_ms_per_frame", "loop_ms_per_keyframe", "bias_translation_error_m",
        "bias_gps_error_m", "bias_rotation_error_deg", "bias_tracking_failures",
        "colmap_translation_error_m", "colmap_rotation_error_deg", "colmap_registered_share",
    ]  # fmt: skip
    flat: dict = {}
    for k in keys:
        vals = [d[k] for d in per_drive.values() if k in d]
        if vals:
            flat[k] = float(np.mean(vals))
            if len(vals) > 1:  # the spread over the drives beside their mean
                flat[f"{k}_std"] = float(np.std(vals))
    flat["tracking_failures_max"] = max(d["tracking_failures"] for d in per_drive.values())
    flat.update(chapter3)
    flat["drives"] = per_drive
    flat["full"] = bool(args.full)
    flat.update(provenance(SPLITS[args.split]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(flat, indent=2) + "\n")
    print(markdown(flat))
    print(f"figures: {args.out}")
    return 0


def markdown(flat: dict) -> str:
    """The tables printed at the end."""
    rows = [
        ("tracking_failures", "0 on every drive"),
        ("bad_observation_share", "<= 0.02"),
        ("translation_error_over_gps", "<= 0.5"),
        ("rotation_error_deg", "<= 0.5"),
        ("translation_error_over_colmap", "<= 1.0"),
        ("wall_time_over_colmap", "reported"),
        ("frames_per_second", ">= 10"),
    ]
    out = ["| figure (mean over drives, sigma_b 0.75) | measured | target |", "|---|---|---|"]
    for k, target in rows:
        if k in flat:
            out.append(f"| {k} | {flat[k]:.3f} | {target} |")
    out += [
        "",
        "| drive | m | kf | fails | bad obs | err m | GPS m | err/GPS | rot deg | COLMAP m | fps | bias err m |",
        "|" + "---|" * 12,
    ]
    for name, d in flat["drives"].items():
        out.append(
            f"| {name} | {d.get('length_m', 0):.0f} | {d.get('keyframes', 0)} | {d.get('tracking_failures')} "
            f"| {d.get('bad_observation_share', float('nan')):.3f} | {d.get('translation_error_m', float('nan')):.2f} "
            f"| {d.get('gps_error_m', float('nan')):.2f} | {d.get('translation_error_over_gps', float('nan')):.2f} "
            f"| {d.get('rotation_error_deg', float('nan')):.2f} | {d.get('colmap_translation_error_m', float('nan')):.2f} "
            f"| {d.get('frames_per_second', float('nan')):.1f} | {d.get('bias_translation_error_m', float('nan')):.2f} |"
        )
    ch3 = sorted(
        k[len("chapter3_") :] for k in flat if k.startswith("chapter3_") and "simulated" not in k
    )
    if ch3:
        out += [
            "",
            "| chapter 3 (known start, GPS every keyframe) | image tracks | simulated tracks |",
        ]
        out.append("|---|---|---|")
        for k in ch3:
            sim = flat.get(f"chapter3_simulated_{k}", float("nan"))
            out.append(f"| {k} | {flat[f'chapter3_{k}']:.3f} | {sim:.3f} |")
    return "\n".join(out)


if __name__ == "__main__":
    raise SystemExit(main())
