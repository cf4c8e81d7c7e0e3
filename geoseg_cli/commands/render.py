"""``geoseg render``: render a synthetic sequence and its GIS products to a directory.

Example::

    geoseg render --config configs/world_default.yaml --out out/seq0 --frames 30 \\
        --condition winter --rig tram --size 320x240 --seed 3

The world config is a :class:`geoseg.synth.world.WorldConfig` YAML; ``--set key=value`` overrides
its keys, ``--gis key=value`` those of :class:`geoseg.synth.export.GisConfig` (e.g.
``--gis gps.bias_max_m=5``). The output layout is described in :mod:`geoseg.synth.export` and in
the ``README.txt`` written next to the files.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

logger = logging.getLogger(__name__)

DEFAULT_CONFIG = Path("configs/world_default.yaml")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help=f"world config YAML (default: {DEFAULT_CONFIG} of the working directory, else of "
        "the geoseg source tree, else built-in defaults)",
    )
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--frames", type=int, default=30, help="number of frames (default 30)")
    parser.add_argument("--condition", default="summer_day", help="appearance condition")
    parser.add_argument("--rig", choices=("car", "tram"), default="car", help="camera rig")
    parser.add_argument("--size", default="320x240", help="image size WxH (default 320x240)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the city, route and GIS")
    parser.add_argument("--fps", type=float, default=10.0, help="frame rate (default 10)")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a world config key (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--gis", dest="gis_overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a GIS error-model key, e.g. gps.bias_max_m=5 (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--workers", type=int, default=1,
        help="processes rendering frames side by side (default 1; the files do not change)",
    )  # fmt: skip
    parser.add_argument("--force", action="store_true", help="re-render even if up to date")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="write into an --out folder that holds files no render wrote (they are kept, "
        "unless a file of the same name is rendered)",
    )


def run(args: argparse.Namespace) -> int:
    from geoseg.config import default_config_file, load_config
    from geoseg.errors import GeosegError
    from geoseg.synth.export import GisConfig, check_fps, parse_size, render_sequence
    from geoseg.synth.world import WorldConfig

    size = parse_size(args.size)
    if args.frames < 1:
        raise GeosegError(f"--frames: expected an integer >= 1, got {args.frames}")
    check_fps(args.fps, "--fps")
    source = args.config
    if source is None:
        source = default_config_file(DEFAULT_CONFIG.name)
        if source is None:
            logger.warning("no %s found: using the built-in world defaults", DEFAULT_CONFIG)
    overrides = list(args.overrides) + ([f"seed={args.seed}"] if args.seed is not None else [])
    world_config = load_config(WorldConfig, source, overrides=overrides)
    gis = load_config(GisConfig, None, overrides=args.gis_overrides)
    meta = args.out / "meta.json"
    before = meta.stat().st_mtime_ns if meta.is_file() else None
    out = render_sequence(
        world_config,
        args.out,
        frames=args.frames,
        condition=args.condition,
        rig=args.rig,
        image_size=size,
        fps=args.fps,
        gis=gis,
        overwrite=args.force,
        allow_other_files=args.overwrite,
        workers=args.workers,
    )
    if before is not None and meta.stat().st_mtime_ns == before:
        print(f"{out} already holds this render (same request); nothing redone (--force redoes it)")
    else:
        print(f"rendered {args.frames} frames ({args.rig}, {args.condition}) to {out}")
    print(f"  preview: {out / 'preview.png'}")
    print(f"  map:     {out / 'map.png'}")
    print(f"  layout:  {out / 'README.txt'}")
    return 0
