"""The chapter-4 experiment on its reporting drives: mean and spread over cities never tuned on.

``bench/buildings_ch4.py`` runs the experiment on the drive its settings were chosen on
(``configs/buildings_ch4.yaml``, seed 7). This bench runs the same experiment, settings
unchanged, on the drives of ``bench/splits.py``'s ``CH4_REPORT_SEEDS`` (each a new
``dense_occlusion`` city and route, ``CH4_REPORT_LENGTH_M`` long), twice per drive:

* ``sync``: as the chapter-4 bench runs it (the network's bridge inline, every second keyframe
  labelled): methods ``nobuild``, ``raycast`` (the geometric rule), ``bayes`` (the joint
  network + eq. 4.14) and ``oracle`` (the renderer's truth), models ``exact`` (true facades,
  odometry + DEM, no GPS) and ``gis`` (the GIS model with its errors, GPS 0.75 m + DEM +
  odometry);
* ``async``: ``bayes`` as a user runs it (``geoseg slam run --buildings``: the asynchronous
  worker, every keyframe labelled, its results applied when ready): keys with ``_async``.

Keys: for every figure ``<key>`` of the chapter-4 bench (``translation_error_m_<m>_<model>``,
``rotation_error_deg_<m>_<model>``, ``tracking_failures_<m>_<model>``,
``association_precision_<m>`` / ``association_recall_<m>`` against the exact model, ``..._gis``
beside them), ``<key>_mean`` and ``<key>_std`` (sample standard deviation over the drives) and
the drives' values under ``per_drive``; ``async_minus_sync_translation_error_m_bayes_<model>``
(mean of the per-drive differences). The worker's time cost (``async_time_ratio``) needs an
idle machine and the long drive: ``bench/buildings_ch4.py``.

Usage: ``python bench/buildings_ch4_report.py [--drives 21,22] [--out DIR]``; writes
``bench/results/buildings_ch4_report.json`` (the drives' renders and runs under ``--out``,
default ``runs/bench/buildings_ch4_report``, reused when run again).
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
from splits import CH4_REPORT_LENGTH_M, CH4_REPORT_SEEDS, CH4_TUNING_SEEDS  # noqa: E402

SPLIT = (
    f"report: dense_occlusion drives with world and route seeds {CH4_REPORT_SEEDS}, "
    f"{CH4_REPORT_LENGTH_M:g} m each, never used to choose a setting (the settings were chosen "
    f"on seeds {CH4_TUNING_SEEDS}: bench/splits.py)"
)
SYNC_METHODS = ["nobuild", "raycast", "bayes", "oracle"]
MODELS = ["exact", "gis"]
#: the per-run figures averaged over the drives
RUN_KEYS = ("translation_error_m", "rotation_error_deg", "tracking_failures")


def drive_config(base, seed: int, length_m: float, asynchronous: bool):
    """``base`` (a :class:`BuildingsConfig`) on drive ``seed``: the ``sync`` pass, or the
    ``async`` pass (``bayes`` with the bridge as ``geoseg slam run --buildings`` runs it)."""
    drive = dataclasses.replace(base.drive, world_seed=seed, route_seed=seed, length_m=length_m)
    cfg = dataclasses.replace(base, drive=drive, models=list(MODELS), async_run=False)
    cfg = dataclasses.replace(cfg, timing_pairs=0)
    if not asynchronous:
        return dataclasses.replace(cfg, methods=list(SYNC_METHODS))
    from slam_bridge.bridge.builder import BridgeConfig

    user = BridgeConfig()  # what slam run's --buildings uses: asynchronous, every keyframe
    bridge = dataclasses.replace(
        cfg.bridge, asynchronous=user.asynchronous, infer_every=user.infer_every,
        lag_keyframes=user.lag_keyframes,
    )  # fmt: skip
    return dataclasses.replace(cfg, methods=["bayes"], bridge=bridge)


def drive_figures(sync: dict, asynchronous: dict) -> dict[str, float]:
    """One drive's flat figures from its two passes' ``buildings_ch4.json``."""
    figures = {k: v for k, v in sync.items() if _is_figure(k, v)}
    for key, value in asynchronous.items():
        if _is_figure(key, value) and "bayes" in key:
            figures[f"{key}_async"] = value
    return figures


def _is_figure(key: str, value) -> bool:
    prefixes = RUN_KEYS + ("association_precision", "association_recall")
    return key.startswith(prefixes) and isinstance(value, (int, float))


def aggregate(per_drive: dict[str, dict[str, float]]) -> dict[str, float]:
    """``<key>_mean`` / ``<key>_std`` over the drives (keys every drive has), and the mean
    async - sync difference of ``bayes``'s error per model."""
    drives = list(per_drive.values())
    common = sorted(set.intersection(*(set(d) for d in drives)))
    out: dict[str, float] = {}
    for key in common:
        values = np.array([d[key] for d in drives], dtype=float)
        out[f"{key}_mean"] = float(values.mean())
        out[f"{key}_std"] = float(values.std(ddof=1)) if len(values) > 1 else 0.0
    for model in MODELS:
        sync, late = (
            f"translation_error_m_bayes_{model}",
            f"translation_error_m_bayes_{model}_async",
        )
        if sync in common and late in common:
            out[f"async_minus_sync_translation_error_m_bayes_{model}"] = float(
                np.mean([d[late] - d[sync] for d in drives])
            )
    return out


def main(argv: list[str] | None = None) -> int:
    from geoseg.config import load_config
    from slam_bridge.experiments.buildings_ch4 import BuildingsConfig, run_experiment

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--drives", default=",".join(map(str, CH4_REPORT_SEEDS)),
        help="comma-separated seeds (default: bench/splits.py's CH4_REPORT_SEEDS)",
    )  # fmt: skip
    parser.add_argument("--length-m", type=float, default=CH4_REPORT_LENGTH_M)
    parser.add_argument(
        "--out", type=Path, default=ROOT / "runs" / "bench" / "buildings_ch4_report"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    seeds = [int(s) for s in args.drives.split(",") if s.strip()]
    tuned = sorted(set(seeds) & set(CH4_TUNING_SEEDS))
    if tuned:
        parser.error(f"--drives {tuned}: settings were chosen on these (bench/splits.py)")
    meta = provenance(
        SPLIT if seeds == list(CH4_REPORT_SEEDS) and args.length_m == CH4_REPORT_LENGTH_M
        else f"report (a subset or another length): seeds {seeds}, {args.length_m:g} m",
        command=" ".join(["python", "bench/buildings_ch4_report.py", *(argv or sys.argv[1:])]),
    )  # fmt: skip
    base = load_config(BuildingsConfig, ROOT / "configs" / "buildings_ch4.yaml")
    per_drive: dict[str, dict[str, float]] = {}
    for seed in seeds:
        folder = args.out / f"seed{seed}"
        passes = {}
        for name, asynchronous in (("sync", False), ("async", True)):
            cfg = drive_config(base, seed, args.length_m, asynchronous)
            out = run_experiment(cfg, folder / name, data_dir=folder / "drive", overwrite=True)
            passes[name] = json.loads((out / "buildings_ch4.json").read_text())
        per_drive[str(seed)] = drive_figures(passes["sync"], passes["async"])
        per_drive[str(seed)]["drive_length_m"] = passes["sync"]["drive_length_m"]
        logging.info("drive %d: %s", seed, per_drive[str(seed)])
    results = {**meta, **aggregate(per_drive), "drives": len(per_drive), "per_drive": per_drive}
    path = ROOT / "bench" / "results" / "buildings_ch4_report.json"
    path.write_text(json.dumps(results, indent=1) + "\n")
    print(json.dumps({k: v for k, v in results.items() if k.endswith("_mean")}, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
