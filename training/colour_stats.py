"""The training set's colour statistics, recorded in a run's model card (key
``colour_statistics``) for the colour transfer at inference (:mod:`geoseg.colour_transfer`).

Every image trainer records them at the end of its run (:func:`training.common.finish_run`).
For a run made before, or a shipped weights folder::

    python -m training.colour_stats geoseg/weights/seg [--frames 64]

recomputes them from the data section of the card's config (the same frames, before
augmentation) and adds them to ``model_card.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from geoseg.atomic import atomic_write
from geoseg.colour_transfer import CARD_KEY, ColourStatistics, typical_statistics
from geoseg.config import from_dict
from geoseg.errors import GeosegError
from training.config import DataConfig
from training.frame_data import build_frame_dataset

logger = logging.getLogger(__name__)

DEFAULT_FRAMES = 64


def training_colour_statistics(
    data: DataConfig, *, frames: int = DEFAULT_FRAMES
) -> ColourStatistics:
    """``lαβ`` statistics of a typical training frame of ``data`` (per-channel medians over
    ``frames`` evenly spaced frames, :func:`~geoseg.colour_transfer.typical_statistics`).

    Args:
        data: a run's data section (its ``train`` split, without augmentation, at ``data.size``).
        frames: how many frames to look at (the medians settle within a few dozen).

    Returns:
        The :class:`~geoseg.colour_transfer.ColourStatistics` of a typical frame.
    """
    if frames < 1:
        raise GeosegError(f"frames: expected >= 1, got {frames}")
    dataset = build_frame_dataset(data, "train", augment=False, normalize=False)
    picks = np.linspace(0, len(dataset) - 1, min(frames, len(dataset))).round().astype(int)

    def images():
        for i in picks:
            image = dataset[int(i)]["image"]  # (3, H, W) float in [0, 1]
            yield image.permute(1, 2, 0).clamp(0, 1).numpy()

    return typical_statistics(images())


def card_entry(data: DataConfig, *, frames: int = DEFAULT_FRAMES) -> dict[str, dict]:
    """``{"colour_statistics": {...statistics, "frames": frames}}``: what a model card records
    of ``data``'s training frames (:func:`training_colour_statistics`)."""
    stats = training_colour_statistics(data, frames=frames)
    return {CARD_KEY: {**stats.as_dict(), "frames": int(frames)}}


def record_in_card(run_dir: str | Path, *, frames: int = DEFAULT_FRAMES) -> ColourStatistics:
    """Compute the statistics of the run's training data and write them into its model card.

    Raises:
        GeosegError: no ``model_card.json`` in ``run_dir``, or a card without a data config.
    """
    card_path = Path(run_dir) / "model_card.json"
    if not card_path.is_file():
        raise GeosegError(f"{card_path}: no model card")
    card = json.loads(card_path.read_text())
    try:
        data_dict = dict(card["config"]["data"])
    except (KeyError, TypeError):
        raise GeosegError(f"{card_path}: no config.data section to find the training set") from None
    data_dict["cache_dir"] = None  # read-only: render or read the frames, write no cache
    data_dict["prerender_workers"] = 0
    data = from_dict(DataConfig, data_dict, where="data")
    card.update(card_entry(data, frames=frames))
    atomic_write(card_path, json.dumps(card, indent=1, default=str))
    logger.info("%s: %s = %s", card_path, CARD_KEY, card[CARD_KEY])
    return ColourStatistics.from_dict(card[CARD_KEY])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.colour_stats", description=__doc__)
    parser.add_argument("run_dirs", nargs="+", type=Path, help="run or shipped weights folders")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES, help="frames to look at")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for run_dir in args.run_dirs:
        stats = record_in_card(run_dir, frames=args.frames)
        logger.info(
            "%s: mean %s std %s",
            run_dir,
            np.round(stats.mean, 4).tolist(),
            np.round(stats.std, 4).tolist(),
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
