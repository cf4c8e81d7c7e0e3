"""The shared loop: a step lowers the loss; fit writes its outputs; resume is exact."""

import json
import random
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_run import Frames, TinySeg, ce_loss
from tiny_run import tiny_cfg as _cfg
from tiny_run import tiny_run as _run

from geoseg.config import load_config
from geoseg.errors import ConfigError, GeosegError
from training.config import TrainConfig
from training.loop import evaluate, train_one_epoch
from training.metrics import SegmentationMeter


def test_one_step_lowers_the_loss_on_a_fixed_batch() -> None:
    torch.manual_seed(0)
    model = TinySeg()
    model.drop.p = 0.0
    batch = Frames(4)[0]
    batch = {
        "image": batch["image"][None].repeat(4, 1, 1, 1),
        "labels": batch["labels"][None].repeat(4, 1, 1),
    }
    opt = torch.optim.SGD(model.parameters(), lr=0.5)
    with torch.no_grad():
        before = float(ce_loss(model(batch["image"]), batch))
    stats = train_one_epoch(model, [batch], ce_loss, opt, device="cpu", progress=False)
    with torch.no_grad():
        after = float(ce_loss(model(batch["image"]), batch))
    assert stats["loss"] == pytest.approx(before, rel=1e-5)
    assert after < before
    out = evaluate(model, [batch], SegmentationMeter(3), device="cpu", loss_fn=ce_loss)
    assert out["loss"] == pytest.approx(after, rel=1e-4) and 0 <= out["pixel_acc"] <= 1


def test_fit_writes_checkpoints_metrics_and_plots(tmp_path: Path) -> None:
    run = _run(_cfg(tmp_path / "run"))
    names = {p.name for p in run.iterdir()}
    assert {
        "last.pt",
        "best.pt",
        "metrics.csv",
        "metrics.json",
        "loss.png",
        "metrics.png",
        "config.yaml",
    } <= names
    rows = json.loads((run / "metrics.json").read_text())
    assert [r["epoch"] for r in rows] == [1, 2]
    assert {"train_loss", "val_loss", "val_miou", "lr"} <= set(rows[0])
    assert (run / "metrics.csv").read_text().splitlines()[0].startswith("epoch,")
    # the same out_dir again without resume/overwrite must not clobber the run
    with pytest.raises(GeosegError, match="holds an earlier run.*last.pt"):
        _run(_cfg(tmp_path / "run"))
    # a finished run resumed is a no-op that returns the directory
    stamp = (run / "last.pt").stat().st_mtime_ns
    assert _run(_cfg(tmp_path / "run", resume=True)) == run
    assert (run / "last.pt").stat().st_mtime_ns == stamp


class Crash(RuntimeError):
    pass


def _crashing(after_calls: int):
    calls = {"n": 0}

    def loss(outputs, batch):
        calls["n"] += 1
        if calls["n"] > after_calls:
            raise Crash("simulated crash")
        return ce_loss(outputs, batch)

    return loss


@pytest.mark.parametrize("how", ["crash", "extend"])
def test_resume_is_exact(tmp_path: Path, how: str) -> None:
    """2 epochs straight == 1 epoch, then a fresh resume for the 2nd: bitwise equal weights."""
    schedule = "cosine" if how == "crash" else "constant"
    straight = _run(_cfg(tmp_path / "a", **{"schedule.name": schedule}))
    if how == "crash":  # the process dies in epoch 2 (3 train + 2 val loss calls per epoch)
        with pytest.raises(Crash):
            _run(_cfg(tmp_path / "b", **{"schedule.name": schedule}), loss_fn=_crashing(5))
    else:  # a 1-epoch run extended to 2 epochs
        _run(_cfg(tmp_path / "b", epochs=1, **{"schedule.name": schedule}))
    assert torch.load(tmp_path / "b" / "last.pt", weights_only=True)["epoch"] == 1
    # a "new process": scramble every global RNG and rebuild everything from scratch
    random.seed(123)
    np.random.seed(123)
    torch.manual_seed(123)
    resumed = _run(_cfg(tmp_path / "b", resume=True, **{"schedule.name": schedule}), model_seed=77)
    a = torch.load(straight / "last.pt", weights_only=True)
    b = torch.load(resumed / "last.pt", weights_only=True)
    assert a["epoch"] == b["epoch"] == 2 and a["global_step"] == b["global_step"] == 6
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key
    for sa, sb in zip(a["optimizer"]["state"].values(), b["optimizer"]["state"].values()):
        assert torch.equal(sa["exp_avg"], sb["exp_avg"])
    assert a["history"][1]["train_loss"] == b["history"][1]["train_loss"]
    assert a["history"][1]["lr"] == b["history"][1]["lr"]
    assert len(b["history"]) == 2


def test_config_errors_and_nonfinite_loss(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="optim.lrr"):
        load_config(TrainConfig, {"optim": {"lrr": 1.0}})
    with pytest.raises(ConfigError, match="epochs"):
        load_config(TrainConfig, {"epochs": 0})
    model = TinySeg()
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    batch = Frames(2)[0]
    batch = {"image": batch["image"][None], "labels": batch["labels"][None]}
    with pytest.raises(GeosegError, match="loss is nan"):
        train_one_epoch(
            model,
            [batch],
            lambda o, b: o["logits"].sum() * float("nan"),
            opt,
            device="cpu",
            progress=False,
        )
