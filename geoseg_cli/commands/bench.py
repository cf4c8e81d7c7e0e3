"""``geoseg bench NAME [ARGS...]``: run a benchmark script from the repository's ``bench/`` folder.

Benchmarks live beside the package (they are not installed); this command finds them from a
source checkout (the README's editable install) and runs ``bench/NAME.py`` with the given
arguments, so ``geoseg bench render_speed`` equals ``python bench/render_speed.py``.
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

import geoseg
from geoseg.errors import GeosegError

BENCH_DIR = Path(geoseg.__file__).resolve().parent.parent / "bench"


def available() -> list[str]:
    """Names of the benchmark scripts found in ``bench/``."""
    if not BENCH_DIR.is_dir():
        return []
    return sorted(p.stem for p in BENCH_DIR.glob("*.py") if not p.name.startswith("_"))


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", nargs="?", help="benchmark name (omit to list them)")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="arguments for the script")


def run(args: argparse.Namespace) -> int:
    names = available()
    if not names:
        raise GeosegError(f"no benchmark scripts found in {BENCH_DIR} (run from a source checkout)")
    if args.name is None:
        print("benchmarks: " + ", ".join(names))
        return 0
    if args.name not in names:
        raise GeosegError(f"unknown benchmark {args.name!r}; available: {', '.join(names)}")
    script = BENCH_DIR / f"{args.name}.py"
    sys.argv = [str(script), *args.args]
    runpy.run_path(str(script), run_name="__main__")
    return 0
