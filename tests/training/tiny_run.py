"""A tiny training run for the loop's tests: a two-layer network on random 8x8 frames.

Shared by the loop tests and the fault-injection tests, whose child processes run it as a
script: ``python tiny_run.py OUT_DIR EPOCHS KILL_FILE KILL_WHEN N`` trains in ``OUT_DIR`` and
SIGKILLs itself around the ``N``-th rename onto ``KILL_FILE`` (``KILL_WHEN``: ``before`` or
``after`` it), the way a machine dies while a run writes its files.
"""

from __future__ import annotations

import os
import random
import signal
import sys
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from geoseg.config import load_config
from training.config import TrainConfig
from training.distributed import make_loader
from training.loop import fit
from training.metrics import SegmentationMeter


class TinySeg(nn.Module):
    """A stand-in for the real networks: dict output, dropout to exercise the RNG."""

    def __init__(self, classes: int = 3) -> None:
        super().__init__()
        self.conv = nn.Conv2d(3, 8, 3, padding=1)
        self.drop = nn.Dropout2d(0.2)
        self.head = nn.Conv2d(8, classes, 1)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"logits": self.head(self.drop(torch.relu(self.conv(x))))}


class Frames(Dataset):
    def __init__(self, n: int = 12, seed: int = 0) -> None:
        g = torch.Generator().manual_seed(seed)
        self.images = torch.rand(n, 3, 8, 8, generator=g)
        self.labels = (self.images[:, 0] * 3).long().clamp(max=2)

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        # per-sample randomness from the global RNGs, restored on resume
        noise = 0.01 * torch.rand(1) + 0.0 * random.random() + 0.0 * np.random.rand()
        return {"image": self.images[i] + noise, "labels": self.labels[i]}


def ce_loss(outputs, batch):
    return nn.functional.cross_entropy(outputs["logits"], batch["labels"], ignore_index=255)


def tiny_cfg(out_dir: Path, **overrides) -> TrainConfig:
    base = {
        "model": "tiny",
        "epochs": 2,
        "batch_size": 4,
        "device": "cpu",
        "out_dir": str(out_dir),
        "seed": 3,
        "progress": False,
        "best_metric": "val_miou",
        "best_mode": "max",
        "optim": {"lr": 1e-2},
        "schedule": {"name": "cosine"},
    }
    return load_config(TrainConfig, base, overrides=overrides)


def tiny_run(cfg: TrainConfig, model_seed: int = 0, loss_fn=ce_loss) -> Path:
    torch.manual_seed(model_seed)
    model = TinySeg()
    train = make_loader(Frames(12), batch_size=cfg.batch_size, shuffle=True, seed=cfg.seed)
    val = make_loader(Frames(4, seed=1), batch_size=2, shuffle=False)
    return fit(cfg, model, train, val, loss_fn, SegmentationMeter(3, class_names=["a", "b", "c"]))


def kill_around_rename(target: str, when: str, n: int) -> None:
    """SIGKILL this process ``when`` (``before``/``after``) the ``n``-th rename onto ``target``."""
    real = os.replace
    seen = {"n": 0}

    def replace(src, dst, *args, **kwargs):
        hit = Path(dst).name == target and (seen.__setitem__("n", seen["n"] + 1) or True)
        if hit and seen["n"] == n and when == "before":
            os.kill(os.getpid(), signal.SIGKILL)
        real(src, dst, *args, **kwargs)
        if hit and seen["n"] == n and when == "after":
            os.kill(os.getpid(), signal.SIGKILL)

    os.replace = replace


if __name__ == "__main__":
    out, epochs, target, when, n = sys.argv[1:6]
    kill_around_rename(target, when, int(n))
    tiny_run(tiny_cfg(Path(out), epochs=int(epochs), best_metric="train_loss", best_mode="min"))
