"""`geoseg render` and `geoseg demo` on tiny configs, and their bad-input errors."""

from __future__ import annotations

import json

import pytest

from geoseg_cli.cli import main


@pytest.fixture()
def tiny_config(tmp_path):
    path = tmp_path / "world_tiny.yaml"
    path.write_text("seed: 4\npreset: light\nblocks_x: 1\nblocks_y: 1\n")
    return path


def test_render_command_writes_a_sequence(tmp_path, tiny_config, capsys) -> None:
    out = tmp_path / "seq"
    argv = ["render", "--config", str(tiny_config), "--out", str(out), "--frames", "2"]
    extra = ["--size", "64x48", "--rig", "tram", "--condition", "dusk", "--workers", "2"]
    assert main(argv + extra) == 0
    assert str(out) in capsys.readouterr().out
    assert len(list((out / "rgb").glob("*.png"))) == 2
    for name in ("preview.png", "poses.csv", "gis/facades.csv", "gis/gps.csv", "gis/dem.geojson"):
        assert (out / name).is_file(), name
    request = json.loads((out / "meta.json").read_text())["request"]
    assert request["rig"] == "tram" and request["condition"] == "dusk"
    assert request["image_size"] == [64, 48] and request["world"]["seed"] == 4


def test_render_command_seed_overrides_the_config(tmp_path, tiny_config, capsys) -> None:
    out = tmp_path / "seq"
    argv = ["render", "--config", str(tiny_config), "--out", str(out), "--frames", "1"]
    assert main(argv + ["--size", "32x24", "--seed", "11", "--gis", "gps.dropout_share=0"]) == 0
    request = json.loads((out / "meta.json").read_text())["request"]
    assert request["world"]["seed"] == 11 and request["seed"] == 11
    assert request["gis"]["gps"]["dropout_share"] == 0.0
    capsys.readouterr()
    assert main(argv + ["--size", "32x24", "--seed", "11", "--gis", "gps.dropout_share=0"]) == 0
    assert "already holds this render" in capsys.readouterr().out  # said, not silent


def test_render_command_unwritable_output(tmp_path, tiny_config, capsys) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a directory")
    out = blocker / "out"
    code = main(["render", "--config", str(tiny_config), "--out", str(out), "--frames", "2"])
    assert code == 2
    err = capsys.readouterr().err
    assert "not writable" in err and str(out) in err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--set", "blocks_z=3"], "blocks_z"),
        (["--set", "blocks_x=zero"], "blocks_x"),
        (["--gis", "gps.bias_max=1"], "bias_max"),
        (["--size", "64by48"], "64by48"),
        (["--condition", "monsoon"], "monsoon"),
        (["--frames", "0"], "--frames"),
        (["--workers", "0"], "workers"),
    ],
)
def test_render_command_bad_inputs(tmp_path, tiny_config, capsys, extra, message) -> None:
    argv = ["render", "--config", str(tiny_config), "--out", str(tmp_path / "o")]
    assert main(argv + ["--frames", "1", "--size", "32x24"] + extra) == 2
    err = capsys.readouterr().err
    assert "error" in err and message in err


def test_render_command_bad_config_file(tmp_path, capsys) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("blocks_x: 1\nblocks_y: 1\nnot_a_key: 3\n")
    assert main(["render", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "not_a_key" in capsys.readouterr().err
    missing = tmp_path / "missing.yaml"
    assert main(["render", "--config", str(missing), "--out", str(tmp_path / "o")]) == 2
    assert "missing.yaml" in capsys.readouterr().err


def test_demo_command_on_a_tiny_world(tmp_path, tiny_config, capsys) -> None:
    out = tmp_path / "demo"
    argv = ["demo", "--config", str(tiny_config), "--out", str(out), "--frames", "2"]
    assert main(argv + ["--size", "48x36", "--drive-m", "0"]) == 0
    printed = capsys.readouterr().out
    for name in ("contact_sheet.png", "map.png", "segmentation.png"):
        assert (out / name).is_file() and str(out / name) in printed
    assert "segmentation (model.onnx, 8 frames): mIoU" in printed  # the shipped network ran
    sequences = sorted(p.name for p in (out / "sequences").iterdir())
    assert sequences == ["car_summer_day", "car_winter", "tram_summer_day", "tram_winter"]
    # same route under two conditions: identical poses, different pictures
    car_a, car_b = out / "sequences" / "car_summer_day", out / "sequences" / "car_winter"
    assert (car_a / "poses.csv").read_text() == (car_b / "poses.csv").read_text()
    assert (car_a / "rgb" / "000000.png").read_bytes() != (
        car_b / "rgb" / "000000.png"
    ).read_bytes()


@pytest.mark.slow
def test_demo_command_bad_inputs(tmp_path, capsys) -> None:
    # the buildings step's outputs: tests/test_readme.py runs the demo with its defaults
    assert main(["demo", "--out", str(tmp_path / "d"), "--drive-m", "-1"]) == 2
    assert "--drive-m" in capsys.readouterr().err
    assert main(["demo", "--out", str(tmp_path), "--conditions", "summer_day,monsoon"]) == 2
    assert "monsoon" in capsys.readouterr().err
    blocker = tmp_path / "f"
    blocker.write_text("x")
    assert main(["demo", "--out", str(blocker / "d")]) == 2
    assert "not writable" in capsys.readouterr().err
