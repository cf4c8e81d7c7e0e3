"""``geoseg slam-eval fusion`` end to end on a tiny config (the ch. 3 example's tiny twin)."""

from __future__ import annotations

import json

import pytest
import yaml

from geoseg.config import load_config
from geoseg_cli.cli import main
from slam_bridge.experiments.fusion_ch3 import ExperimentConfig


@pytest.fixture
def tiny(tiny_world_dict) -> dict:
    """The experiment on the tiny city, as a YAML preset would hold it."""
    return {
        "world": tiny_world_dict,
        "sequence": {"length_m": 120.0, "fps": 10.0, "seed": 1, "image_size": [640, 480]},
        "slam": {"window": {"l": 8, "n": 4, "ba_iterations": 8}, "fusion": {"iterations": 8}},
        "methods": ["ba", "dpc", "mpc"],
        "quick_length_m": 40.0,
        "quick_sigmas": [0.0],
        "quick_bias": True,
    }


@pytest.fixture
def tiny_yaml(tmp_path, tiny):
    path = tmp_path / "slam_tiny.yaml"
    path.write_text(yaml.safe_dump(tiny))
    return path


def test_fusion_command_writes_tables_json_plots(tiny_yaml, tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["slam-eval", "fusion", "--config", str(tiny_yaml), "--out", str(out)])
    assert rc == 0
    for name in ("fusion_ch3.md", "fusion_ch3.json", "trajectory.png", "memory.png"):
        assert (out / name).is_file(), name
    printed = capsys.readouterr().out
    assert "Table 3.1" in printed and "Table 3.3" in printed
    res = json.loads((out / "fusion_ch3.json").read_text())
    assert res["settings"] == ["sigma=0", "bias"]
    assert res["sequence_length_m"] == pytest.approx(40.0, abs=3.0)  # the quick run
    for key in ("dpc_time_ratio", "mpc_time_ratio", "memory_ratio", "inlier_loss_max"):
        assert key in res
    # the outcome: with an exact GPS the fused trajectories stay within decimetres of the truth
    for m in ("ba", "dpc", "mpc"):
        assert res[f"{m}_sigma0_t_mean"] < 0.3, m
        assert res[f"{m}_sigma0_r_mean"] < 0.02, m
    assert res["memory_ratio"] > 1.0
    # a second call finds the results and skips the work
    assert main(["slam-eval", "fusion", "--config", str(tiny_yaml), "--out", str(out)]) == 0


def test_default_config_loads_and_quick_is_short():
    cfg = load_config(ExperimentConfig, "configs/slam_ch3.yaml")
    assert cfg.slam.window.l == 40 and cfg.slam.window.n == 30
    assert cfg.settings() == ["sigma=0", "sigma=0.75", "sigma=1.5", "bias"]
    quick = cfg.quick()
    assert quick.sequence.length_m < cfg.sequence.length_m
    assert cfg.sequence.length_m == 640.0


def test_bad_override_is_a_clear_error(tiny_yaml, tmp_path, capsys):
    rc = main(
        ["slam-eval", "fusion", "--config", str(tiny_yaml), "--out", str(tmp_path / "x")]
        + ["--set", "methods=[ba,ekf]"]
    )
    assert rc == 2
    assert "methods" in capsys.readouterr().err


def test_bench_other_drives_mean_and_worst(tiny_yaml, tmp_path, capsys):
    """bench/fusion_ch3.py --drives: the grid on each drive, then per-figure mean and worst."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[3] / "bench" / "fusion_ch3.py"
    spec = importlib.util.spec_from_file_location("fusion_ch3_bench", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    cfg = load_config(ExperimentConfig, tiny_yaml).quick()
    drives = bench.other_drives(cfg, [1, 2], tmp_path)
    assert drives["seeds"] == [1, 2] and set(drives["failures"]) == {"1", "2"}
    per_drive = [
        json.loads((tmp_path / f"drive_{s}" / "fusion_ch3.json").read_text()) for s in (1, 2)
    ]
    assert per_drive[0]["ba_sigma0_t_mean"] != per_drive[1]["ba_sigma0_t_mean"]  # other drives
    for key in ("ba_sigma0_t_mean", "mpc_time_ratio", "inlier_loss_max"):
        values = [d[key] for d in per_drive]
        assert drives["mean"][key] == pytest.approx(sum(values) / 2)
        assert drives["max"][key] == pytest.approx(max(values))
    assert "ba_sigma0_t_mean" in capsys.readouterr().out
    # a drive where every run fails is reported, not averaged; none left is a clear error
    from slam_bridge.errors import SlamError

    real = bench.run_experiment

    def lost_on_drive_2(cfg_s, out, force):
        if cfg_s.sequence.seed == 2:
            raise SlamError("every run failed: tracking lost")
        return real(cfg_s, out, force=force)

    bench.run_experiment = lost_on_drive_2
    one = bench.other_drives(cfg, [1, 2], tmp_path / "again")
    assert "tracking lost" in one["failures"]["2"][0]["error"]
    assert one["mean"]["ba_sigma0_t_mean"] == pytest.approx(per_drive[0]["ba_sigma0_t_mean"])
    with pytest.raises(SlamError, match="every run failed"):
        bench.other_drives(cfg, [2], tmp_path / "none")


def test_chapter3_experiment_on_image_tracks(tmp_path, tiny):
    """The same experiment with the visual front end on rendered frames instead of simulated
    tracks: the frames are rendered once, the runs stay near the truth with an exact GPS."""
    from slam_bridge.experiments.fusion_ch3 import run_experiment

    cfg = load_config(
        ExperimentConfig,
        {
            **tiny,
            "sequence": {**tiny["sequence"], "length_m": 50.0, "image_size": [320, 240]},
            "tracks": "images",
            "methods": ["ba", "dpc"],
            "gps_sigmas": [0.0],
            "gps_bias": False,
        },
    )
    out = run_experiment(cfg, tmp_path / "images")
    res = json.loads((out / "fusion_ch3.json").read_text())
    assert res["tracks"] == "images" and res["keyframes"] >= 15
    assert len(list((out / "frames").glob("*.png"))) > res["keyframes"]
    for m in ("ba", "dpc"):
        assert res[f"{m}_sigma0_t_mean"] < 0.5, m
        assert res[f"{m}_sigma0_r_mean"] < 0.02, m
