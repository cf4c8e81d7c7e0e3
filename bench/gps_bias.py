"""A biased GPS caught by the building model (thesis §4.4).

The chapter-4 experiment (:mod:`slam_bridge.experiments.buildings_ch4`, ``configs/
buildings_ch4.yaml``) on short drives with a *biased* GPS: the ``gis`` building model (its
shifted and rotated footprints, missing and extra buildings), wheel odometry, the road DEM, and
:func:`geoseg.synth.gps.simulate_gps`'s default receiver at the frame rate (a locally constant
bias of up to 3 m, noise, dropouts; ``BuildingsConfig.gps_bias``) in place of the unbiased
``sigma_b = 0.75 m``. Three runs per drive, each started as a user starts it (two views,
georeferenced by the GPS), and two with the unbiased GPS:

* ``nobuild``: no building constraint (the map follows the biased fixes);
* ``bayes`` with ``slam.gps_bias.enabled`` true: the joint network's building constraints
  (eq. 4.14) and the GPS bias estimated from the facades and removed from the fixes
  (:mod:`slam_bridge.bridge.gps_bias`);
* ``bayes`` with it false: the building constraints alone.

Keys: ``bias_ratio_buildings`` (the runs' mean horizontal keyframe error over the fixes' mean
error on the same keyframes, pooled over the drives: ``sum(SLAM) / sum(fixes)``; target <= 0.5),
``bias_ratio_buildings_noestimate`` (the same without the bias estimate), ``bias_ratio_nobuild``
(no building constraint); with the unbiased GPS of the chapter-4 experiment (``sigma_b =
0.75 m``), ``unbiased_ratio_buildings`` and ``unbiased_ratio_buildings_noestimate`` (does
the estimate cost a GPS without bias anything?); ``<key>_mean`` and ``<key>_std`` over the
drives' own ratios; the errors themselves (``translation_error_m_<run>_mean``,
``gps_error_m_<run>_mean``); per drive under ``drives`` (its ratios, errors, tracking
failures and the mean bias of its fixes, ``true_bias_m``).

Usage: ``python bench/gps_bias.py [--split tuning|report] [--data DIR] [--out DIR] [--set
KEY=VALUE]`` (``--set``: overrides of ``BuildingsConfig``, e.g.
``slam.gps_bias.memory_s=10``). ``--split report`` (default) runs :data:`REPORT_SEEDS` and
writes ``bench/results/gps_bias.json``; ``--split tuning`` runs :data:`TUNING_SEEDS`, where the
estimator's settings were chosen, and writes ``bench/results/gps_bias_tuning.json``. Runs are
saved under ``--out`` and reused while their settings are unchanged.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402
from splits import GPS_BIAS_REPORT_SEEDS, GPS_BIAS_TUNING_SEEDS  # noqa: E402

#: where the bias estimate's settings were chosen, and the drives reported: bench/splits.py
TUNING_SEEDS = GPS_BIAS_TUNING_SEEDS
REPORT_SEEDS = GPS_BIAS_REPORT_SEEDS
#: each drive's length (CPU is scarce: three runs of a 150 m drive take a few minutes)
LENGTH_M = 150.0

SPLITS = {
    "tuning": f"tuning: the {LENGTH_M:.0f} m chapter-4 drives of TUNING_SEEDS (world, route and "
    f"GPS seeds {', '.join(map(str, TUNING_SEEDS))}), on which slam.gps_bias's settings were "
    "chosen",
    "report": f"report: the {LENGTH_M:.0f} m chapter-4 drives of REPORT_SEEDS (world, route and "
    f"GPS seeds {', '.join(map(str, REPORT_SEEDS))}), never used to choose a setting",
}
#: run name -> (method, estimate the bias, biased GPS)
RUNS = {
    "nobuild": ("nobuild", False, True),
    "buildings": ("bayes", True, True),
    "buildings_noestimate": ("bayes", False, True),
    # the unbiased GPS (sigma_b = 0.75 m): does the estimate cost a GPS without bias anything?
    "unbiased_buildings": ("bayes", True, False),
    "unbiased_buildings_noestimate": ("bayes", False, False),
}

logger = logging.getLogger("bench.gps_bias")


def drive_config(base, seed: int, estimate: bool, biased: bool, methods: list[str]):
    """The experiment of one drive: ``base`` on drive ``seed`` with the biased GPS (or the
    unbiased one of ``base.gps_sigma_m``)."""
    slam = dataclasses.replace(
        base.slam, gps_bias=dataclasses.replace(base.slam.gps_bias, enabled=estimate)
    )
    drive = dataclasses.replace(base.drive, world_seed=seed, route_seed=seed, length_m=LENGTH_M)
    return dataclasses.replace(
        base, drive=drive, slam=slam, gps_bias=biased, seed=seed, methods=methods,
        models=["gis"], async_run=False, timing_pairs=0,
    )  # fmt: skip


def run_drive(base, seed: int, data: Path, out: Path) -> dict:
    """The runs of drive ``seed``: their figures by run name (:data:`RUNS`)."""
    from slam_bridge.experiments.buildings_ch4 import run_experiment

    figures = {}
    for group in sorted({(e, b) for _, e, b in RUNS.values()}, reverse=True):
        names = [n for n, (_, e, b) in RUNS.items() if (e, b) == group]
        methods = [RUNS[n][0] for n in names]
        cfg = drive_config(base, seed, *group, methods)
        folder = (
            out
            / f"seed{seed}"
            / (("estimate" if group[0] else "plain") + ("" if group[1] else "_unbiased"))
        )
        done = run_experiment(cfg, folder, data_dir=data / f"seed{seed}", overwrite=True)
        runs = json.loads((done / "buildings_ch4.json").read_text())["runs"]
        for name, method in zip(names, methods):
            figures[name] = runs[f"{method}_gis"]
    return figures


def gps_bias_of(data: Path, seed: int) -> float:
    """Mean magnitude of the true bias of the drive's valid fixes, metres."""
    from slam_bridge.csv_columns import read_columns

    cols = read_columns(
        data / f"seed{seed}" / f"gps_bias_seed{seed}.csv", ["valid", "bias_x", "bias_y"]
    )
    valid = cols["valid"] > 0.5
    return float(np.hypot(cols["bias_x"], cols["bias_y"])[valid].mean())


def ratio_key(name: str) -> str:
    """The ratio key of run ``name``: ``bias_ratio_<name>`` with the biased GPS,
    ``unbiased_ratio_<name less its prefix>`` with the unbiased one."""
    if RUNS[name][2]:
        return f"bias_ratio_{name}"
    return f"unbiased_ratio_{name.removeprefix('unbiased_')}"


def summarize(per_drive: dict[str, dict]) -> dict:
    """The flat keys (module docstring) from each drive's figures by run name."""
    out: dict = {"drives": {}}
    for drive, figures in per_drive.items():
        d: dict = {}
        for name, f in figures.items():
            if "error" in f or "translation_error_m" not in f:
                d[f"failed_{name}"] = f.get("error", "no keyframe in the world frame")
                continue
            d[f"translation_error_m_{name}"] = f["translation_error_m"]
            d[f"gps_error_m_{name}"] = f["gps_error_m"]
            d[ratio_key(name)] = f["translation_error_m"] / f["gps_error_m"]
            d[f"tracking_failures_{name}"] = f["tracking_failures"]
        out["drives"][drive] = d
    for name in RUNS:
        key = ratio_key(name)
        ok = [d for d in out["drives"].values() if key in d]
        if not ok:
            continue
        slam = np.array([d[f"translation_error_m_{name}"] for d in ok])
        fixes = np.array([d[f"gps_error_m_{name}"] for d in ok])
        ratios = np.array([d[key] for d in ok])
        out[key] = float(slam.sum() / fixes.sum())
        out[f"{key}_mean"], out[f"{key}_std"] = float(ratios.mean()), float(ratios.std())
        out[f"translation_error_m_{name}_mean"] = float(slam.mean())
        out[f"translation_error_m_{name}_std"] = float(slam.std())
        out[f"gps_error_m_{name}_mean"] = float(fixes.mean())
        out[f"drives_{name}"] = len(ok)
    return out


def markdown(summary: dict) -> str:
    """A row per drive: the fixes' bias, then each run's error and ratio."""
    head = " | ".join(f"{n} m (ratio)" for n in RUNS)
    lines = [
        f"| drive | fixes' bias m | biased fixes m | {head} |",
        "|---|---|---|" + "---|" * len(RUNS),
    ]
    for drive, d in summary["drives"].items():
        cells = [
            f"{d[f'translation_error_m_{n}']:.3f} ({d[ratio_key(n)]:.3f})"
            if ratio_key(n) in d
            else "failed"
            for n in RUNS
        ]
        fixes = d.get("gps_error_m_buildings", float("nan"))
        lines.append(
            f"| {drive} | {d['true_bias_m']:.3f} | {fixes:.3f} | " + " | ".join(cells) + " |"
        )
    for name in RUNS:
        key = ratio_key(name)
        if key in summary:
            lines.append(
                f"- `{key}`: {summary[key]:.3f} (per drive {summary[f'{key}_mean']:.3f} +- "
                f"{summary[f'{key}_std']:.3f})"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from geoseg.config import load_config
    from slam_bridge.experiments.buildings_ch4 import BuildingsConfig

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=sorted(SPLITS), default="report")
    parser.add_argument("--data", type=Path, default=ROOT / "runs" / "gps_bias" / "drives")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "gps_bias" / "bench")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")

    meta = provenance(
        SPLITS[args.split],
        command=" ".join(
            ["python", "bench/gps_bias.py", *(argv if argv is not None else sys.argv[1:])]
        ),
    )
    base = load_config(
        BuildingsConfig, ROOT / "configs" / "buildings_ch4.yaml", overrides=args.overrides
    )
    seeds = TUNING_SEEDS if args.split == "tuning" else REPORT_SEEDS
    per_drive = {}
    for seed in seeds:
        per_drive[f"seed{seed}"] = run_drive(base, seed, args.data, args.out)
    summary = summarize(per_drive)
    for seed in seeds:
        summary["drives"][f"seed{seed}"]["true_bias_m"] = gps_bias_of(args.data, seed)
    summary["length_m"] = LENGTH_M
    summary["seeds"] = list(seeds)
    summary["overrides"] = list(args.overrides)
    summary.update(meta)
    name = "gps_bias.json" if args.split == "report" else "gps_bias_tuning.json"
    results = ROOT / "bench" / "results" / name
    results.write_text(json.dumps(summary, indent=1, sort_keys=True))
    print(markdown(summary))
    print(f"wrote {results}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
