"""Typed configs: defaults, YAML overrides, dotted overrides and the errors they raise."""

from dataclasses import dataclass, field
from pathlib import Path

import pytest

from geoseg.config import load_config, to_dict
from geoseg.errors import ConfigError


@dataclass
class Inner:
    size: tuple[int, int] = (320, 240)
    name: str = "a"


@dataclass
class Outer:
    epochs: int = 3
    lr: float = 1e-3
    flag: bool = False
    inner: Inner = field(default_factory=Inner)
    tags: list[str] = field(default_factory=list)
    maybe: float | None = None


def test_defaults_yaml_and_overrides(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("epochs: 5\ninner:\n  size: [64, 48]\n")
    cfg = load_config(Outer, path, overrides=["lr=0.5", "inner.name=b", "maybe=2"])
    assert cfg.epochs == 5 and cfg.lr == 0.5 and cfg.inner.size == (64, 48)
    assert cfg.inner.name == "b" and cfg.maybe == 2.0 and cfg.flag is False
    assert to_dict(cfg)["inner"]["size"] == [64, 48]


@pytest.mark.parametrize(
    "data, needle",
    [
        ({"epoch": 1}, "epoch"),
        ({"epochs": "three"}, "epochs"),
        ({"epochs": 1.5}, "epochs"),
        ({"flag": 1}, "flag"),
        ({"inner": {"size": [1, 2, 3]}}, "inner.size"),
        ({"inner": {"colour": 1}}, "inner.colour"),
    ],
)
def test_bad_keys_and_types_name_the_key(data: dict, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle.replace(".", r"\.")):
        load_config(Outer, data)


def test_missing_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(Outer, tmp_path / "nope.yaml")


@dataclass
class WithPath:
    out: Path = Path("runs")
    lr: float = 1e-3


def test_paths_save_and_numeric_strings_load(tmp_path: Path) -> None:
    from geoseg.config import save_config

    cfg = load_config(WithPath, overrides=["lr=1e-4", f"out={tmp_path}"])
    assert cfg.lr == 1e-4 and cfg.out == tmp_path
    save_config(cfg, tmp_path / "c.yaml")
    assert load_config(WithPath, tmp_path / "c.yaml") == cfg
    with pytest.raises(ConfigError, match="lr"):
        load_config(WithPath, {"lr": "fast"})


# ---------------------------------------------------------------------------- reliability


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("optim.lr=nan", "optim.lr"),
        ("optim.lr=.inf", "optim.lr"),
        ("optim.betas=[0.9, .nan]", "optim.betas[1]"),
        ("data.augment.scale=[0.5, .nan]", "data.augment.scale[1]"),
        ("data.synth.frames=.nan", "data.synth.frames"),
        ("data.synth.val.seeds=[1, .inf]", "data.synth.val.seeds[1]"),
        ("model_config.num_classes=.nan", "model_config.num_classes"),
        ("optim.momentum=-1", "optim.momentum"),
        ("schedule.gamma=0", "schedule.gamma"),
        ("class_weight_c=0.5", "class_weight_c"),
    ],
)
def test_non_finite_and_out_of_range_values_name_their_full_key(override, key) -> None:
    from training.seg import SegConfig

    with pytest.raises(ConfigError) as info:
        load_config(SegConfig, None, overrides=[override])
    assert str(info.value).startswith(key), str(info.value)


def test_train_finds_the_repository_preset_from_any_folder(tmp_path, monkeypatch, capsys) -> None:
    import geoseg.config
    from geoseg_cli.cli import main

    monkeypatch.chdir(tmp_path)
    assert geoseg.config.default_config_file("seg.yaml") == geoseg.config.REPO_CONFIGS / "seg.yaml"
    # the preset is loaded (and printed) before the bad override is refused
    assert main(["train", "seg", "--set", "epochs=0"]) == 2
    captured = capsys.readouterr()
    assert str(geoseg.config.REPO_CONFIGS / "seg.yaml") in captured.out
    assert "epochs" in captured.err
    # no preset anywhere: --config is required instead of silent built-in defaults
    monkeypatch.setattr(geoseg.config, "REPO_CONFIGS", tmp_path / "nowhere")
    assert main(["train", "seg"]) == 2
    assert "--config" in capsys.readouterr().err
