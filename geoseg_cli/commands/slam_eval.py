"""``geoseg slam-eval``: localisation experiments on the synthetic world.

Examples::

    geoseg slam-eval fusion --out out/fusion_ch3            # chapter 3, short run
    geoseg slam-eval fusion --full                          # chapter 3, the whole grid
    geoseg slam-eval buildings --out out/buildings_ch4      # chapter 4, short drive
    geoseg slam-eval buildings --full --data data/ch4_drive # chapter 4, the 1.2 km drive

``fusion`` (thesis §3.7) runs :func:`slam_bridge.experiments.fusion_ch3.run_experiment`
(``configs/slam_ch3.yaml``): the GPS fusion of the hybrid windows against the plain k-BA. It
writes ``fusion_ch3.md`` (Tables 3.1-3.3 beside the thesis's figures), ``fusion_ch3.json``,
``trajectory.png`` and ``memory.png`` (fig. 3.7).

``buildings`` (thesis chapter 4) runs :func:`slam_bridge.experiments.buildings_ch4.
run_experiment` (``configs/buildings_ch4.yaml``): the image SLAM on a rendered drive with
building constraints chosen by the ray-cast baseline, the naive CNN + Dirichlet filter, the
joint network + eq. 4.14 and the oracle, against the exact and the GIS building models. It
writes ``buildings_ch4.md``, ``buildings_ch4.json``, ``runs/`` and the pictures.

``run`` measures a run's keyframes (``--run``, a ``geoseg slam run`` folder) against a
reference trajectory (``--reference``): a drive's true poses (``poses.csv``) or, on a drive
without truth, a refined run (``geoseg slam refine``: one bundle adjustment over the whole run
constrained to the building model and the DEM, the thesis's pseudo ground truth, §3.7)::

    geoseg slam refine out/run --buildings gis/facades.csv --dem gis/dem.csv --gps gps.csv
    geoseg slam-eval run --run out/run --reference out/run_refined

It prints the errors (:func:`slam_bridge.system.reference.compare_trajectories`) and, with
``--out``, writes them to ``OUT/reference_eval.json``.

Without ``--full`` each runs the short version of its config (``quick_*`` keys); with it the
whole experiment. A folder already holding the results of the same config is not recomputed
(``--force`` recomputes).
"""

from __future__ import annotations

import argparse
from pathlib import Path

#: experiment -> (default config file, default output folder, results file)
EXPERIMENTS = {
    "fusion": ("slam_ch3.yaml", "out/fusion_ch3", "fusion_ch3"),
    "buildings": ("buildings_ch4.yaml", "out/buildings_ch4", "buildings_ch4"),
}


def configure(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Localisation experiments on the synthetic world. fusion: the chapter-3 experiment "
        "(thesis section 3.7; configs/slam_ch3.yaml): plain keyframe bundle adjustment against "
        "the hybrid BA / pose-graph windows (DPC, MPC), fused with GPS by the barrier term; "
        "short run by default (160 m, GPS sigma_b 0.75 m and the biased GPS), --full the whole "
        "grid. buildings: the chapter-4 experiment (configs/buildings_ch4.yaml): the image SLAM "
        "with building constraints chosen by the ray-cast baseline, the naive CNN + Dirichlet "
        "filter, the joint network + eq. 4.14 and an oracle, against the exact and a GIS "
        "building model; a 250 m drive by default, --full the 1.2 km drive."
    )
    parser.add_argument(
        "experiment", choices=sorted([*EXPERIMENTS, "run"]),
        help="fusion: chapter 3 (GPS fusion, hybrid windows); buildings: chapter 4 (networks "
        "choose building constraints); run: a run's keyframes against a reference (--run, "
        "--reference)",
    )  # fmt: skip
    parser.add_argument(
        "--run", type=Path, default=None,
        help="run: the `geoseg slam run` folder whose keyframes are measured",
    )  # fmt: skip
    parser.add_argument(
        "--reference", type=Path, default=None,
        help="run: the reference trajectory: a refined run folder (`geoseg slam refine`, the "
        "pseudo ground truth of a drive without truth) or a poses.csv of true poses",
    )  # fmt: skip
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="experiment YAML (default: the repository's configs/slam_ch3.yaml or "
        "configs/buildings_ch4.yaml, else built-in defaults)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="output directory (default: out/<experiment>)"
    )
    parser.add_argument(
        "--data", type=Path, default=None,
        help="buildings: where the drive is rendered (default: OUT/drive); reused when it "
        "holds the same rendering",
    )  # fmt: skip
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config key, e.g. slam.window.n=20 (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--full", action="store_true",
        help="the whole experiment (fusion: every method and GPS setting on the full sequence; "
        "buildings: the 1.2 km drive) instead of the short default run",
    )  # fmt: skip
    parser.add_argument("--force", action="store_true", help="recompute even if up to date")
    parser.add_argument(
        "--overwrite", action="store_true", help="write into a folder holding other files"
    )


def run(args: argparse.Namespace) -> int:
    from geoseg.config import default_config_file, load_config
    from geoseg.errors import GeosegError

    if args.experiment == "run":
        return _against_reference(args)
    if args.run is not None or args.reference is not None:
        raise GeosegError("--run, --reference: only the run experiment takes them")
    config_name, default_out, results = EXPERIMENTS[args.experiment]
    if args.data is not None and args.experiment != "buildings":
        raise GeosegError("--data: only the buildings experiment renders a drive")
    out_dir = args.out or Path(default_out)
    source = args.config or default_config_file(config_name)
    if args.experiment == "fusion":
        from slam_bridge.experiments.fusion_ch3 import ExperimentConfig, run_experiment

        cfg = load_config(ExperimentConfig, source, overrides=args.overrides)
        cfg = cfg if args.full else cfg.quick()
        out = run_experiment(cfg, out_dir, force=args.force, overwrite=args.overwrite)
        plots = [out / "trajectory.png", out / "memory.png"]
    else:
        from slam_bridge.experiments.buildings_ch4 import BuildingsConfig, run_experiment

        cfg = load_config(BuildingsConfig, source, overrides=args.overrides)
        cfg = cfg if args.full else cfg.quick()
        out = run_experiment(
            cfg, out_dir, data_dir=args.data, force=args.force, overwrite=args.overwrite
        )
        plots = sorted(out.glob("*.png"))
    print((out / f"{results}.md").read_text())
    print(f"results: {out / f'{results}.json'}")
    print("plots:   " + ", ".join(str(p) for p in plots))
    return 0


def _against_reference(args: argparse.Namespace) -> int:
    """``slam-eval run``: the run's keyframes against the reference (module docstring)."""
    import json

    from geoseg.atomic import atomic_write
    from geoseg.errors import GeosegError
    from slam_bridge.system.reference import compare_trajectories, read_trajectory

    if args.run is None or args.reference is None:
        raise GeosegError("slam-eval run: needs --run RUN_DIR and --reference REFERENCE")
    for name in ("config", "data"):
        if getattr(args, name) is not None:
            raise GeosegError(f"--{name}: the run experiment takes none")
    if args.full or args.overrides:
        raise GeosegError("--full, --set: the run experiment takes none")
    figures = compare_trajectories(read_trajectory(args.run), read_trajectory(args.reference))
    figures.update(run=str(args.run), reference=str(args.reference))
    print(
        f"{args.run} against {args.reference}: {figures['matched']} keyframes, "
        f"{figures['translation_error_m']:.3f} m horizontal (max "
        f"{figures['translation_error_max_m']:.3f} m), {figures['translation_error_3d_m']:.3f} m "
        f"3D, {figures['rotation_error_deg']:.3f} deg"
    )
    if figures["unmatched"]:
        print(f"  {figures['unmatched']} keyframe(s) without a reference pose at their time")
    if args.out is not None:
        from geoseg.output_dir import ensure_writable_dir

        out = ensure_writable_dir(args.out)
        path = atomic_write(out / "reference_eval.json", json.dumps(figures, indent=1) + "\n")
        print(f"results: {path}")
    return 0
