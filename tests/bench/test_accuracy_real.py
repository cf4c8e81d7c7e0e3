"""bench/accuracy_real.py on a CamVid-layout folder made here: ``--split train`` measures a
model on the train frames and writes beside, never over, the val figures."""

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from geoseg.pretrained import pretrained_file

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("accuracy_real", ROOT / "bench/accuracy_real.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _camvid(root: Path, split: str, n: int) -> None:
    """``n`` 48x64 grey frames of ``split``: road ids in the bottom half, building above."""
    (root / split).mkdir(parents=True)
    (root / f"{split}annot").mkdir()
    for i in range(n):
        rgb = np.full((48, 64, 3), 90 + 10 * i, np.uint8)
        ids = np.ones((48, 64), np.uint8)  # CamVid 1: building
        ids[24:] = 3  # CamVid 3: road
        cv2.imwrite(str(root / split / f"f_{i:02d}.png"), rgb)
        cv2.imwrite(str(root / f"{split}annot" / f"f_{i:02d}.png"), ids)


def test_split_train_measures_the_train_frames_apart_from_val(bench, tmp_path):
    camvid = tmp_path / "camvid"
    _camvid(camvid, "train", n=3)
    _camvid(camvid, "val", n=1)
    out = tmp_path / "out"
    model = pretrained_file("seg", "model.onnx")
    common = ["--camvid", str(camvid), "--model", str(model), "--tag", "t", "--out", str(out)]
    assert bench.main([*common, "--split", "train"]) == 0
    train = json.loads((out / "accuracy_real_t_train.json").read_text())
    assert train["split"] == "train" and train["frames"] == 3
    assert not (out / "accuracy_real_t.json").exists()
    assert (out / "accuracy_real_t_train_panel.png").is_file()
    assert bench.main(common) == 0
    val = json.loads((out / "accuracy_real_t.json").read_text())
    assert val["split"] == "val" and val["frames"] == 1
    assert json.loads((out / "accuracy_real_t_train.json").read_text()) == train  # kept


def test_split_train_needs_a_model(bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--camvid", str(tmp_path), "--split", "train"])
    assert exit_info.value.code == 2
    assert "--split train: only with --model" in capsys.readouterr().err
