"""The four segmentation-side trainers on tiny configs: end to end, one step, resume, freezing,
the Dirichlet stage and the ``geoseg train`` command's errors."""

import json
from pathlib import Path

import onnx
import pytest
import torch

from geoseg.classes import BUILDING
from geoseg.config import load_config
from geoseg.data.synthetic import synthetic_config
from geoseg.errors import ConfigError, GeosegError
from geoseg.models.registry import get_model
from geoseg_cli.cli import main as cli_main
from training import common, frame_data
from training import dirichlet_fit as dirichlet_trainer
from training import naive as naive_trainer
from training import normals as normals_trainer
from training import seg as seg_trainer
from training.checkpoint import load_checkpoint
from training.losses import NormalsLoss, PatchNLL, WeightedCrossEntropy

TINY_SEG = Path(__file__).parent / "configs" / "tiny_seg.yaml"


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("synth_cache")


def _data(cache: Path) -> dict:
    return {
        "size": [48, 64],
        "cache_dir": str(cache),
        "synth": {"seeds": [1], "frames": 4, "val": {"frames": 4}},
    }


def _base(cache: Path, out: Path, **kw) -> dict:
    base = {"epochs": 1, "batch_size": 2, "device": "cpu", "progress": False, "out_dir": str(out)}
    base["data"] = _data(cache)
    base.update(kw)
    return base


def _check_run(run_dir: Path, run_files: tuple[str, ...]) -> dict:
    for name in (*run_files, "loss.png"):  # these runs plot
        assert (run_dir / name).is_file(), name
    onnx.checker.check_model(str(run_dir / "model.onnx"))
    card = json.loads((run_dir / "model_card.json").read_text())
    assert card["metrics"] and card["data"]["source"] == "synth" and card["command"]
    assert card["epochs"] == 1 and "config" in card
    return card


def test_prerender_frames_fills_the_cache_before_training(tmp_path):
    cfg = load_config(
        seg_trainer.SegConfig,
        _base(tmp_path / "cache", tmp_path / "run") | {"model": "enet"},
        overrides=["data.prerender_workers=1", "data.synth.val.seeds=[2]"],
    )
    train = frame_data.build_frame_dataset(cfg.data, "train")
    val = frame_data.build_frame_dataset(cfg.data, "val")
    common.prerender_frames(cfg.data, train, val)
    assert len(list((tmp_path / "cache").rglob("*.npz"))) == len(train) + len(val)
    # without prerender_workers nothing is rendered up front
    cfg.data.prerender_workers = 0
    cfg.data.cache_dir = tmp_path / "cold"
    common.prerender_frames(cfg.data, frame_data.build_frame_dataset(cfg.data, "train"))
    assert not (tmp_path / "cold").exists()


def test_negative_prerender_workers_is_a_config_error():
    with pytest.raises(ConfigError, match="prerender_workers"):
        load_config(seg_trainer.SegConfig, None, overrides=["data.prerender_workers=-1"])


@pytest.fixture(scope="module")
def seg_run(tmp_path_factory, cache_dir) -> Path:
    out = tmp_path_factory.mktemp("seg") / "run"
    cfg = load_config(seg_trainer.SegConfig, TINY_SEG, overrides=[f"out_dir={out}"])
    cfg.data.cache_dir = cache_dir
    return seg_trainer.main(cfg, command="pytest seg")


@pytest.fixture(scope="module")
def naive_run(tmp_path_factory, cache_dir) -> Path:
    out = tmp_path_factory.mktemp("naive") / "run"
    cfg = load_config(
        naive_trainer.NaiveConfig,
        _base(
            cache_dir,
            out,
            batch_size=16,
            patches_per_frame=8,
            val_patches_per_frame=4,
            dense_eval_frames=2,
        ),
    )
    return naive_trainer.main(cfg)


def test_naive_frame_augment_changes_the_frames_not_the_labels(cache_dir, tmp_path):
    """frame_augment puts each training frame through the colour jitter and camera effects
    before its patches are cut (geometry off here: the labels must stay the rendered ones)."""
    augment = {"hflip": 0.0, "brightness": 0.5, "contrast": 0.5, "camera": {"p_noise": 1.0}}
    frames = {}
    for on in (False, True):
        base = _base(cache_dir, tmp_path / "run", frame_augment=on)
        base["data"]["augment"] = augment
        cfg = load_config(naive_trainer.NaiveConfig, base)
        frames[on] = naive_trainer.patch_datasets(cfg)[0].frames[0]
    assert not torch.allclose(frames[True]["image"], frames[False]["image"], atol=1e-3)
    assert torch.equal(
        torch.as_tensor(frames[True]["labels"]), torch.as_tensor(frames[False]["labels"])
    )


# ----------------------------------------------------------------------------- end to end
@pytest.mark.slow  # a whole run with its ONNX export
def test_seg_main_writes_a_complete_run(seg_run, run_files):
    card = _check_run(seg_run, run_files)
    assert "val_miou" in card["metrics"] and len(card["class_weights"]) == 8
    ckpt = load_checkpoint(seg_run / "last.pt")
    assert ckpt["model_name"] == "enet" and len(ckpt["extra"]["class_weights"]) == 8
    from geoseg.infer import Segmenter

    result = Segmenter.from_file(seg_run / "model.pt")(
        torch.zeros(48, 64, 3, dtype=torch.uint8).numpy()
    )
    assert result.labels.shape == (1, 48, 64)


def test_seg_resume_is_passed_through(seg_run, cache_dir, tmp_path):
    out = tmp_path / "resumed"
    import shutil

    shutil.copytree(seg_run, out)
    with pytest.raises(GeosegError, match="resume"):
        seg_trainer.main(load_config(seg_trainer.SegConfig, TINY_SEG, overrides=[f"out_dir={out}"]))
    cfg = load_config(
        seg_trainer.SegConfig,
        TINY_SEG,
        overrides=[f"out_dir={out}", "epochs=2", "resume=true", "export=false"],
    )
    cfg.data.cache_dir = cache_dir
    seg_trainer.main(cfg)
    ckpt = load_checkpoint(out / "last.pt")
    assert ckpt["epoch"] == 2 and [r["epoch"] for r in ckpt["history"]] == [1, 2]


def test_seg_encoder_first_schedule(cache_dir, tmp_path):
    cfg = load_config(
        seg_trainer.SegConfig,
        TINY_SEG,
        overrides=[f"out_dir={tmp_path / 'run'}", "encoder_epochs=1", "export=false"],
    )
    cfg.data.cache_dir = cache_dir
    run = seg_trainer.main(cfg)
    enc = load_checkpoint(run / "encoder" / "last.pt")
    assert enc["model_name"] == "enet_encoder" and enc["epoch"] == 1
    # stage 2 started from the encoder's trunk (the checkpoint after one more epoch differs,
    # but its initial trunk was the encoder's: check the first stage's stored weights exist)
    assert any(k.startswith("trunk.") for k in enc["model"])
    assert load_checkpoint(run / "last.pt")["model_name"] == "enet"


@pytest.mark.slow  # a whole run with its ONNX export
def test_normals_main_keeps_trunk_and_label_head(seg_run, cache_dir, tmp_path, run_files):
    cfg = load_config(
        normals_trainer.NormalsConfig,
        _base(cache_dir, tmp_path / "run", enet_checkpoint=str(seg_run)),
    )
    run = normals_trainer.main(cfg)
    card = _check_run(run, run_files)
    for key in ("val_building_angle_median", "val_building_within_11_25", "val_angle_mean"):
        assert key in card["metrics"]
    enet_state = torch.load(seg_run / "model.pt", weights_only=True)["state_dict"]
    joint_state = torch.load(run / "model.pt", weights_only=True)["state_dict"]
    for key, value in enet_state.items():
        jkey = key if key.startswith("trunk.") else "label_head." + key[len("head.") :]
        assert torch.equal(joint_state[jkey], value), key  # frozen, BN statistics included
    normal_keys = [k for k in joint_state if k.startswith("normal_head.") and "weight" in k]
    fresh = get_model("joint").state_dict()
    assert any(not torch.equal(joint_state[k], fresh[k]) for k in normal_keys)


def test_normals_refuses_another_architecture(naive_run, cache_dir, tmp_path):
    cfg = load_config(
        normals_trainer.NormalsConfig,
        _base(cache_dir, tmp_path / "run", enet_checkpoint=str(naive_run)),
    )
    with pytest.raises(GeosegError, match="naive_cnn.*expected 'enet'"):
        normals_trainer.main(cfg)
    cfg.enet_checkpoint = None
    with pytest.raises(GeosegError, match="enet_checkpoint"):
        normals_trainer.main(cfg)


def test_naive_main_writes_a_complete_run(naive_run, run_files):
    card = _check_run(naive_run, run_files)
    assert "dense_miou" in card["metrics"] and "dense_iou_building" in card["metrics"]


@pytest.mark.parametrize("window", [1, 3])
def test_dirichlet_fits_and_writes_the_filter(naive_run, cache_dir, tmp_path, window, monkeypatch):
    from geoseg.dirichlet import DirichletFilter, load_filter

    cfg = load_config(
        dirichlet_trainer.DirichletConfig,
        {
            "naive_checkpoint": str(naive_run),
            "out_dir": str(tmp_path / "dir"),
            "device": "cpu",
            "progress": False,
            "fit_frames": 2,
            "calib_frames": 2,
            "eval_frames": 2,
            "eps": 1e-6,
            "window": window,
            "data": _data(cache_dir),
        },
    )
    out = dirichlet_trainer.main(cfg)
    filt = load_filter(out / "dirichlet.json")
    assert isinstance(filt, DirichletFilter) and filt.threshold is not None
    assert filt.eps == 1e-6  # the configured floor is part of the saved filter
    assert filt.window == window == load_filter(out / "max_probability.json").window
    assert (filt.alpha > 0).all()
    metrics = json.loads((out / "metrics.json").read_text())
    for key in (
        "dirichlet_fp_removed",
        "dirichlet_extra_false_rejections",
        "maxprob_fp_removed_same_rejections",
        "winner",
        "fit_seconds",
    ):
        assert key in metrics
    assert metrics["n_fit_pixels"] > 100
    mtime = (out / "metrics.json").stat().st_mtime_ns
    dirichlet_trainer.main(cfg)  # finished: skipped
    assert (out / "metrics.json").stat().st_mtime_ns == mtime
    # a network that calls no pixel building: fitting on the accepted ones must say so
    real = dirichlet_trainer.dense_probabilities

    def never_building(*args, **kwargs):
        for probs, labels in real(*args, **kwargs):
            probs = probs.copy()
            probs[..., 0] += probs[..., BUILDING]  # its building mass goes to the road
            probs[..., BUILDING] = 0.0
            yield probs, labels

    monkeypatch.setattr(dirichlet_trainer, "dense_probabilities", never_building)
    cfg.fit_pixels, cfg.overwrite = "accepted", True
    with pytest.raises(GeosegError, match="0 accepted true building pixels"):
        dirichlet_trainer.main(cfg)


# ----------------------------------------------------------------------------- one step
def _one_step_lowers(model, loss_fn, batch, lr=1e-3) -> None:
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=lr)
    model.train()

    def loss():
        torch.manual_seed(0)  # same dropout masks both times
        value = loss_fn(model(batch["image"]), batch)
        return value["loss"] if isinstance(value, dict) else value

    before = loss()
    opt.zero_grad()
    before.backward()
    opt.step()
    with torch.no_grad():
        after = loss()
    assert float(after) < float(before.detach())


def _frames(cache: Path, n: int = 2) -> dict:
    cfg = load_config(seg_trainer.SegConfig, {"data": _data(cache)})
    ds = frame_data.build_frame_dataset(cfg.data, "train", augment=False)
    samples = [ds[i] for i in range(n)]
    return {k: torch.stack([s[k] for s in samples]) for k in ("image", "labels", "normals")}


def test_one_step_of_each_trainer_lowers_the_loss(cache_dir):
    torch.manual_seed(0)
    batch = _frames(cache_dir)
    _one_step_lowers(get_model("enet"), WeightedCrossEntropy(torch.ones(8)), batch)
    joint = get_model("joint")
    joint.freeze_trunk_and_labels(True)
    _one_step_lowers(joint, NormalsLoss(), batch)
    naive = get_model("naive_cnn")
    patches = {"image": torch.randn(8, 3, 46, 46), "labels": torch.arange(8)}
    _one_step_lowers(naive, PatchNLL(), patches, lr=1e-4)


def test_losses_ignore_and_mask():
    logits = torch.randn(1, 8, 4, 4, requires_grad=True)
    labels = torch.full((1, 4, 4), 255)
    assert float(WeightedCrossEntropy()({"logits": logits}, {"labels": labels})) == 0.0
    # downsampled labels for the encoder-first stage
    small = torch.randn(1, 8, 2, 2)
    assert (
        WeightedCrossEntropy()({"logits": small}, {"labels": torch.zeros(1, 4, 4).long()}).ndim == 0
    )
    n = torch.nn.functional.normalize(torch.randn(1, 3, 4, 4), dim=1)
    target = n.clone()
    target[..., :2, :] = 0  # invalid rows
    out = NormalsLoss(angular_weight=0.5)({"normals": n}, {"normals": target})
    assert float(out["mse"]) < 1e-10 and float(out["loss"]) < 1e-2


# ----------------------------------------------------------------------------- the command
def test_cli_bad_config_key_exits_2_naming_it(capsys):
    code = cli_main(["train", "seg", "--config", str(TINY_SEG), "--set", "no_such_key=1"])
    assert code == 2
    assert "no_such_key" in capsys.readouterr().err


def test_cli_dataset_in_the_wrong_layout_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "images").mkdir()
    code = cli_main(
        [
            "train",
            "seg",
            "--config",
            str(TINY_SEG),
            "--out",
            str(tmp_path / "run"),
            "--set",
            "data.source=cityscapes",
            "--set",
            f"data.root={tmp_path}",
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "Cityscapes layout" in err and "leftImg8bit" in err


def test_configs_in_the_repository_load():
    root = Path(__file__).resolve().parents[2] / "configs"
    for module, name in (
        (seg_trainer, "seg"),
        (normals_trainer, "normals"),
        (naive_trainer, "naive"),
        (dirichlet_trainer, "dirichlet"),
        (seg_trainer, "seg_real"),
        (seg_trainer, "seg_real_480"),
        (seg_trainer, "seg_real_parked"),
        (normals_trainer, "normals_real"),
        (naive_trainer, "naive_real"),
        (dirichlet_trainer, "dirichlet_real"),
        (dirichlet_trainer, "dirichlet_real_synth"),
    ):
        cfg = load_config(module.CONFIG_CLASS, root / f"{name}.yaml")
        assert cfg.data.source == "synth"
    # stage two of seg_real: stage one's run, at 480x360 with a cache of its own
    stage_two = load_config(seg_trainer.SegConfig, root / "seg_real_480.yaml")
    assert stage_two.init_checkpoint == Path("runs/seg_real/best.pt")
    assert tuple(stage_two.data.size) == (360, 480)
    assert (
        stage_two.data.cache_dir
        != load_config(seg_trainer.SegConfig, root / "seg_real.yaml").data.cache_dir
    )
    # the branch averaged into seg_real: stage two with every second narrow city parked
    parked = load_config(seg_trainer.SegConfig, root / "seg_real_parked.yaml").data.synth
    variants = synthetic_config(parked, split="train").narrow_variants
    assert [v["parking_width"] for v in variants] == [0.0, 2.0]
    with pytest.raises(ConfigError, match="train_crop"):
        load_config(seg_trainer.SegConfig, {"train_crop": [0, 4]})
    for key, value in (("window", 4), ("window", 0), ("fit_pixels", "argmax")):
        with pytest.raises(ConfigError, match=key):
            load_config(dirichlet_trainer.DirichletConfig, {key: value})


def _cityscapes_folder(root: Path) -> Path:
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    for split in ("train", "val"):
        for i in range(2):
            img_dir = root / "leftImg8bit" / split / "aachen"
            lab_dir = root / "gtFine" / split / "aachen"
            img_dir.mkdir(parents=True, exist_ok=True)
            lab_dir.mkdir(parents=True, exist_ok=True)
            name = f"aachen_00000{i}_000019"
            rgb = rng.integers(0, 255, (32, 48, 3), dtype=np.uint8)
            cv2.imwrite(str(img_dir / f"{name}_leftImg8bit.png"), rgb)
            ids = np.array([7, 8, 11, 21, 23, 26], np.uint8)[rng.integers(0, 6, (32, 48))]
            cv2.imwrite(str(lab_dir / f"{name}_gtFine_labelIds.png"), ids)
    return root


def test_seg_trains_on_a_cityscapes_folder(tmp_path):
    root = _cityscapes_folder(tmp_path / "cs")
    cfg = load_config(
        seg_trainer.SegConfig,
        {
            "epochs": 1,
            "batch_size": 2,
            "device": "cpu",
            "progress": False,
            "export": False,
            "class_weight_samples": 2,
            "out_dir": str(tmp_path / "run"),
            "data": {"source": "cityscapes", "root": str(root), "size": [32, 48]},
        },
    )
    run = seg_trainer.main(cfg)
    card = json.loads((run / "model_card.json").read_text())
    assert card["data"]["source"] == "cityscapes" and "val_miou" in card["metrics"]
    assert "onnx" not in card["files"]


def test_cli_trains_end_to_end(tmp_path, cache_dir, capsys):
    out = tmp_path / "run"
    args = ["train", "seg", "--config", str(TINY_SEG), "--out", str(out), "--device", "cpu"]
    args += ["--set", "export=false", "--set", f"data.cache_dir={cache_dir}"]
    assert cli_main(args) == 0
    assert str(out) in capsys.readouterr().out
    card = json.loads((out / "model_card.json").read_text())
    assert card["command"].startswith("geoseg train seg --config")
    assert cli_main(args + ["--resume", "--set", "epochs=2"]) == 0
    assert load_checkpoint(out / "last.pt")["epoch"] == 2
