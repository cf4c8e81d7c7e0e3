"""``init_checkpoint``: fine-tuning starts from given weights; another architecture is refused."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from geoseg.config import load_config
from geoseg.errors import ConfigError, GeosegError
from geoseg.infer import load_model_checkpoint, save_model_checkpoint
from geoseg.models.registry import get_model
from training import common
from training import normals as normals_trainer
from training import seg as seg_trainer


def _camvid_folder(root: Path) -> Path:
    rng = np.random.default_rng(0)
    for split in ("train", "val"):
        (root / split).mkdir(parents=True)
        (root / f"{split}annot").mkdir()
        for i in range(2):
            rgb = rng.integers(0, 255, (32, 48, 3), dtype=np.uint8)
            cv2.imwrite(str(root / split / f"f{i}.png"), rgb)
            ids = rng.integers(0, 12, (32, 48)).astype(np.uint8)
            cv2.imwrite(str(root / f"{split}annot" / f"f{i}.png"), ids)
    return root


def _enet_file(path: Path, seed: int, **config) -> Path:
    torch.manual_seed(seed)
    model = get_model("enet", **config)
    return save_model_checkpoint(model, path, model_name="enet", model_config=config)


def _tiny_seg_settings(tmp_path: Path, init: Path, **changes) -> dict:
    """A one-epoch seg run on a tiny CamVid folder made in ``tmp_path``, from ``init``."""
    root = _camvid_folder(tmp_path / "camvid")
    return {
        "epochs": 1,
        "batch_size": 2,
        "device": "cpu",
        "progress": False,
        "export": False,
        "plots": False,
        "class_weight_samples": 2,
        "init_checkpoint": str(init),
        "out_dir": str(tmp_path / "run"),
        "data": {"source": "camvid", "root": str(root), "size": [32, 48]},
        **changes,
    }


def test_seg_fine_tunes_from_init_checkpoint_on_a_camvid_folder(tmp_path):
    init = _enet_file(tmp_path / "init" / "model.pt", seed=123)
    settings = _tiny_seg_settings(
        tmp_path,
        init.parent,  # a run directory works too
        optim={"lr": 1e-12},  # the weights stay (numerically) where they started
    )
    cfg = load_config(seg_trainer.SegConfig, settings)
    run = seg_trainer.main(cfg)
    tuned, _ = load_model_checkpoint(run / "model.pt")
    start, _ = load_model_checkpoint(init)
    torch.manual_seed(cfg.seed)
    fresh = get_model("enet")
    name = "trunk.initial.conv.weight"
    tuned_w, start_w = tuned.state_dict(), start.state_dict()
    key = name if name in tuned_w else next(k for k in tuned_w if k.endswith("weight"))
    assert torch.allclose(tuned_w[key], start_w[key], atol=1e-6)
    assert not torch.allclose(tuned_w[key], fresh.state_dict()[key], atol=1e-3)
    card = json.loads((run / "model_card.json").read_text())
    # CamVid labels 7 classes: no terrain IoU, and the card records the training colours
    assert "val_iou_terrain" not in card["metrics"] and "val_iou_building" in card["metrics"]
    assert len(card["colour_statistics"]["mean"]) == 3


def test_freeze_trains_the_rest_alone_and_keeps_the_frozen_statistics(tmp_path):
    init = _enet_file(tmp_path / "init" / "model.pt", seed=123)
    settings = _tiny_seg_settings(tmp_path, init, freeze=["trunk"], optim={"lr": 1e-2})
    run = seg_trainer.main(load_config(seg_trainer.SegConfig, settings))
    tuned = load_model_checkpoint(run / "model.pt")[0].state_dict()
    start = load_model_checkpoint(init)[0].state_dict()
    trunk = [k for k in start if k.startswith("trunk.")]
    running = [k for k in trunk if k.endswith("running_mean")]
    assert running and all(torch.equal(tuned[k], start[k]) for k in trunk)  # BN stats too
    head = [k for k in start if k.startswith("head.") and start[k].is_floating_point()]
    assert any(not torch.allclose(tuned[k], start[k]) for k in head)

    model = get_model("enet").freeze(["trunk.initial", "head.up4"])
    model.train()
    assert not model.trunk.initial.training and not model.head.up4.training
    assert model.trunk.stage1.training and model.head.stage4.training
    frozen = [n for n, p in model.named_parameters() if not p.requires_grad]
    assert frozen and all(n.startswith(("trunk.initial.", "head.up4.")) for n in frozen)
    assert all(p.requires_grad for p in model.freeze([]).parameters())  # unfrozen again
    with pytest.raises(ConfigError, match=r"freeze: no submodule \['trunk.stage9'\]"):
        model.freeze(["trunk.stage9"])
    with pytest.raises(ConfigError, match="freeze: needs init_checkpoint"):
        load_config(seg_trainer.SegConfig, {**settings, "init_checkpoint": None})
    with pytest.raises(ConfigError, match="freeze: no submodule"):  # before any data is read
        load_config(seg_trainer.SegConfig, {**settings, "freeze": ["trunk.stage9"]})


def test_init_checkpoint_refuses_another_architecture(tmp_path):
    model = get_model("enet")
    five = _enet_file(tmp_path / "five" / "model.pt", seed=0, num_classes=5)
    with pytest.raises(GeosegError, match=r"init_checkpoint: .* does not fit .*shape: "):
        common.load_init_weights(model, five, model_name="enet")
    naive = get_model("naive_cnn")
    save_model_checkpoint(naive, tmp_path / "naive.pt", model_name="naive_cnn")
    with pytest.raises(GeosegError, match="init_checkpoint: .*holds a 'naive_cnn' model"):
        common.load_init_weights(model, tmp_path / "naive.pt", model_name="enet")
    with pytest.raises(GeosegError, match="init_checkpoint: .*no such checkpoint"):
        common.load_init_weights(model, tmp_path / "missing.pt", model_name="enet")


def test_init_checkpoint_takes_a_shipped_name(monkeypatch, tmp_path):
    from geoseg.pretrained import pretrained_file

    monkeypatch.chdir(tmp_path)  # no folder "seg" here: the name means the shipped weights
    model = get_model("enet")
    assert common.load_init_weights(model, "seg", model_name="enet") == pretrained_file("seg")
    shipped, _ = load_model_checkpoint(pretrained_file("seg"))
    key = next(iter(shipped.state_dict()))
    assert torch.equal(model.state_dict()[key], shipped.state_dict()[key])


def test_trainers_without_init_checkpoint_refuse_the_key():
    with pytest.raises(ConfigError, match="init_checkpoint: the normals trainer does not take it"):
        load_config(normals_trainer.NormalsConfig, {"init_checkpoint": "runs/seg"})
