"""The chapter-3 fusion experiment (thesis §3.7, Tables 3.1-3.3, fig. 3.7) as a benchmark.

Runs :func:`slam_bridge.experiments.fusion_ch3.run_experiment` on ``configs/slam_ch3.yaml``: by default its
short run (``quick_length_m`` metres, ``quick_sigmas`` and the bias setting), with ``--full``
the whole grid (n = 0, DPC, MPC x sigma_b in {0, 0.75, 1.5} m + a locally constant bias) on the
640 m sequence. Prints the Markdown tables (ours beside the thesis's) and writes the flat
figures to ``bench/results/fusion_ch3.json`` (``--full`` only: that file always holds the full
grid; the short run writes ``bench/results/fusion_ch3_quick.json`` instead): ``dpc_time_ratio``, ``mpc_time_ratio``,
``memory_ratio`` (n = 0 memory / hybrid memory), ``inlier_loss_max`` (0-1), the error figures
``<method>_<setting>_{t,r}_{mean,std,median}``, plus ``machine`` and ``command``.

``--drives SEED ...`` also runs the grid on other drives (``sequence.seed``) and records, under
``drives`` in the JSON, the mean and worst of each figure over them: one drive's inlier loss
and height drift are a single draw (session notes: the bench drive is a favourable one).

Usage: ``python bench/fusion_ch3.py [--full] [--drives SEED ...] [--set key=value ...] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from geoseg.config import load_config
from slam_bridge.errors import SlamError
from slam_bridge.experiments.fusion_ch3 import ExperimentConfig, run_experiment

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402


def other_drives(cfg: ExperimentConfig, seeds: list[int], out_dir: Path) -> dict:
    """Run the grid of ``cfg`` on each drive ``sequence.seed = s`` (into ``out_dir/drive_<s>``)
    and return ``{"seeds", "failures" (per seed), "mean", "max"}``, the last two over the drives
    that produced results, of every numeric figure that they all report. Prints the mean
    translation errors and inlier losses.

    Raises:
        SlamError: no drive produced a result.
    """
    figures, failures = [], {}
    for seed in seeds:
        cfg_s = dataclasses.replace(cfg, sequence=dataclasses.replace(cfg.sequence, seed=seed))
        try:
            out = run_experiment(cfg_s, out_dir / f"drive_{seed}", force=True)
        except SlamError as err:  # every run of the drive failed (e.g. lost tracking)
            failures[str(seed)] = [{"error": str(err)}]
            continue
        summary = json.loads((out / "fusion_ch3.json").read_text())
        failures[str(seed)] = summary.get("failures", [])
        figures.append(
            {k: v for k, v in summary.items() if isinstance(v, int | float) and k != "wall_seconds"}
        )
    if not figures:
        raise SlamError(f"drives {seeds}: every run failed: {failures}")
    common = sorted(set.intersection(*(set(f) for f in figures)))
    mean = {k: float(np.mean([f[k] for f in figures])) for k in common}
    worst = {k: float(np.max([f[k] for f in figures])) for k in common}
    print(f"\n### Over the drives {seeds} (mean; worst)\n")
    print("| figure | mean | worst |\n|---|---|---|")
    for k in common:
        if k.endswith(("_t_mean", "_inlier_loss")):
            print(f"| {k} | {mean[k]:.4f} | {worst[k]:.4f} |")
    return {"seeds": list(seeds), "failures": failures, "mean": mean, "max": worst}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--full", action="store_true", help="whole grid, 640 m sequence")
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "slam_ch3.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--out", type=Path, default=None, help="run directory (default: temp)")
    parser.add_argument(
        "--drives",
        type=int,
        nargs="+",
        default=None,
        metavar="SEED",
        help="also run the grid on these drives (sequence.seed) and record mean / worst figures",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    cfg = load_config(ExperimentConfig, args.config, overrides=args.overrides)
    if not args.full:
        cfg = cfg.quick()
    out_dir = args.out or ROOT / "bench" / "results" / (
        "fusion_ch3_full" if args.full else "fusion_ch3_quick"
    )
    meta = provenance(
        f"the chapter-3 simulated drive of {args.config.name} (sequence seed {cfg.sequence.seed})"
        + (f" and drives {', '.join(map(str, args.drives))}" if args.drives else "")
        + ": the thesis's experiment, not a held-out split",
        command=" ".join(
            ["python", "bench/fusion_ch3.py", *(argv if argv is not None else sys.argv[1:])]
        ),
    )
    t0 = time.perf_counter()
    out = run_experiment(cfg, out_dir, force=True)
    wall = time.perf_counter() - t0
    summary = json.loads((out / "fusion_ch3.json").read_text())
    flat = {k: v for k, v in summary.items() if not isinstance(v, list | dict)}
    flat["wall_seconds"] = wall
    flat["full"] = bool(args.full)
    flat.update(meta)
    if args.drives:
        flat["drives"] = other_drives(cfg, args.drives, out_dir)
    name = "fusion_ch3.json" if args.full else "fusion_ch3_quick.json"
    results = ROOT / "bench" / "results" / name
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(json.dumps(flat, indent=2) + "\n")
    print((out / "fusion_ch3.md").read_text())
    print(f"wall time: {wall:.0f} s; figures: {results}; plots: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
