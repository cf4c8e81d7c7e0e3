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


def test_user_installed_weights_are_found_by_name(finished_run, tmp_path, monkeypatch):
    """``street`` (CamVid-trained) lives in the user weights folder, never in the package; the
    real-photo default falls back to the shipped normals_real until it is installed."""
    user = tmp_path / "user"
    monkeypatch.setattr(pretrained, "USER_WEIGHTS_DIR", user)
    assert "street" in pretrained.USER_ONLY and not (pretrained.WEIGHTS_DIR / "street").exists()
    assert pretrained.real_photo_network() == "normals_real"
    with pytest.raises(GeosegError, match="--user"):
        pretrained.pretrained_dir("street")
    ship(finished_run, "street", weights_dir=user)
    assert pretrained.pretrained_dir("street") == user / "street"
    assert pretrained.real_photo_network() == "street"
    assert pretrained.path_or_shipped("street", "model.onnx") == user / "street" / "model.onnx"


def test_ship_keeps_user_only_weights_out_of_the_package(finished_run, tmp_path, monkeypatch):
    from training import ship as ship_module

    monkeypatch.setattr(ship_module, "USER_WEIGHTS_DIR", tmp_path / "user")
    assert ship_module.main([str(finished_run), "street"]) == 2
    assert ship_module.main(["--user", str(finished_run), "street"]) == 0
    assert (tmp_path / "user" / "street" / "model.onnx").is_file()
