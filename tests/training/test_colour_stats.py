"""The training set's colour statistics recorded into a model card."""

import json

import cv2
import numpy as np
import pytest

from geoseg.colour_transfer import colour_statistics, statistics_from_card
from geoseg.errors import GeosegError
from training.colour_stats import record_in_card


def test_record_in_card_writes_the_typical_frame_statistics(tmp_path) -> None:
    root = tmp_path / "camvid"
    (root / "train").mkdir(parents=True)
    (root / "trainannot").mkdir()
    frames = []
    for i, value in enumerate((60, 120, 180)):
        rgb = (
            np.random.default_rng(i).integers(value - 40, value + 40, (16, 24, 3)).astype(np.uint8)
        )
        frames.append(rgb)
        cv2.imwrite(str(root / "train" / f"f{i}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "trainannot" / f"f{i}.png"), np.zeros((16, 24), np.uint8))
    run = tmp_path / "run"
    run.mkdir()
    card = {"config": {"data": {"source": "camvid", "root": str(root), "size": [16, 24]}}}
    (run / "model_card.json").write_text(json.dumps(card))
    record_in_card(run, frames=3)
    stats = statistics_from_card(json.loads((run / "model_card.json").read_text()))
    # the median frame is the middle-brightness one
    middle = colour_statistics(frames[1])
    assert stats.mean[0] == pytest.approx(middle.mean[0], abs=1e-4)
    with pytest.raises(GeosegError, match="no model card"):
        record_in_card(tmp_path / "nowhere")
