"""``geoseg train``: train a segmentation-side network, or fit the Dirichlet filter.

Examples::

    geoseg train seg --config configs/seg.yaml
    geoseg train normals --config configs/normals.yaml --set enet_checkpoint=runs/seg
    geoseg train naive --config configs/naive.yaml --device cpu --set epochs=2
    geoseg train dirichlet --config configs/dirichlet.yaml --set naive_checkpoint=runs/naive
    geoseg train reloc --config configs/reloc.yaml --set trunk_checkpoint=runs/seg
    geoseg train relpose --config configs/relpose.yaml --set trunk_checkpoint=runs/seg
    geoseg train seg --config configs/seg.yaml --resume        # continue after a crash
    torchrun --nproc_per_node=2 -m geoseg_cli train seg ...    # data-parallel

The config YAML overrides the trainer's typed defaults (``training.<trainer>``); ``--set
key.sub=value`` overrides it (values parsed as YAML). An unknown key is an error naming it.
``--config`` defaults to ``configs/<trainer>.yaml`` of the working directory, else of the geoseg
source tree (:func:`geoseg.config.default_config_file`); without either, ``--config`` is required
(an empty YAML file selects the built-in defaults), so that a run never silently trains with
other settings than the preset. The config file used is printed.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

TRAINERS: dict[str, str] = {
    "seg": "training.seg",
    "normals": "training.normals",
    "naive": "training.naive",
    "dirichlet": "training.dirichlet_fit",
    "reloc": "training.reloc",
    "relpose": "training.relpose",
}


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("trainer", choices=list(TRAINERS), help="what to train")
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="trainer config YAML (default: configs/<trainer>.yaml of the working directory, "
        "else of the geoseg source tree)",
    )
    parser.add_argument("--resume", action="store_true", help="continue from <out>/last.pt")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="start afresh over an earlier run in --out (its checkpoints and results are "
        "replaced), or write into a folder that holds other files (they are kept)",
    )
    parser.add_argument(
        "--device", default=None, help="auto (CUDA when present), cpu, cuda or cuda:N"
    )
    parser.add_argument("--out", type=Path, default=None, help="run directory (out_dir)")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config key, e.g. --set epochs=2 --set optim.lr=1e-3 (repeatable)",
    )  # fmt: skip


def _command_line(args: argparse.Namespace, config: Path | None) -> str:
    parts = ["geoseg", "train", args.trainer]
    if config is not None:
        parts += ["--config", str(config)]
    if args.resume:
        parts.append("--resume")
    if args.overwrite:
        parts.append("--overwrite")
    if args.device:
        parts += ["--device", args.device]
    if args.out is not None:
        parts += ["--out", str(args.out)]
    for item in args.overrides:
        parts += ["--set", item]
    return " ".join(parts)


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from geoseg.config import default_config_file, load_config
    from geoseg.errors import GeosegError

    module = importlib.import_module(TRAINERS[args.trainer])
    cls = module.CONFIG_CLASS
    fields = {f.name for f in dataclasses.fields(cls)}
    config = args.config
    if config is None:
        config = default_config_file(f"{args.trainer}.yaml")
        if config is None:
            raise GeosegError(
                f"--config: no configs/{args.trainer}.yaml in the working directory nor in the "
                "geoseg source tree; pass --config FILE (an empty file selects the built-in "
                "defaults)"
            )
    print(f"geoseg train {args.trainer}: config {config}")
    overrides = list(args.overrides)
    if args.resume:
        if "resume" not in fields:
            print(
                f"geoseg train {args.trainer}: --resume has no effect (a finished stage is skipped)"
            )
        else:
            overrides.append("resume=true")
    if args.overwrite:
        if "overwrite" not in fields:
            raise GeosegError(f"train {args.trainer}: --overwrite is not an option of this trainer")
        overrides.append("overwrite=true")
    if args.device is not None:
        overrides.append(f"device={args.device}")
    if args.out is not None:
        overrides.append(f"out_dir={args.out}")
    cfg = load_config(cls, config, overrides=overrides)

    from training import distributed as dd

    dd.init_distributed(getattr(cfg, "device", "auto"))
    dd.quiet_non_main_ranks()
    try:
        run_dir = module.main(cfg, command=_command_line(args, config))
        main_process = dd.is_main_process()
    finally:
        dd.cleanup()
    if main_process:
        print(f"geoseg train {args.trainer}: outputs in {run_dir}")
    return 0
