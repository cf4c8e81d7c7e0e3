"""Fault injection on a training run: kill or fail at every write, then resume.

The run writes, per epoch, ``last.pt`` then (when the epoch is the best so far) ``best.pt``, then
``metrics.csv``/``metrics.json`` and the plots, each atomically (temporary file, then rename).
A child process is SIGKILLed before or after the rename of each file in turn; a resume must then
end exactly where an uninterrupted run ends (weights, optimizer, ``best.pt`` and history), with
no temporary file left. The same for a write that fails (disk full) instead of a kill.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tiny_run import tiny_cfg, tiny_run

import geoseg
from geoseg.atomic import TEMP_PATTERN
from geoseg.errors import GeosegError
from training.checkpoint import (
    BEST,
    LAST,
    load_checkpoint,
    reconcile_run_checkpoints,
    save_checkpoint,
)
from training.common import load_best_weights

EPOCHS = 3
TINY = Path(__file__).with_name("tiny_run.py")
ROOT = Path(geoseg.__file__).resolve().parent.parent


def _cfg(out: Path, **kw):
    return tiny_cfg(
        out, **{"epochs": EPOCHS, "best_metric": "train_loss", "best_mode": "min", **kw}
    )


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """The uninterrupted run (every epoch improves the training loss: best.pt is rewritten)."""
    run = tiny_run(_cfg(tmp_path_factory.mktemp("ref") / "run"))
    assert [r["epoch"] for r in json.loads((run / "metrics.json").read_text())] == [1, 2, 3]
    assert load_checkpoint(run / BEST)["epoch"] == EPOCHS
    return run


def _same_run(run: Path, reference: Path) -> None:
    for name in (LAST, BEST):
        a, b = load_checkpoint(reference / name), load_checkpoint(run / name)
        assert a["epoch"] == b["epoch"] and a["best_epoch"] == b["best_epoch"], name
        for key, value in a["model"].items():
            assert torch.equal(value, b["model"][key]), (name, key)
    for sa, sb in zip(
        load_checkpoint(reference / LAST)["optimizer"]["state"].values(),
        load_checkpoint(run / LAST)["optimizer"]["state"].values(),
    ):
        assert torch.equal(sa["exp_avg"], sb["exp_avg"])

    def rows(folder: Path) -> list[dict]:
        return [
            {k: v for k, v in r.items() if k != "time_s"}
            for r in json.loads((folder / "metrics.json").read_text())
        ]

    assert rows(run) == rows(reference)
    assert not [p for p in run.rglob("*") if TEMP_PATTERN.match(p.name)]


@pytest.mark.parametrize(
    ("target", "when", "n"),
    [
        ("config.yaml", "after", 1),  # before any epoch
        (LAST, "before", 2),  # last.pt's temporary file written, not renamed
        (LAST, "after", 2),  # between the two checkpoint files
        (BEST, "before", 2),
        (BEST, "after", 2),  # checkpoints written, history not
        ("metrics.json", "before", 2),
        (LAST, "after", EPOCHS),  # the last epoch's last.pt, then the kill
    ],
)
def test_kill_at_each_write_then_resume_matches_an_uninterrupted_run(
    tmp_path, reference, target, when, n
) -> None:
    out = tmp_path / "run"
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    )
    proc = subprocess.run(
        [sys.executable, str(TINY), str(out), str(EPOCHS), target, when, str(n)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    tiny_run(_cfg(out, resume=True))
    _same_run(out, reference)


@pytest.mark.parametrize(("target", "n"), [(LAST, 2), (BEST, 2), ("metrics.csv", 2)])
def test_a_failed_write_is_a_clear_error_and_resume_recovers(
    tmp_path, reference, monkeypatch, target, n
) -> None:
    out = tmp_path / "run"
    real, seen = os.replace, {"n": 0}

    def replace(src, dst, *args, **kwargs):
        if Path(dst).name == target:
            seen["n"] += 1
            if seen["n"] == n:
                raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(GeosegError, match=rf"{target}.*no space left"):
        tiny_run(_cfg(out))
    monkeypatch.undo()
    assert not [p for p in out.rglob("*") if TEMP_PATTERN.match(p.name)]
    tiny_run(_cfg(out, resume=True))
    _same_run(out, reference)


def test_reconcile_restores_best_from_last_after_a_kill_between_them(tmp_path) -> None:
    out = tmp_path / "run"
    tiny_run(_cfg(out, epochs=1))
    stale_best = (out / BEST).read_bytes()  # epoch 1
    tiny_run(_cfg(out, epochs=2, resume=True))
    assert load_checkpoint(out / BEST)["epoch"] == 2
    (out / BEST).write_bytes(stale_best)  # as if killed after last.pt of epoch 2
    (out / ".best.pt.a1b2c3d4.tmp").write_bytes(b"half a checkpoint")
    last = reconcile_run_checkpoints(out)
    assert last is not None and last["best_epoch"] == 2
    assert load_checkpoint(out / BEST)["epoch"] == 2
    assert not (out / ".best.pt.a1b2c3d4.tmp").exists()
    # the weights and the card's metrics then come from the same epoch
    from tiny_run import TinySeg

    file, metrics = load_best_weights(TinySeg(), out)
    assert file.name == BEST and metrics["epoch"] == 2


def test_best_and_last_of_two_runs_are_refused(tmp_path) -> None:
    """A pair no crash produces (last.pt's best is an earlier epoch than best.pt holds)."""
    out = tmp_path / "run"
    tiny_run(_cfg(out, epochs=2))
    last = load_checkpoint(out / LAST)
    save_checkpoint({**last, "best_epoch": 1}, out / LAST)  # best.pt holds epoch 2
    with pytest.raises(GeosegError, match="do not belong together"):
        reconcile_run_checkpoints(out)
    with pytest.raises(GeosegError, match="do not belong together"):
        tiny_run(_cfg(out, resume=True))
