"""Shipped weights: copying a run into the package (training.ship) and opening it back."""

import json
import shutil

import numpy as np
import pytest

from geoseg import pretrained
from geoseg.errors import GeosegError
from geoseg.infer import save_model_checkpoint
from training.ship import ship


@pytest.fixture
def finished_run(tmp_path, exported_model):
    """A run folder with an ENet's checkpoint and its export (shared: see tests/conftest.py)."""
    run = tmp_path / "run"
    model, onnx_path = exported_model("enet")
    assert model.num_classes == 8
    save_model_checkpoint(model, run / "model.pt", model_name="enet", model_config={})
    shutil.copyfile(onnx_path, run / "model.onnx")
    (run / "model_card.json").write_text(json.dumps({"command": "geoseg train seg", "metrics": {}}))
    (run / "last.pt").write_bytes(b"optimizer state: not shipped")
    return run


def test_ship_copies_the_inference_files_only_and_they_load(finished_run, tmp_path, monkeypatch):
    weights = tmp_path / "weights"
    target = ship(finished_run, "seg", weights_dir=weights)
    assert sorted(p.name for p in target.iterdir()) == ["model.onnx", "model.pt", "model_card.json"]
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", weights)
    assert pretrained.model_card("seg")["command"] == "geoseg train seg"
    image = np.random.default_rng(0).integers(0, 256, (40, 56, 3), dtype=np.uint8)
    ort = pretrained.pretrained_segmenter("seg", backend="onnx")(image)
    pt = pretrained.pretrained_segmenter("seg", backend="torch")(image)
    assert ort.labels.shape == (1, 40, 56)
    assert (ort.labels == pt.labels).mean() > 0.999
    # shipping again replaces the folder whole (no stale files, no leftover staging folders)
    (finished_run / "model_card.md").write_text("# card")
    ship(finished_run, "seg", weights_dir=weights)
    assert (target / "model_card.md").is_file()
    assert [p.name for p in weights.iterdir()] == ["seg"]


def test_ship_refuses_an_unfinished_run_and_keeps_the_shipped_one(finished_run, tmp_path):
    weights = tmp_path / "weights"
    ship(finished_run, "seg", weights_dir=weights)
    (finished_run / "model.onnx").unlink()
    with pytest.raises(GeosegError, match="missing model.onnx"):
        ship(finished_run, "seg", weights_dir=weights)
    assert (weights / "seg" / "model.onnx").is_file()
    with pytest.raises(GeosegError, match="expected one of"):
        ship(finished_run, "nonet", weights_dir=weights)


def test_missing_or_unknown_pretrained_weights_say_how_to_get_them(tmp_path, monkeypatch):
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path)
    with pytest.raises(GeosegError, match="geoseg train naive"):
        pretrained.pretrained_dir("naive")
    with pytest.raises(GeosegError, match="unknown name"):
        pretrained.pretrained_dir("resnet")
    with pytest.raises(GeosegError, match="backend"):
        monkeypatch.setattr(pretrained, "pretrained_file", lambda *a: tmp_path)
        pretrained.pretrained_segmenter("seg", backend="tensorrt")
