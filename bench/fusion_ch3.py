"""The chapter-3 fusion experiment (thesis §3.7, Tables 3.1-3.3, fig. 3.7) as a benchmark.

Runs :func:`slam_bridge.pipeline.run_experiment` on ``configs/slam_ch3.yaml``: by default its
short run (``quick_length_m`` metres, ``quick_sigmas`` and the bias setting), with ``--full``
the whole grid (n = 0, DPC, MPC x sigma_b in {0, 0.75, 1.5} m + a locally constant bias) on the
640 m sequence. Prints the Markdown tables (ours beside the thesis's) and writes the flat
figures to ``bench/results/fusion_ch3.json`` (``--full`` only: that file always holds the full
grid; the short run writes ``bench/results/fusion_ch3_quick.json`` instead): ``dpc_time_ratio``, ``mpc_time_ratio``,
``memory_ratio`` (n = 0 memory / hybrid memory), ``inlier_loss_max`` (0-1), the error figures
``<method>_<setting>_{t,r}_{mean,std,median}``, plus ``machine`` and ``command``.

Usage: ``python bench/fusion_ch3.py [--full] [--set key=value ...] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import time
from pathlib import Path

from geoseg.config import load_config
from slam_bridge.pipeline import ExperimentConfig, run_experiment

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--full", action="store_true", help="whole grid, 640 m sequence")
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "slam_ch3.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--out", type=Path, default=None, help="run directory (default: temp)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    cfg = load_config(ExperimentConfig, args.config, overrides=args.overrides)
    if not args.full:
        cfg = cfg.quick()
    out_dir = args.out or ROOT / "bench" / "results" / (
        "fusion_ch3_full" if args.full else "fusion_ch3_quick"
    )
    t0 = time.perf_counter()
    out = run_experiment(cfg, out_dir, force=True)
    wall = time.perf_counter() - t0
    summary = json.loads((out / "fusion_ch3.json").read_text())
    flat = {k: v for k, v in summary.items() if not isinstance(v, list | dict)}
    flat["wall_seconds"] = wall
    flat["full"] = bool(args.full)
    flat["machine"] = (
        f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cpus".strip()
    )
    flat["command"] = " ".join(
        ["python", "bench/fusion_ch3.py", *(argv if argv is not None else sys.argv[1:])]
    )
    name = "fusion_ch3.json" if args.full else "fusion_ch3_quick.json"
    results = ROOT / "bench" / "results" / name
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(json.dumps(flat, indent=2) + "\n")
    print((out / "fusion_ch3.md").read_text())
    print(f"wall time: {wall:.0f} s; figures: {results}; plots: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
