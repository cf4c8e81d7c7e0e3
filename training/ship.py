"""Copy a finished ``geoseg train`` run into the package's shipped weights (geoseg/weights/NAME).

Usage::

    python -m training.ship runs/seg seg
    python -m training.ship runs/dirichlet dirichlet

Only :data:`geoseg.pretrained.SHIPPED_FILES` are copied (no optimizer checkpoints); each file is
written to a temporary name and renamed, and the target folder is replaced only once every file
is in place, so an interrupted copy never leaves half a model behind.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

from geoseg.errors import GeosegError
from geoseg.pretrained import PRETRAINED, SHIPPED_FILES, WEIGHTS_DIR

# What a run must hold to be shipped, per name (networks: the model and its card).
REQUIRED = {"dirichlet": ("dirichlet.json", "max_probability.json", "metrics.json")}
NETWORK_REQUIRED = ("model.pt", "model.onnx", "model_card.json")


def ship(run_dir: str | Path, name: str, *, weights_dir: Path = WEIGHTS_DIR) -> Path:
    """Copy ``run_dir``'s shipped files to ``weights_dir / name``; returns that folder.

    Raises:
        GeosegError: unknown name, missing run directory, or a run that is not finished.
    """
    run_dir = Path(run_dir)
    if name not in PRETRAINED:
        raise GeosegError(f"name: expected one of {sorted(PRETRAINED)}, got {name!r}")
    if not run_dir.is_dir():
        raise GeosegError(f"{run_dir}: no such run directory")
    missing = [f for f in REQUIRED.get(name, NETWORK_REQUIRED) if not (run_dir / f).is_file()]
    if missing:
        raise GeosegError(f"{run_dir}: not a finished {name} run (missing {', '.join(missing)})")
    weights_dir.mkdir(parents=True, exist_ok=True)
    target = weights_dir / name
    staging = Path(tempfile.mkdtemp(prefix=f".{name}-", dir=weights_dir))
    try:
        for file in SHIPPED_FILES:
            if (run_dir / file).is_file():
                shutil.copy2(run_dir / file, staging / file)
                (staging / file).chmod(0o644)  # package files: readable whatever the run umask
        if name == "dirichlet" and not (staging / "model_card.json").exists():
            # the filter's card is its metrics (fit data, threshold, figures, wall time)
            shutil.copy2(run_dir / "metrics.json", staging / "model_card.json")
            (staging / "model_card.json").chmod(0o644)
        staging.chmod(0o755)  # mkdtemp makes it 0700
        old = None
        if target.exists():
            old = target.rename(weights_dir / f".{name}-old")
        staging.rename(target)
        if old is not None:
            shutil.rmtree(old)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a finished run directory")
    parser.add_argument("name", choices=sorted(PRETRAINED), help="shipped weights name")
    args = parser.parse_args(argv)
    try:
        target = ship(args.run_dir, args.name)
    except GeosegError as err:
        sys.stderr.write(f"error: {err}\n")
        return 2
    sys.stdout.write(f"shipped {args.run_dir} -> {target}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
