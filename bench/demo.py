"""The demo's figures: what ``geoseg demo`` prints, as the README quotes it.

Runs ``geoseg demo`` with its defaults in a temporary folder (as a user runs it) and writes its
``demo.json`` (the network's score on the demo frames, each SLAM run of the buildings step:
mean translation and rotation error, tracking failures, the GPS fixes' error, the map points
each building rule put on a facade and the share on the right one) with the provenance keys.
``python docs/make_results.py`` writes the README's demo paragraph from this file, and
``tests/test_readme.py`` runs the demo and checks its figures against it.

Split: the demo's own world (``configs/world_default.yaml``'s seed) and drive, a demonstration:
no setting was chosen on it.

Usage: ``python bench/demo.py [--keep DIR]``; writes ``bench/results/demo.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import ROOT, provenance  # noqa: E402

SPLIT = "demo: the demo's world and drive (configs/world_default.yaml), no setting chosen on it"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", type=Path, default=None, help="keep the demo's folder here")
    args = parser.parse_args(argv)
    meta = provenance(SPLIT)
    work = Path(tempfile.mkdtemp(prefix="geoseg_demo_bench_"))
    try:
        # the user's command, from a folder outside the repository (the packaged defaults)
        subprocess.run([sys.executable, "-m", "geoseg_cli", "demo"], cwd=work, check=True)
        figures = json.loads((work / "geoseg_demo" / "demo.json").read_text())
        if args.keep is not None:
            shutil.copytree(work / "geoseg_demo", args.keep, dirs_exist_ok=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    path = ROOT / "bench" / "results" / "demo.json"
    path.write_text(json.dumps({**meta, **figures}, indent=1) + "\n")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
