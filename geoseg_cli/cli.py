"""The ``geoseg`` command: one entry point, one subcommand per job.

Each subcommand lives in :mod:`geoseg_cli.commands` as a module exposing
``configure(parser: argparse.ArgumentParser) -> None`` and ``run(args) -> int``. Only the module of
the subcommand being run is imported, so ``geoseg --help`` stays fast (no torch import).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from geoseg import __version__
from geoseg.errors import GeosegError

# name -> (module, one-line help). Order is the order of `geoseg --help`.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("geoseg_cli.commands.demo", "run the end-to-end demonstration on the synthetic world"),
    "render": ("geoseg_cli.commands.render", "render a synthetic sequence and its GIS products"),
    "train": (
        "geoseg_cli.commands.train",
        "train a network (seg, normals, naive, dirichlet, reloc, relpose)",
    ),
    "export": ("geoseg_cli.commands.export", "export a trained network to ONNX"),
    "infer": (
        "geoseg_cli.commands.infer",
        "segment images and predict normals with a trained network",
    ),
    "base": ("geoseg_cli.commands.base", "build an image base from geotagged images (base build)"),
    "localize": (
        "geoseg_cli.commands.localize",
        "relocalise query images against a georeferenced image base",
    ),
    "slam": ("geoseg_cli.commands.slam", "run the SLAM on a folder of images (slam run)"),
    "slam-eval": (
        "geoseg_cli.commands.slam_eval",
        "run a localisation experiment (fusion: the chapter-3 experiment)",
    ),
    "bench": ("geoseg_cli.commands.bench", "run a benchmark script from bench/"),
}

logger = logging.getLogger("geoseg")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The top-level parser; only ``command``'s module is imported to configure its arguments."""
    parser = argparse.ArgumentParser(
        prog="geoseg",
        description="Georeferenced vehicle localisation with deep networks and GIS (Salehi 2018).",
    )
    parser.add_argument("--version", action="version", version=f"geoseg {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        sub_parser = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            _load(module_name).configure(sub_parser)
    return parser


#: exit code after Ctrl-C (the shell's convention: 128 + SIGINT)
EXIT_INTERRUPTED = 130


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    if args.command is None:
        parser.print_help()
        return 0
    module = _load(COMMANDS[args.command][0])
    try:
        return int(module.run(args) or 0)
    except GeosegError as err:
        print(f"geoseg {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        out = getattr(args, "out", None)
        kept = (
            f": {out} keeps what was written before (outputs are written whole or not at "
            "all; a folder without its summary is an unfinished run)"
            if out is not None
            else ""
        )
        print(f"geoseg {args.command}: interrupted{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED


def _load(module_name: str):
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name == module_name:
            raise SystemExit(f"geoseg: this command is not available yet ({module_name})") from None
        raise


if __name__ == "__main__":
    raise SystemExit(main())
