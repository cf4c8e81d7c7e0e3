"""``geoseg slam-eval``: localisation experiments on the synthetic world.

Example (the chapter-3 experiment, thesis §3.7)::

    geoseg slam-eval fusion --config configs/slam_ch3.yaml --out out/fusion_ch3
    geoseg slam-eval fusion --config configs/slam_ch3.yaml --full
    geoseg slam-eval fusion --set slam.window.n=20 --set quick_length_m=100

``fusion`` runs :func:`slam_bridge.experiments.fusion_ch3.run_experiment`: by default the short run of the
config (``quick_length_m``, ``quick_sigmas``, ``quick_bias``), with ``--full`` the whole grid
(every method and GPS setting on the full sequence). It writes ``fusion_ch3.md`` (Tables
3.1-3.3 beside the thesis's figures), ``fusion_ch3.json``, ``trajectory.png`` and ``memory.png``
(fig. 3.7) to ``--out``, and prints the tables. A directory already holding the results of the
same config is not recomputed (``--force`` recomputes).
"""

from __future__ import annotations

import argparse
from pathlib import Path

DEFAULT_CONFIG = Path("configs/slam_ch3.yaml")
EXPERIMENTS = ("fusion",)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Run the chapter-3 fusion experiment (thesis section 3.7) on a simulated drive: plain "
        "keyframe bundle adjustment (n = 0) against the hybrid BA / pose-graph windows (DPC, "
        "MPC), fused with GPS by the barrier term. By default the short run (the config's "
        "quick_length_m, quick_sigmas, quick_bias; configs/slam_ch3.yaml: 160 m, GPS "
        "sigma_b 0.75 m and the biased GPS); --full runs the whole grid (3 methods x 4 GPS "
        "settings on the full sequence)."
    )
    parser.add_argument(
        "experiment", choices=EXPERIMENTS, help="which experiment (fusion: chapter 3)"
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help=f"experiment YAML (default: the repository's {DEFAULT_CONFIG}, else built-in defaults)",
    )
    parser.add_argument("--out", type=Path, default=Path("out/fusion_ch3"), help="output directory")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config key, e.g. slam.window.n=20 (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--full",
        action="store_true",
        help="the whole grid (every method and GPS setting, full sequence) instead of the "
        "short default run",
    )
    parser.add_argument("--force", action="store_true", help="recompute even if up to date")
    parser.add_argument(
        "--overwrite", action="store_true", help="write into a folder holding other files"
    )


def run(args: argparse.Namespace) -> int:
    from geoseg.config import default_config_file, load_config
    from slam_bridge.experiments.fusion_ch3 import ExperimentConfig, run_experiment

    source = args.config or default_config_file(DEFAULT_CONFIG.name)
    cfg = load_config(ExperimentConfig, source, overrides=args.overrides)
    if not args.full:
        cfg = cfg.quick()
    out = run_experiment(cfg, args.out, force=args.force, overwrite=args.overwrite)
    print((out / "fusion_ch3.md").read_text())
    print(f"results: {out / 'fusion_ch3.json'}")
    print(f"plots:   {out / 'trajectory.png'}, {out / 'memory.png'}")
    return 0
