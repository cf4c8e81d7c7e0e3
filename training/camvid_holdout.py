"""A CamVid-layout folder whose training split leaves out whole sequences, held out for selection.

Model selection (the epoch kept, the recipe chosen) must not look at the split that reports the
figures. CamVid's frames are named ``<sequence>_<frame>``; this stage links (symbolic links, no
copy) the frames of ``root/train`` into a new folder::

    <out>/train/, <out>/trainannot/      frames of the sequences not held out
    <out>/select/, <out>/selectannot/    frames of the held-out sequences (selection)
    <out>/val/, <out>/valannot/          root's val split, unchanged (reported only)

so that a trainer reads ``data.root=<out>``, ``data.train_split=train``,
``data.val_split=select`` (``configs/street.yaml``). Skips work whose outputs exist.

Usage::

    python -m training.camvid_holdout /path/to/camvid runs/camvid_holdout --hold 0001TP
"""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Sequence
from pathlib import Path

from geoseg.data.camvid import IMAGE_SUFFIXES, LABEL_DIR_SUFFIX
from geoseg.errors import GeosegError

logger = logging.getLogger(__name__)

DEFAULT_HELD_OUT: tuple[str, ...] = ("0001TP",)
"""CamVid train's smallest sequence (62 frames, a drive at dusk): the selection part."""


def sequence_of(name: str) -> str:
    """``"0001TP_006690"`` -> ``"0001TP"`` (the part before the first underscore)."""
    return name.split("_", 1)[0]


def _link(src: Path, dst: Path) -> None:
    if dst.is_symlink() or dst.exists():
        return
    os.symlink(src.resolve(), dst)


def make_holdout(
    root: str | Path,
    out: str | Path,
    *,
    held_out: Sequence[str] = DEFAULT_HELD_OUT,
    train_split: str = "train",
    val_split: str = "val",
) -> Path:
    """Link ``root``'s frames into ``out`` with ``held_out`` sequences moved to ``select``.

    Args:
        root: a CamVid-layout folder (``<split>/`` and ``<split>annot/``).
        out: the folder to fill (created).
        held_out: sequence names (file-name prefixes) moved from ``train_split`` to ``select``.
        train_split, val_split: root's split names.

    Returns:
        ``out``.

    Raises:
        GeosegError: a missing split folder, a held-out sequence with no frame, or nothing left
            to train on.
    """
    root, out = Path(root), Path(out)
    for split in (train_split, val_split):
        for folder in (root / split, root / f"{split}{LABEL_DIR_SUFFIX}"):
            if not folder.is_dir():
                raise GeosegError(f"CamVid layout: expected folder {folder}")
    images = sorted(p for p in (root / train_split).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    held = set(held_out)
    found = {sequence_of(p.stem) for p in images}
    missing = sorted(held - found)
    if missing:
        raise GeosegError(
            f"held_out: no frame of sequence(s) {missing} in {root / train_split}; "
            f"sequences there: {sorted(found)}"
        )
    if not found - held:
        raise GeosegError(f"held_out: {sorted(held)} leaves no training sequence")
    for split in ("train", "select", "val"):
        (out / split).mkdir(parents=True, exist_ok=True)
        (out / f"{split}{LABEL_DIR_SUFFIX}").mkdir(parents=True, exist_ok=True)
    counts = {"train": 0, "select": 0}
    for image in images:
        split = "select" if sequence_of(image.stem) in held else "train"
        label = root / f"{train_split}{LABEL_DIR_SUFFIX}" / f"{image.stem}.png"
        _link(image, out / split / image.name)
        _link(label, out / f"{split}{LABEL_DIR_SUFFIX}" / label.name)
        counts[split] += 1
    for image in sorted((root / val_split).iterdir()):
        if image.suffix.lower() in IMAGE_SUFFIXES:
            label = root / f"{val_split}{LABEL_DIR_SUFFIX}" / f"{image.stem}.png"
            _link(image, out / "val" / image.name)
            _link(label, out / f"val{LABEL_DIR_SUFFIX}" / label.name)
    logger.info(
        "%s: %d training frames, %d held out for selection (%s)",
        out,
        counts["train"],
        counts["select"],
        ", ".join(sorted(held)),
    )
    return out


def main(argv: Sequence[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", help="a CamVid-layout folder")
    parser.add_argument("out", help="the folder to fill with links")
    parser.add_argument("--hold", nargs="+", default=list(DEFAULT_HELD_OUT))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    return make_holdout(args.root, args.out, held_out=args.hold)


if __name__ == "__main__":
    main()
