"""Weight averaging (training/average.py): the weighted mean on hand values, the refusals, and a
run folder written from two tiny ENet checkpoints."""

import json
from pathlib import Path

import pytest
import torch

from geoseg.config import load_config
from geoseg.errors import GeosegError
from geoseg.infer import load_model_checkpoint, save_model_checkpoint
from geoseg.models.registry import get_model
from training import average
from training.seg import SegConfig


def test_weighted_mean_of_float_tensors_and_integer_buffers_of_the_heaviest():
    a = {"w": torch.tensor([1.0, 2.0]), "steps": torch.tensor(3)}
    b = {"w": torch.tensor([3.0, 6.0]), "steps": torch.tensor(5)}
    out = average.average_states([a, b], [1.0, 3.0])
    assert torch.allclose(out["w"], torch.tensor([2.5, 5.0]))  # (1*a + 3*b) / 4
    assert out["w"].dtype == torch.float32 and int(out["steps"]) == 5
    # weights are normalised; a zero weight leaves the other state as it is
    assert torch.equal(average.average_states([a, b], [2.0, 0.0])["w"], a["w"])


@pytest.mark.parametrize(
    ("b", "weights", "match"),
    [
        ({"w": torch.zeros(2), "extra": torch.zeros(1)}, [1, 1], "other tensors"),
        ({"w": torch.zeros(3)}, [1, 1], "shape or dtype"),
        ({"w": torch.zeros(2, dtype=torch.float64)}, [1, 1], "shape or dtype"),
        ({"w": torch.zeros(2)}, [1, -1], "finite, >= 0"),
        ({"w": torch.zeros(2)}, [0, 0], "positive sum"),
        ({"w": torch.zeros(2)}, [1, float("nan")], "finite"),
        ({"w": torch.zeros(2)}, [1], "2 state dicts"),
    ],
)
def test_states_of_other_architectures_and_bad_weights_are_refused(b, weights, match):
    with pytest.raises(GeosegError, match=match):
        average.average_states([{"w": torch.ones(2)}, b], weights)


def test_sources_parse_with_and_without_a_weight():
    assert average.parse_source("runs/a:0.25") == average.Source(Path("runs/a"), 0.25)
    assert average.parse_source("runs/a") == average.Source(Path("runs/a"), 1.0)
    assert average.parse_source("c:/runs/a").path == Path("c:/runs/a")  # a colon in the path
    for bad in ("runs/a:x", "runs/a:-1", "runs/a:inf"):
        with pytest.raises(GeosegError, match="weight"):
            average.parse_source(bad)


def _enet_file(path: Path, seed: int) -> Path:
    torch.manual_seed(seed)
    return save_model_checkpoint(get_model("enet"), path, model_name="enet", model_config={})


def test_two_checkpoints_averaged_into_a_run_folder(tmp_path):
    cfg = load_config(
        SegConfig,
        {
            "device": "cpu",
            "export": False,
            "data": {
                "size": [48, 64],
                "cache_dir": str(tmp_path / "cache"),
                "synth": {"seeds": [1], "frames": 2, "val": {"frames": 2}},
            },
        },
    )
    first = _enet_file(tmp_path / "a" / "model.pt", seed=0)
    second = _enet_file(tmp_path / "b" / "model.pt", seed=1)
    for run_dir in (first.parent, second.parent):  # the runs' cards: how long each trained
        (run_dir / "model_card.json").write_text(json.dumps({"epochs": 2, "train_minutes": 1.5}))
    ancestry = [{"file": "runs/older/model.pt", "weight": 1.0, "sha256": "0" * 64}]
    (first.parent / "model_card.json").write_text(  # the first is itself an average
        json.dumps({"epochs": 2, "train_minutes": 1.5, "command": "avg", "averaged_from": ancestry})
    )
    sources = [average.Source(first, 3.0), average.Source(second.parent, 1.0)]  # a run folder too
    run = average.average_runs(tmp_path / "avg", sources, cfg, command="test")

    model, _ = load_model_checkpoint(run / "model.pt")
    a, _ = load_model_checkpoint(first)
    b, _ = load_model_checkpoint(second)
    got, sa, sb = model.state_dict(), a.state_dict(), b.state_dict()
    for name in ("trunk.initial.conv.weight", "trunk.initial.bn.running_var"):
        assert torch.allclose(got[name], 0.75 * sa[name] + 0.25 * sb[name], atol=1e-7)
    card = json.loads((run / "model_card.json").read_text())
    assert [s["weight"] for s in card["averaged_from"]] == [3.0, 1.0]
    assert card["averaged_from"][1]["file"] == str(second)
    assert card["averaged_from"][0]["averaged_from"] == ancestry  # the ancestry is kept
    assert card["averaged_from"][0]["command"] == "avg"
    assert "averaged_from" not in card["averaged_from"][1]
    markdown = (run / "model_card.md").read_text()
    assert "## Averaged from" in markdown and "  - 1.0 x `runs/older/model.pt`" in markdown
    assert 0.0 <= card["metrics"]["val_miou"] <= 1.0 and "colour_statistics" in card
    assert card["epochs"] == 4 and card["train_minutes"] == 3.0
    assert not (run / "model.onnx").exists()  # export off in this config

    with pytest.raises(GeosegError, match="--overwrite"):
        average.average_runs(run, sources, cfg)
    with pytest.raises(GeosegError, match="at least two"):
        average.average_runs(tmp_path / "one", sources[:1], cfg)
    naive = get_model("naive_cnn")
    other = save_model_checkpoint(naive, tmp_path / "n.pt", model_name="naive_cnn", model_config={})
    with pytest.raises(GeosegError, match="expected 'enet'"):
        average.average_runs(tmp_path / "x", [sources[0], average.Source(other)], cfg)


def test_command_reports_a_bad_weight(tmp_path, capsys):
    code = average.main([str(tmp_path / "out"), "a:x", "b", "--config", "configs/seg.yaml"])
    assert code == 2 and "must be a number" in capsys.readouterr().err
