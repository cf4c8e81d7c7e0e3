"""bench/accuracy_real_street.py's parts on folders made here: colour and grey figures of a
CamVid-layout split, and the bridge's network on single-channel KITTI-layout frames."""

import importlib.util
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from geoseg.export import export_onnx
from geoseg.infer import save_model_checkpoint
from geoseg.models import get_model

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(ROOT / "bench"))
    spec = importlib.util.spec_from_file_location("ars", ROOT / "bench/accuracy_real_street.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def joint(tmp_path_factory):
    root = tmp_path_factory.mktemp("street")
    torch.manual_seed(0)
    model = get_model("joint", num_classes=8).eval()
    save_model_checkpoint(model, root / "model.pt", model_name="joint")
    export_onnx(model, root / "model.onnx", metadata={"model_name": "joint"})
    return root


def test_to_grey_is_bt601_luma(bench):
    image = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]]], np.uint8)
    np.testing.assert_array_equal(bench.to_grey(image), [[76, 150, 29, 18]])


def test_label_figures_colour_and_grey(bench, joint, tmp_path):
    from accuracy_real import load_segmenter

    (tmp_path / "val").mkdir()
    (tmp_path / "valannot").mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):
        cv2.imwrite(
            str(tmp_path / "val" / f"a_{i}.png"), rng.integers(0, 256, (36, 48, 3), np.uint8)
        )
        cv2.imwrite(str(tmp_path / "valannot" / f"a_{i}.png"), np.full((36, 48), 1, np.uint8))
    figures = bench.label_figures(load_segmenter(joint), tmp_path, "val", 0)
    assert figures["frames"] == 2
    for suffix in ("", "_320x240"):
        assert 0.0 <= figures[f"grayscale_miou{suffix}"] <= 1.0
        assert figures[f"grayscale_miou_ratio{suffix}"] == pytest.approx(
            figures[f"grayscale_miou{suffix}"] / figures[f"miou{suffix}"]
        )


def test_kitti_frames_run_through_the_bridges_network(bench, joint, tmp_path):
    clip = tmp_path / "clips" / "drive" / "image_0"
    clip.mkdir(parents=True)
    rng = np.random.default_rng(1)
    for i in range(2):
        cv2.imwrite(str(clip / f"{i:06d}.jpg"), rng.integers(0, 256, (74, 245), np.uint8))
    panel = tmp_path / "panel.png"
    figures = bench.kitti_figures(panel, joint / "model.onnx", tmp_path / "clips")
    assert figures["kitti_frames_drive"] == len(bench.KITTI_FRAMES)
    shares = [v for k, v in figures.items() if k.startswith("kitti_share_")]
    assert len(shares) == 8 and sum(shares) == pytest.approx(1.0)
    assert cv2.imread(str(panel)).shape[1] == 3 * 640
