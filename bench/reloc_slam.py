"""Relocalisation inside the SLAM: an image base starts, constrains and recovers the run.

For each drive of ``bench/splits.py``'s ``RELOC_SLAM_REPORT_SEEDS``: a summer car drive
(``light`` city, 640x480, 10 fps, ``--length-m`` long) and a winter traversal of the same
route at ``BASE_FPS`` frames per second, made an image base (``geoseg base build``). Three
runs of the image SLAM, each with wheel odometry and the road DEM:

* ``noGPS_base``: no GPS, the base's fixes only (``geoseg slam run --base``);
* ``gps_only``: a GPS of sigma 0.75 m per axis at the frame rate, no base;
* ``gps_plus_base``: both.

Keys: ``noGPS_base_translation_error_m`` (target <= 0.5), ``noGPS_base_tracking_failures``
(target 0; the sum over the drives), ``noGPS_base_segments`` (maps started, summed: 1 per
drive is a run that never restarted), ``base_constrained_share`` (keyframes fused with a base
fix, no-GPS run), ``gps_plus_base_translation_error_m`` (target <= ``gps_only``'s),
``gps_only_translation_error_m``, ``base_fix_error_m`` (the fixes themselves against the
truth), and for the runs with a base the errors before the run's closing adjustment on the
fixes: of the positions the loop left (``noGPS_base_loop_translation_error_m``,
``gps_plus_base_loop_translation_error_m``) and of those it gave each keyframe as it went
(``..._online_translation_error_m``); each the mean over the drives with ``_std`` beside it, every drive's under
``per_drive``; ``base_structure_fix_error_m`` the fixes placed on the base's points alone, and
the counts summed over the drives: ``base_frames_localised`` (retrieval), ``base_frames_tracked``
(placed on the points without it), ``base_fixes``, ``base_fixes_from_structure``. The base
traverses the same lane as the drive (the renderer drives one route per seed): its images are
never more than half its spacing from a query, with no lateral offset.

Usage: ``python bench/reloc_slam.py [--tuning] [--drives 31,32] [--length-m 200] [--data DIR]``;
writes ``bench/results/reloc_slam.json`` (``--tuning``: ``reloc_slam_tuning.json``, the tuning
drives).
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402
from splits import RELOC_SLAM_REPORT_SEEDS, RELOC_SLAM_TUNING_SEEDS  # noqa: E402

BASE_FPS = 2.5  # a base image every ~3.5 m at city speed
LENGTH_M = 200.0
SPLIT = (
    f"report: light-city drives with world and route seeds {RELOC_SLAM_REPORT_SEEDS} "
    "(bench/splits.py); no setting was chosen on them"
)
TUNING_SPLIT = (
    f"tuning: light-city drives with world and route seeds {RELOC_SLAM_TUNING_SEEDS} "
    "(bench/splits.py), on which the points' inlier gate and the base fixes' weights, tracking "
    "and refit distance were chosen"
)
RUNS = ("noGPS_base", "gps_only", "gps_plus_base")


def render_pair(data: Path, seed: int, length_m: float) -> tuple[Path, Path, dict[str, Path]]:
    """The summer drive with its GPS logs, and the winter traversal as an image base."""
    import slam_images as si

    from geoseg.synth.export import render_sequence
    from geoseg.synth.world import WorldConfig, build_world

    drive = si.render_drive(data, f"drive{seed}", "car", "light", "summer_day", seed, length_m)
    gps = si.write_gps_logs(drive, seed)
    frames = sum(1 for _ in open(drive / "poses.csv")) - 1
    config = WorldConfig(seed=seed, preset="light", blocks_x=4, blocks_y=3)
    winter = render_sequence(
        config, data / f"winter{seed}", frames=int(frames * BASE_FPS / si.FPS) + 1,
        condition="winter", rig="car", image_size=si.SIZE, fps=BASE_FPS, seed=seed,
        world=build_world(config),
    )  # fmt: skip
    base = data / f"base{seed}"
    if not (base / "poses.csv").is_file():
        subprocess.run(
            [sys.executable, "-m", "geoseg_cli", "base", "build", str(winter), "--out", str(base)],
            check=True,
        )
    return drive, base, gps


def run_one(drive: Path, gps: Path | None, base: Path | None, fixes=None) -> tuple[dict, object]:
    """One SLAM run's figures, and the base's fixes (``fixes``: those of an earlier run of the
    same drive and base, reused rather than localised again)."""
    from geoseg.config import load_config
    from slam_bridge.system.image_slam import (
        ImageSlamConfig,
        base_fixes_of,
        evaluate_run,
        load_inputs,
        run_on_images,
    )

    cfg = load_config(ImageSlamConfig, ROOT / "configs" / "slam_images.yaml")
    inputs = load_inputs(
        drive, gps=gps, base=base, odometry=drive / "gis" / "odometry.csv",
        dem=drive / "gis" / "dem.csv",
    )  # fmt: skip
    inputs.base_fixes = fixes if base is not None else None
    result, _ = run_on_images(inputs, cfg, progress=False)
    out = {
        "keyframes": result.map.num_keyframes,
        "segments": int(result.map.segment.max()) + 1,
        "tracking_failures": result.tracking_failures,
        "georeferenced": bool(result.georeferenced),
    }
    if result.georeferenced:
        out.update(evaluate_run(result, inputs))
    fixes = base_fixes_of(inputs, cfg)
    if fixes is not None:
        out["base_constrained_share"] = sum("base" in r.constraints for r in result.records) / max(
            result.map.num_keyframes, 1
        )
        t_true, _, T_true = inputs.truth
        ok = np.isfinite(fixes.xy[:, 0])
        idx = np.searchsorted(t_true, fixes.timestamps[ok])
        errors = np.linalg.norm(fixes.xy[ok] - T_true[idx, :2], axis=1)
        out["base_fix_error_m"] = float(errors.mean())
        on_points = np.array([m == "structure" for m in fixes.methods])[ok]
        if on_points.any():
            out["base_structure_fix_error_m"] = float(errors[on_points].mean())
        out.update(fixes.summary())
    return out, fixes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", default=None, help="seeds (default: the report drives)")
    parser.add_argument(
        "--tuning", action="store_true",
        help="the tuning drives (bench/splits.py), written to reloc_slam_tuning.json",
    )  # fmt: skip
    parser.add_argument("--length-m", type=float, default=LENGTH_M)
    parser.add_argument("--data", type=Path, default=ROOT / "runs" / "bench" / "reloc_slam")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    default = RELOC_SLAM_TUNING_SEEDS if args.tuning else RELOC_SLAM_REPORT_SEEDS
    seeds = [int(s) for s in (args.drives or ",".join(map(str, default))).split(",") if s.strip()]
    split = TUNING_SPLIT if args.tuning else SPLIT
    meta = provenance(
        split if seeds == list(default) else f"a subset of {split.split(':')[0]}: seeds {seeds}",
        command=" ".join(["python", "bench/reloc_slam.py", *(argv or sys.argv[1:])]),
    )
    per_drive: dict[str, dict] = {}
    for seed in seeds:
        drive, base, gps = render_pair(args.data, seed, args.length_m)
        runs = {}
        runs["noGPS_base"], fixes = run_one(drive, None, base)
        runs["gps_only"], _ = run_one(drive, gps["sigma0.75"], None)
        runs["gps_plus_base"], _ = run_one(drive, gps["sigma0.75"], base, fixes)
        per_drive[str(seed)] = {
            f"{name}_{key}": value
            for name, run in runs.items()
            for key, value in run.items()
            if isinstance(value, (int, float)) and not isinstance(value, bool)
        }
        logging.info("drive %d: %s", seed, per_drive[str(seed)])
    figures = {
        "noGPS_base_translation_error_m": "noGPS_base_translation_error_m",
        "noGPS_base_rotation_error_deg": "noGPS_base_rotation_error_deg",
        "noGPS_base_loop_translation_error_m": "noGPS_base_loop_translation_error_m",
        "noGPS_base_online_translation_error_m": "noGPS_base_online_translation_error_m",
        "base_constrained_share": "noGPS_base_base_constrained_share",
        "base_fix_error_m": "noGPS_base_base_fix_error_m",
        "base_structure_fix_error_m": "noGPS_base_base_structure_fix_error_m",
        "gps_plus_base_translation_error_m": "gps_plus_base_translation_error_m",
        "gps_plus_base_loop_translation_error_m": "gps_plus_base_loop_translation_error_m",
        "gps_plus_base_online_translation_error_m": "gps_plus_base_online_translation_error_m",
        "gps_only_translation_error_m": "gps_only_translation_error_m",
        "gps_error_m": "gps_only_gps_error_m",
    }
    results: dict = dict(meta)
    for key, source in figures.items():
        values = [d[source] for d in per_drive.values() if source in d]
        if len(values) == len(per_drive):  # a figure every drive has (else: under per_drive)
            results[key] = float(np.mean(values))
            results[f"{key}_std"] = float(np.std(values, ddof=1)) if len(values) > 1 else 0.0
    for key in ("tracking_failures", "segments"):
        results[f"noGPS_base_{key}"] = int(sum(d[f"noGPS_base_{key}"] for d in per_drive.values()))
    for key in ("frames_localised", "frames_tracked", "fixes", "fixes_from_structure"):
        results[f"base_{key}"] = int(sum(d[f"noGPS_base_base_{key}"] for d in per_drive.values()))
    results["drives"] = len(per_drive)
    results["per_drive"] = per_drive
    path = (
        ROOT
        / "bench"
        / "results"
        / ("reloc_slam_tuning.json" if args.tuning else "reloc_slam.json")
    )
    path.write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps({k: v for k, v in results.items() if k != "per_drive"}, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
