"""Building constraints chosen by networks: the chapter-4 experiment (thesis §4.2.4.2, §4.3.4).

Runs :func:`slam_bridge.experiments.buildings_ch4.run_experiment` (``configs/buildings_ch4.yaml``)
and writes its flat figures to ``bench/results/buildings_ch4.json``. With ``--full``, a 1.2 km
drive with loops through a ``dense_occlusion`` city at 640x480, 10 fps; without, its first
``quick_length_m``. Methods (each on the same rendered drive, same front end): ``nobuild``,
``raycast`` (chapter-2 baseline), ``dirichlet`` (naive CNN + Dirichlet filter), ``bayes`` (joint
network + eq. 4.14), ``oracle`` (the renderer's truth); models ``exact`` (true facades,
odometry + DEM, no GPS, known first pose, a 60-keyframe window) and ``gis`` (the render's
erroneous GIS model, GPS sigma 0.75 m + DEM + odometry).

Keys (``<m>`` a method, ``<model>`` ``exact`` or ``gis``): ``association_precision_<m>``,
``association_recall_<m>`` (against the exact model; ``..._<m>_gis`` beside them),
``translation_error_m_<m>_<model>`` (mean horizontal error of the keyframes),
``rotation_error_deg_<m>_<model>``, ``tracking_failures_<m>_<model>``,
``inference_ms_per_keyframe`` and ``association_ms_per_keyframe`` (the joint network's bridge:
worker time per keyframe on this machine's CPU, in the asynchronous run), ``async_time_ratio`` (main-loop time per
keyframe with the asynchronous worker on / off, GIS model, same drive: the median of
``timing_pairs`` back-to-back pairs of runs, each pair's ratio under ``async_time_ratios``;
parted into ``building_rows_time_ratio``, the asynchronous run's building rows replayed without
its worker against ``nobuild``, and ``async_time_ratio_same_rows``, the run with its worker
against that replay: :mod:`slam_bridge.experiments.replay`),
``constraint_lag_keyframes_median`` / ``_max``; every run's figures under ``runs``.

Usage: ``python bench/buildings_ch4.py [--full] [--data DIR] [--out DIR] [--force]``
(``--data``: where the drive is rendered and reused; ``--out``: the experiment's folder with
its runs and pictures, default ``runs/bench/buildings_ch4``).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402

SPLIT = (
    "tuning: the chapter-4 drive of configs/buildings_ch4.yaml (world and route seed 7, or "
    "--set overrides), on which the exact model's window and radius_m were chosen"
)


def main(argv: list[str] | None = None) -> int:
    from geoseg.config import load_config
    from slam_bridge.experiments.buildings_ch4 import BuildingsConfig, run_experiment

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the 1.2 km drive")
    parser.add_argument("--data", type=Path, default=None, help="where the drive is rendered")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench" / "buildings_ch4")
    parser.add_argument("--force", action="store_true", help="rerun the saved runs")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")

    meta = provenance(
        SPLIT,
        command=" ".join(
            ["python", "bench/buildings_ch4.py", *(argv if argv is not None else sys.argv[1:])]
        ),
    )
    config = ROOT / "configs" / "buildings_ch4.yaml"
    cfg = load_config(BuildingsConfig, config, overrides=args.overrides)
    cfg = cfg if args.full else cfg.quick()
    out = run_experiment(cfg, args.out, data_dir=args.data, force=args.force, overwrite=True)
    summary = json.loads((out / "buildings_ch4.json").read_text())
    summary["setting"] = "full" if args.full else "quick"
    summary.update(meta)
    results = ROOT / "bench" / "results" / "buildings_ch4.json"
    results.write_text(json.dumps(summary, indent=1, sort_keys=True))
    print((out / "buildings_ch4.md").read_text())
    print(f"wrote {results}; runs and pictures in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
