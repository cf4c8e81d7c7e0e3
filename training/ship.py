"""Copy a finished ``geoseg train`` run into the package's shipped weights (geoseg/weights/NAME).

Usage::

    python -m training.ship runs/seg seg
    python -m training.ship runs/dirichlet dirichlet
    python -m training.ship --record-digests seg     # refresh the card's SHA-256 of shipped seg
    python -m training.ship runs/street street --user   # into the user weights folder

``--user`` installs into :data:`geoseg.pretrained.USER_WEIGHTS_DIR` instead of the package, for
weights whose training data's terms keep them out of the package (:data:`USER_ONLY`: ``street``,
trained on CamVid, is only ever installed there).

Only :data:`geoseg.pretrained.SHIPPED_FILES` are copied (no optimizer checkpoints); each file is
written to a temporary name and renamed, and the target folder is replaced only once every file
is in place, so an interrupted copy never leaves half a model behind. The model card records the
SHA-256 of every weights file (:data:`WEIGHT_FILES`, key ``"sha256"``), which loading verifies
for files that carry no digest of their own (:mod:`geoseg.integrity`).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

from geoseg.atomic import atomic_write
from geoseg.errors import GeosegError
from geoseg.integrity import CARD_FILE, DIGEST_KEY, file_sha256
from geoseg.pretrained import PRETRAINED, SHIPPED_FILES, USER_ONLY, USER_WEIGHTS_DIR, WEIGHTS_DIR

# What a run must hold to be shipped, per name (networks: the model and its card).
FILTER_REQUIRED = ("dirichlet.json", "max_probability.json", "metrics.json")
REQUIRED = {name: FILTER_REQUIRED for name in PRETRAINED if name.startswith("dirichlet")}
NETWORK_REQUIRED = ("model.pt", "model.onnx", "model_card.json")
# The files whose SHA-256 the shipped card records.
WEIGHT_FILES = ("model.pt", "model.onnx", "dirichlet.json", "max_probability.json")


def record_digests(folder: str | Path) -> dict[str, str]:
    """Write the SHA-256 of ``folder``'s weights files into its ``model_card.json``.

    Returns:
        ``{file name: hex digest}`` as recorded.

    Raises:
        GeosegError: no model card in ``folder``.
    """
    folder = Path(folder)
    card_path = folder / CARD_FILE
    if not card_path.is_file():
        raise GeosegError(f"{folder}: no {CARD_FILE} to record the digests in")
    card = json.loads(card_path.read_text())
    digests = {f: file_sha256(folder / f) for f in WEIGHT_FILES if (folder / f).is_file()}
    card[DIGEST_KEY] = digests
    atomic_write(card_path, json.dumps(card, indent=1, default=str))
    card_path.chmod(0o644)
    return digests


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
        if name in REQUIRED and not (staging / "model_card.json").exists():
            # the filter's card is its metrics (fit data, threshold, figures, wall time)
            shutil.copy2(run_dir / "metrics.json", staging / "model_card.json")
            (staging / "model_card.json").chmod(0o644)
        record_digests(staging)
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
    parser.add_argument(
        "--record-digests",
        metavar="NAME",
        choices=sorted(PRETRAINED),
        help="only refresh the SHA-256 digests in the card of shipped weights NAME",
    )
    parser.add_argument(
        "--user",
        action="store_true",
        help=f"install into the user weights folder ({USER_WEIGHTS_DIR}), not the package",
    )
    parser.add_argument("run_dir", type=Path, nargs="?", help="a finished run directory")
    parser.add_argument("name", nargs="?", choices=sorted(PRETRAINED), help="shipped weights name")
    args = parser.parse_args(argv)
    try:
        if args.record_digests is not None:
            digests = record_digests(WEIGHTS_DIR / args.record_digests)
            sys.stdout.write(f"recorded {', '.join(sorted(digests))} in {args.record_digests}\n")
            return 0
        if args.run_dir is None or args.name is None:
            parser.error("run_dir and name are required")
        if args.name in USER_ONLY and not args.user:
            raise GeosegError(
                f"{args.name}: its training data's terms keep it out of the package; install it "
                "with --user"
            )
        target = ship(
            args.run_dir, args.name, weights_dir=USER_WEIGHTS_DIR if args.user else WEIGHTS_DIR
        )
    except GeosegError as err:
        sys.stderr.write(f"error: {err}\n")
        return 2
    sys.stdout.write(f"shipped {args.run_dir} -> {target}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
