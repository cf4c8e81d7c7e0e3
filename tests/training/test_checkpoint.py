"""Checkpoints: round trip with weights_only, atomic writes, clear errors."""

import errno
import random
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

import training.checkpoint as ckpt_mod
from geoseg.errors import GeosegError
from training.checkpoint import (
    BEST,
    LAST,
    build_checkpoint,
    load_checkpoint,
    restore_checkpoint,
    save_checkpoint,
    save_run_checkpoints,
)


class Tiny(nn.Module):
    def __init__(self, width: int = 4) -> None:
        super().__init__()
        self.conv = nn.Conv2d(3, width, 3, padding=1)
        self.head = nn.Conv2d(width, 3, 1)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"logits": self.head(torch.relu(self.conv(x)))}


def _make(width: int = 4, seed: int = 0):
    torch.manual_seed(seed)
    model = Tiny(width)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.5**s)
    model(torch.rand(1, 3, 4, 4))["logits"].sum().backward()
    opt.step()
    sched.step()
    return model, opt, sched


def _checkpoint(model, opt, sched, **kw):
    return build_checkpoint(
        model,
        optimizer=opt,
        scheduler=sched,
        epoch=3,
        global_step=12,
        model_name="tiny",
        model_config={"width": 4},
        config={"out_dir": Path("/x"), "size": (2, 3)},
        history=[{"epoch": 1, "loss": 0.5}],
        **kw,
    )


def test_round_trip_restores_everything(tmp_path: Path) -> None:
    model, opt, sched = _make()
    random.seed(5)
    np.random.seed(5)
    torch.manual_seed(5)
    path = save_checkpoint(_checkpoint(model, opt, sched), tmp_path / "a.pt")
    expected = (random.random(), np.random.rand(), torch.rand(1))
    raw = torch.load(path, weights_only=True)  # loads with weights_only: plain data only
    assert raw["config"] == {"out_dir": "/x", "size": [2, 3]}

    model2, opt2, sched2 = _make(seed=1)
    random.seed(9)
    np.random.seed(9)
    torch.manual_seed(9)
    data = restore_checkpoint(path, model2, optimizer=opt2, scheduler=sched2, model_name="tiny")
    assert (data["epoch"], data["global_step"]) == (3, 12)
    assert data["history"] == [{"epoch": 1, "loss": 0.5}]
    for a, b in zip(model.state_dict().values(), model2.state_dict().values()):
        assert torch.equal(a, b)
    assert sched2.last_epoch == sched.last_epoch
    assert torch.equal(
        opt2.state_dict()["state"][0]["exp_avg"], opt.state_dict()["state"][0]["exp_avg"]
    )
    got = (random.random(), np.random.rand(), torch.rand(1))
    assert got[0] == expected[0] and got[1] == expected[1] and torch.equal(got[2], expected[2])


def test_last_and_best(tmp_path: Path) -> None:
    model, opt, sched = _make()
    save_run_checkpoints(_checkpoint(model, opt, sched), tmp_path, is_best=False)
    assert (tmp_path / LAST).is_file() and not (tmp_path / BEST).exists()
    save_run_checkpoints(_checkpoint(model, opt, sched), tmp_path, is_best=True)
    assert load_checkpoint(tmp_path / BEST)["epoch"] == 3


def test_missing_corrupt_and_foreign_files(tmp_path: Path) -> None:
    with pytest.raises(GeosegError, match="does not exist"):
        load_checkpoint(tmp_path / "nope.pt")
    model, opt, sched = _make()
    good = save_checkpoint(_checkpoint(model, opt, sched), tmp_path / "good.pt")
    truncated = tmp_path / "trunc.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(GeosegError, match=r"trunc\.pt.*corrupt"):
        load_checkpoint(truncated)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all")
    with pytest.raises(GeosegError, match=r"garbage\.pt: a text file, not a torch checkpoint"):
        load_checkpoint(garbage)
    foreign = tmp_path / "foreign.pt"
    torch.save(model.state_dict(), foreign)  # a bare state dict, not ours
    with pytest.raises(GeosegError, match=r"foreign\.pt is not a geoseg checkpoint"):
        load_checkpoint(foreign)


def test_other_architecture_is_refused(tmp_path: Path) -> None:
    model, opt, sched = _make(width=4)
    path = save_checkpoint(_checkpoint(model, opt, sched), tmp_path / "w4.pt")
    wider = Tiny(width=8)
    with pytest.raises(GeosegError, match=r"w4\.pt.*does not fit.*shape mismatch"):
        restore_checkpoint(path, wider)
    with pytest.raises(GeosegError, match=r"w4\.pt holds model 'tiny', not 'enet'"):
        restore_checkpoint(path, Tiny(width=4), model_name="enet")

    class Other(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.lin = nn.Linear(2, 2)

    with pytest.raises(GeosegError, match="missing keys"):
        restore_checkpoint(path, Other())


def test_disk_full_keeps_previous_checkpoint_and_removes_temp(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model, opt, sched = _make()
    path = save_checkpoint(_checkpoint(model, opt, sched), tmp_path / LAST)
    before = path.read_bytes()

    def full_disk(obj, f, *args, **kwargs):
        f.write(b"partial bytes")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ckpt_mod.torch, "save", full_disk)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)
    with pytest.raises(GeosegError, match=r"last\.pt.*no space left.*previous checkpoint is kept"):
        save_checkpoint(_checkpoint(model, opt, sched), path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [LAST]  # no temp file left
    assert load_checkpoint(path)["epoch"] == 3


def test_disk_full_on_first_write_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model, opt, sched = _make()

    def full_disk(obj, f, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ckpt_mod.torch, "save", full_disk)
    with pytest.raises(GeosegError, match="no space left"):
        save_checkpoint(_checkpoint(model, opt, sched), tmp_path / LAST)
    assert list(tmp_path.iterdir()) == []


def test_unstorable_content_is_refused(tmp_path: Path) -> None:
    model, opt, sched = _make()
    with pytest.raises(GeosegError, match="cannot store"):
        _checkpoint(model, opt, sched, extra={"fn": object()})
