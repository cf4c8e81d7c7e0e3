"""What a resumed or restarted run may do: nothing silently lost, nothing silently ignored."""

from __future__ import annotations

import json

import pytest
import torch
import yaml
from tiny_run import tiny_cfg, tiny_run

from geoseg.errors import GeosegError
from geoseg.output_dir import output_producer
from training.checkpoint import BEST, LAST, load_checkpoint


def test_resume_applies_a_new_learning_rate_and_records_it(tmp_path) -> None:
    run = tiny_run(tiny_cfg(tmp_path / "run", epochs=1, **{"schedule.name": "constant"}))
    assert load_checkpoint(run / LAST)["history"][0]["lr"] == pytest.approx(1e-2)
    tiny_run(
        tiny_cfg(run, epochs=2, resume=True, **{"schedule.name": "constant", "optim.lr": 1e-3})
    )
    ckpt = load_checkpoint(run / LAST)
    assert ckpt["history"][1]["lr"] == pytest.approx(1e-3)  # what the optimizer used
    assert ckpt["optimizer"]["param_groups"][0]["lr"] == pytest.approx(1e-3)
    assert yaml.safe_load((run / "config.yaml").read_text())["optim"]["lr"] == 1e-3


@pytest.mark.parametrize(
    ("override", "key"),
    [({"seed": 4}, "seed"), ({"batch_size": 2}, "batch_size"), ({"optim.name": "sgd"}, "optim")],
)
def test_resume_refuses_changes_it_cannot_honour(tmp_path, override, key) -> None:
    run = tiny_run(tiny_cfg(tmp_path / "run", epochs=1))
    before = (run / LAST).read_bytes()
    with pytest.raises(GeosegError, match=rf"resume: .*{key}"):
        tiny_run(tiny_cfg(run, epochs=2, resume=True, **override))
    assert (run / LAST).read_bytes() == before


def test_resume_without_last_never_clobbers_an_earlier_run(tmp_path) -> None:
    run = tiny_run(tiny_cfg(tmp_path / "run", epochs=1))
    (run / LAST).unlink()
    best, metrics = (run / BEST).read_bytes(), (run / "metrics.csv").read_text()
    with pytest.raises(GeosegError, match=r"resume: .*last.pt does not exist.*best.pt"):
        tiny_run(tiny_cfg(run, epochs=2, resume=True))
    assert (run / BEST).read_bytes() == best and (run / "metrics.csv").read_text() == metrics
    # in an empty folder, resume simply starts (a job script that always passes --resume)
    assert tiny_run(tiny_cfg(tmp_path / "new", epochs=1, resume=True)).is_dir()


def test_a_fresh_start_with_overwrite_removes_the_earlier_runs_results(tmp_path) -> None:
    run = tiny_run(tiny_cfg(tmp_path / "run", epochs=2))
    # a metric that never gets a value: no best.pt is written by the new run
    tiny_run(tiny_cfg(run, epochs=1, overwrite=True, best_metric="val_nothing"))
    assert not (run / BEST).exists()  # the old run's best.pt did not outlive it
    assert [r["epoch"] for r in json.loads((run / "metrics.json").read_text())] == [1]


def test_training_refuses_a_folder_of_someone_elses_files(tmp_path) -> None:
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "holiday.jpg").write_bytes(b"jpeg")
    with pytest.raises(GeosegError, match="holiday.jpg.*--overwrite"):
        tiny_run(tiny_cfg(folder, epochs=1))
    assert [p.name for p in folder.iterdir()] == ["holiday.jpg"]
    run = tiny_run(tiny_cfg(tmp_path / "run", epochs=1))
    assert output_producer(run) == "train"


def test_a_run_dir_from_before_markers_is_adopted(tmp_path) -> None:
    run = tiny_run(tiny_cfg(tmp_path / "run", epochs=1))
    (run / ".geoseg-output.json").unlink()  # as written by an older geoseg
    tiny_run(tiny_cfg(run, epochs=2, resume=True))
    assert load_checkpoint(run / LAST)["epoch"] == 2


def test_resume_refuses_a_corrupt_last_checkpoint(tmp_path) -> None:
    run = tiny_run(tiny_cfg(tmp_path / "run", epochs=1))
    data = bytearray((run / LAST).read_bytes())
    middle = len(data) // 2
    for i in range(middle, middle + 8):
        data[i] ^= 0xFF
    (run / LAST).write_bytes(bytes(data))
    with pytest.raises(GeosegError, match="last.pt"):
        tiny_run(tiny_cfg(run, epochs=2, resume=True))


def test_weights_of_resumed_runs_are_sealed(tmp_path) -> None:
    run = tiny_run(tiny_cfg(tmp_path / "run", epochs=1))
    raw = torch.load(run / LAST, weights_only=True)
    assert isinstance(raw.get("sha256"), str) and raw["best_epoch"] == 1
