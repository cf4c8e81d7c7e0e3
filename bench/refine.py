"""How good a pseudo ground truth the global constrained bundle adjustment is (thesis §3.7).

For each drive (a 200 m summer car drive of a light city, 640x480 at 10 fps, rendered by
``bench/slam_images.py``'s :func:`render_drive`, with its two frame-rate GPS logs,
:func:`write_gps_logs`: sigma 0.75 m per axis, and the simulator's biased receiver, a locally
constant bias of up to 3 m): ``geoseg slam run`` with a GPS log, the wheel odometry, the road
DEM and the GIS building model the render writes (``gis/facades.csv``: the network bridge
associates the map points with its facades, and estimates the GPS's bias from them), then
``geoseg slam refine`` of that run with the same GPS, odometry, DEM and building model
(:func:`slam_bridge.system.refine.refine_run`, default settings), and the refined keyframes
measured against the truth (``poses.csv``). Once per GPS log.

Keys: ``pseudo_truth_error_m`` (the refined keyframes' mean horizontal error against the truth,
mean over the drives, ``_std`` their standard deviation), ``pseudo_truth_error_3d_m``,
``pseudo_truth_rotation_error_deg``; the run's own errors on the same keyframes,
``run_translation_error_m``, ``run_translation_error_3d_m``, ``run_rotation_error_deg``; the
GPS fixes' mean horizontal error, ``gps_error_m``; ``run_error_vs_pseudo_truth_m``: the run's
mean horizontal error measured against the refined run instead of the truth (what ``geoseg
slam-eval run --reference`` reports on a drive without truth), beside the same against the
truth; all with the 0.75 m GPS, and the same with the biased one prefixed ``biased_gps_``;
every drive's figures under ``per_drive``.

Usage: ``python bench/refine.py [--split report|tuning] [--data DIR]``: ``report`` (default)
runs ``REFINE_REPORT_SEEDS`` and writes ``bench/results/refine.json``; ``tuning`` runs
``REFINE_TUNING_SEEDS``, where the refinement's settings were chosen, and writes
``bench/results/refine_tuning.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402
from splits import REFINE_REPORT_SEEDS, REFINE_TUNING_SEEDS  # noqa: E402

LENGTH_M = 200.0
SPLITS = {
    "report": f"report: {LENGTH_M:.0f} m light-city car drives of world, route and GPS seeds "
    f"{REFINE_REPORT_SEEDS} (bench/splits.py REFINE_REPORT_SEEDS), never used to choose a "
    "setting",
    "tuning": f"tuning: {LENGTH_M:.0f} m light-city car drives of seeds {REFINE_TUNING_SEEDS} "
    "(bench/splits.py REFINE_TUNING_SEEDS), on which the refinement's settings were chosen",
}
#: bench key -> the per-drive figure it averages
FIGURES = {
    "pseudo_truth_error_m": "translation_error_m",
    "pseudo_truth_error_3d_m": "translation_error_3d_m",
    "pseudo_truth_rotation_error_deg": "rotation_error_deg",
    "run_translation_error_m": "run_translation_error_m",
    "run_translation_error_3d_m": "run_translation_error_3d_m",
    "run_rotation_error_deg": "run_rotation_error_deg",
    "run_error_vs_pseudo_truth_m": "run_error_vs_pseudo_truth_m",
    "gps_error_m": "gps_error_m",
    "refine_seconds": "seconds",
}


#: key prefix -> (GPS log of write_gps_logs, run folder prefix)
GPS_LOGS = {"": ("sigma0.75", "run"), "biased_gps_": ("bias", "runbias")}


def run_drive(data: Path, seed: int, log: str, name: str) -> dict:
    """Render (once), run and refine drive ``seed`` with GPS ``log``; its figures."""
    import slam_images as si

    from slam_bridge.system.reference import compare_trajectories, read_trajectory
    from slam_bridge.system.refine import refine_run

    drive = si.render_drive(data / "drives", f"drive{seed}", "car", "light", "summer_day", seed,
                            LENGTH_M)  # fmt: skip
    gps = si.write_gps_logs(drive, seed)[log]
    gis = drive / "gis"
    run = data / "bench" / f"{name}{seed}"
    logs = ["--gps", str(gps), "--odometry", str(gis / "odometry.csv"), "--dem",
            str(gis / "dem.csv"), "--buildings", str(gis / "facades.csv")]  # fmt: skip
    done = subprocess.run(
        [sys.executable, "-m", "geoseg_cli", "slam", "run", str(drive), "--out", str(run),
         "--no-progress", "--overwrite", *logs],
        check=False,
    )  # fmt: skip
    if done.returncode not in (0, 3):  # 3: a run whose status is failed (outputs written)
        raise RuntimeError(f"slam run of drive {seed} exited {done.returncode}")
    refined = refine_run(
        run, data / "bench" / f"{name}{seed}_refined", buildings=gis / "facades.csv",
        dem=gis / "dem.csv", gps=gps, odometry=gis / "odometry.csv", truth=drive / "poses.csv",
        overwrite=True,
    )  # fmt: skip
    figures = json.loads((refined / "summary.json").read_text())
    run_summary = json.loads((run / "summary.json").read_text())
    versus = compare_trajectories(read_trajectory(run), read_trajectory(refined))
    figures["run_error_vs_pseudo_truth_m"] = versus["translation_error_m"]
    figures["gps_error_m"] = run_summary["gps_error_m"]
    figures["run_status"] = run_summary["status"]
    figures["run_tracking_failures"] = run_summary["tracking_failures"]
    figures["run_associated_points"] = run_summary.get("associated_points", 0)
    return {k: v for k, v in figures.items() if k != "run"}


def main(argv: list[str] | None = None) -> int:
    from slam_bridge.system.refine import RefineConfig

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=sorted(SPLITS), default="report")
    parser.add_argument("--data", type=Path, default=ROOT / "runs" / "refine")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    meta = provenance(
        SPLITS[args.split],
        command=" ".join(
            ["python", "bench/refine.py", *(argv if argv is not None else sys.argv[1:])]
        ),
    )
    seeds = REFINE_REPORT_SEEDS if args.split == "report" else REFINE_TUNING_SEEDS
    per_drive: dict = {f"seed{seed}": {} for seed in seeds}
    for prefix, (log, name) in GPS_LOGS.items():
        for seed in seeds:
            figures = run_drive(args.data, seed, log, name)
            per_drive[f"seed{seed}"].update({f"{prefix}{k}": v for k, v in figures.items()})
    results: dict = dict(meta)
    for prefix in GPS_LOGS:
        for key, source in FIGURES.items():
            values = np.array([d[f"{prefix}{source}"] for d in per_drive.values()])
            results[f"{prefix}{key}"] = float(values.mean())
            results[f"{prefix}{key}_std"] = float(values.std(ddof=1)) if values.size > 1 else 0.0
    results.update(
        error_definition="mean over the keyframes in the world frame of the horizontal "
        "distance to the true optical centre at the same time (3d: in 3D), no alignment",
        drives=len(per_drive), seeds=list(seeds), length_m=LENGTH_M,
        config=dataclasses.asdict(RefineConfig()), per_drive=per_drive,
    )  # fmt: skip
    name = "refine.json" if args.split == "report" else "refine_tuning.json"
    path = ROOT / "bench" / "results" / name
    path.write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps({k: v for k, v in results.items() if k not in ("per_drive", "config")},
                     indent=1))  # fmt: skip
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
