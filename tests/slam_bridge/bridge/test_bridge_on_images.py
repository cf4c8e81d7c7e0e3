"""The whole chain on a tiny rendered drive: the shipped joint network labels the keyframes, the
points gather its evidence, eq. 4.14 associates them with the GIS model's facades and the fusion
uses them, beside the image SLAM's GPS, DEM and odometry."""

from __future__ import annotations

import json

import numpy as np
import pytest

from geoseg.classes import BUILDING, NUM_CLASSES
from geoseg.errors import GeosegError
from geoseg.infer import Segmenter
from geoseg.pretrained import pretrained_file
from geoseg.synth.export import render_sequence
from geoseg_cli.cli import main
from slam_bridge.bridge.association import associate_bayes
from slam_bridge.bridge.builder import BridgeConfig, build_bridge
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.bridge.facades import Facades
from slam_bridge.bridge.worker import BridgeWorker, segmenter_outputs
from slam_bridge.experiments.facade_truth import FacadeTruth
from slam_bridge.system.image_slam import ImageSlamConfig, load_inputs, run_on_images


@pytest.fixture(scope="module")
def drive(tmp_path_factory, make_tiny_world):
    folder = tmp_path_factory.mktemp("bridge") / "render"
    render_sequence(
        make_tiny_world(),
        folder,
        frames=120,
        image_size=(320, 240),
        seed=1,
        progress=False,
    )
    poses = np.genfromtxt(folder / "poses.csv", delimiter=",", names=True)
    rng = np.random.default_rng(3)
    xy = np.column_stack([poses["vehicle_x"], poses["vehicle_y"]]) + rng.normal(0, 0.75, (120, 2))
    np.savetxt(
        folder / "gps.csv", np.column_stack([poses["timestamp"], xy]), delimiter=",",
        header="timestamp,x,y", comments="",
    )  # fmt: skip
    return folder


def test_joint_network_bridge_on_images(drive):
    """A 120-frame drive, the GIS model with its errors (shifted, rotated, missing, extra
    buildings). Measured: 723 points associated at precision 0.91 against the renderer's facade
    ids; building constraints fused at 41 of 73 keyframes (from the georeferencing on)."""
    inputs = load_inputs(
        drive, gps=drive / "gps.csv", odometry=drive / "gis" / "odometry.csv",
        dem=drive / "gis" / "dem.csv",
    )  # fmt: skip
    facades = Facades.read_csv(drive / "gis" / "facades.csv")
    network = segmenter_outputs(Segmenter.from_file(pretrained_file("normals", "model.onnx")))
    worker = BridgeWorker(
        network,
        NUM_CLASSES,
        lambda s: associate_bayes(facades, s.points, s.labels, s.normals, BUILDING, 3.0),
        BuildingConstraints(facades),
        asynchronous=False,
    )
    result, _ = run_on_images(inputs, ImageSlamConfig(), progress=False, bridge=worker)
    fused = sum("building" in r.constraints for r in result.records)
    final = worker.constraints.association
    got = np.flatnonzero(final.associated)
    truth = FacadeTruth(drive, inputs.frames.timestamps).observe_all(result.map)
    truth = truth.model_rows(facades, result.map.num_points)
    precision = np.mean(final.facade[got] == truth[got])
    print(f"{got.size} associated, precision {precision:.3f}, fused {fused}/{len(result.records)}")
    assert result.tracking_failures == 0
    assert len(worker.stats.inference_seconds) >= 0.8 * len(result.records)
    assert got.size >= 200 and precision >= 0.8
    assert fused >= 0.4 * len(result.records)


def test_asynchronous_bridge_with_the_network_in_a_child_process(drive):
    """The default bridge (``build_bridge``: shipped joint network in a child process, association
    in a thread) beside the image SLAM: every job comes back, evidence and associations arrive."""
    inputs = load_inputs(drive, gps=drive / "gps.csv", odometry=drive / "gis" / "odometry.csv")
    facades = Facades.read_csv(drive / "gis" / "facades.csv")
    worker = build_bridge(BridgeConfig(), facades, image_size=inputs.frames.image_size)
    assert worker.in_process
    result, _ = run_on_images(inputs, ImageSlamConfig(), progress=False, bridge=worker)
    submitted = len(worker.stats.inference_seconds) + worker.stats.dropped
    assert result.tracking_failures == 0 and submitted >= 0.8 * len(result.records)
    assert len(worker.stats.inference_seconds) > 0
    assert worker.constraints.association.associated.sum() >= 100


def _slam_run(drive, out, *extra) -> list[str]:
    return [
        "slam", "run", str(drive), "--out", str(out), "--gps", str(drive / "gps.csv"),
        "--odometry", str(drive / "gis" / "odometry.csv"), "--dem", str(drive / "gis" / "dem.csv"),
        "--no-progress", *extra,
    ]  # fmt: skip


def test_slam_run_command_with_buildings(drive, tmp_path, capsys, caplog):
    facades = drive / "gis" / "facades.csv"
    args = _slam_run(
        drive, tmp_path / "run", "--buildings", str(facades), "--association", "raycast"
    )
    assert main(args) == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["association"] == "raycast"
    assert summary["associated_points"] > 100 and summary["building_keyframes"] > 0
    # the GPS bias estimated from the facades (configs/slam_images.yaml: on)
    assert summary["gps_bias_facades"] > 0 and len(summary["gps_bias_m"]) == 2
    assert "map points on facades" in capsys.readouterr().out
    # a model far from the route (another frame, say): the run goes on without building rows
    table = np.genfromtxt(facades, delimiter=",", names=True)
    for c in ("x0", "x1"):
        table[c] += 10_000.0
    table["d"] += 10_000.0 * table["nx"]
    far = tmp_path / "far.csv"
    np.savetxt(far, table, delimiter=",", header=",".join(table.dtype.names), comments="")
    mesh = ["--buildings-mesh", str(drive / "gis" / "buildings_model.ply")]
    assert main(_slam_run(drive, tmp_path / "far", "--buildings", str(far), "--association",
                          "raycast", *mesh)) == 0  # fmt: skip
    summary = json.loads((tmp_path / "far" / "summary.json").read_text())
    assert summary["associated_points"] == 0 and summary["building_keyframes"] == 0
    assert summary["gps_bias_facades"] == 0 and summary["gps_bias_m"] == [0.0, 0.0]
    assert "no map point was associated with a facade" in caplog.text


def test_slam_run_refuses_bridge_options_without_a_building_model(drive, tmp_path, capsys):
    assert main(_slam_run(drive, tmp_path / "a", "--association", "bayes")) == 2
    assert "need --buildings" in capsys.readouterr().err
    facades = str(drive / "gis" / "facades.csv")
    mesh = str(drive / "gis" / "buildings_model.ply")
    assert (
        main(_slam_run(drive, tmp_path / "b", "--buildings", facades, "--buildings-mesh", mesh))
        == 2
    )
    assert "only the raycast association" in capsys.readouterr().err
    dirichlet = ["--dirichlet", "dirichlet"]
    assert main(_slam_run(drive, tmp_path / "c", *dirichlet)) == 2
    assert "need --buildings" in capsys.readouterr().err
    assert main(_slam_run(drive, tmp_path / "d", "--buildings", facades, *dirichlet)) == 2
    assert "only the dirichlet association" in capsys.readouterr().err


def _cast(rgb: np.ndarray) -> np.ndarray:
    """Another camera: a warm white balance and darker mid-tones (bench/colour_transfer_ch4.py)."""
    x = np.clip(rgb / 255.0 * np.array([1.3, 1.0, 0.6]), 0.0, 1.0)
    return np.round(x**1.6 * 255.0).astype(np.uint8)


def test_the_card_transfer_gives_the_cast_keyframe_the_plain_ones_labels(drive):
    """Through another camera's colours the shipped joint network mislabels pixels; mapped onto
    its training set's colours (``colour_transfer: card``) it labels them nearly as it labels
    the render itself. Measured: agreement 0.90 cast, 0.985 cast + transfer."""
    import cv2

    from slam_bridge.bridge.builder import colour_transfer_of, network_outputs

    card = colour_transfer_of(BridgeConfig(colour_transfer="card"))
    plain = network_outputs("bayes", None, 1, (320, 240))
    mapped = network_outputs("bayes", None, 1, (320, 240), card)
    agree_cast, agree_mapped = [], []
    for i in (20, 60, 100):
        bgr = cv2.imread(str(drive / "rgb" / f"{i:06d}.png"), cv2.IMREAD_COLOR)
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        reference = plain(rgb)[0].argmax(-1)
        agree_cast.append(np.mean(plain(_cast(rgb))[0].argmax(-1) == reference))
        agree_mapped.append(np.mean(mapped(_cast(rgb))[0].argmax(-1) == reference))
    print(f"agreement with the render's labels: cast {np.mean(agree_cast):.3f}, "
          f"cast + transfer {np.mean(agree_mapped):.3f}")  # fmt: skip
    assert np.mean(agree_mapped) >= 0.93
    assert np.mean(agree_mapped) > np.mean(agree_cast) + 0.03


def test_slam_run_colour_transfer_reaches_the_bridge(drive, tmp_path, monkeypatch):
    """``--colour-transfer REF`` and ``--colour-means-only`` are the bridge's settings."""
    import slam_bridge.bridge.builder as builder

    seen = []

    def build(cfg, *args, **kwargs):
        seen.append(cfg)
        raise GeosegError("stop before the run")

    monkeypatch.setattr(builder, "build_bridge", build)
    facades = str(drive / "gis" / "facades.csv")
    ref = tmp_path / "reference images"  # any character: not passed through --set
    args = ["--buildings", facades, "--colour-transfer", str(ref), "--colour-means-only"]
    assert main(_slam_run(drive, tmp_path / "a", *args)) == 2
    assert seen[-1].colour_transfer == str(ref) and seen[-1].colour_means_only
    assert main(_slam_run(drive, tmp_path / "b", "--buildings", facades)) == 2
    assert seen[-1].colour_transfer is None and not seen[-1].colour_means_only
    assert main(_slam_run(drive, tmp_path / "c", "--buildings", facades, "--colour-transfer",
                          "card", "--set", "bridge.colour_means_only=true")) == 2  # fmt: skip
    assert seen[-1].colour_transfer == "card" and seen[-1].colour_means_only


def test_slam_run_refuses_colour_options_it_cannot_use(drive, tmp_path, capsys):
    facades = str(drive / "gis" / "facades.csv")
    assert main(_slam_run(drive, tmp_path / "a", "--colour-transfer", "card")) == 2
    assert "need --buildings" in capsys.readouterr().err
    raycast = ["--buildings", facades, "--association", "raycast", "--colour-transfer", "card"]
    assert main(_slam_run(drive, tmp_path / "b", *raycast)) == 2
    assert "uses no network" in capsys.readouterr().err
    means = ["--buildings", facades, "--colour-means-only"]
    assert main(_slam_run(drive, tmp_path / "c", *means)) == 2
    assert "needs --colour-transfer" in capsys.readouterr().err
    missing = ["--buildings", facades, "--colour-transfer", str(tmp_path / "no_such.png")]
    assert main(_slam_run(drive, tmp_path / "d", *missing)) == 2
    err = capsys.readouterr().err
    assert "no_such.png" in err and "no such colour reference" in err


def test_slam_run_with_colour_transfer_records_it(drive, tmp_path):
    """The whole run with ``--colour-transfer card``: the bridge associates as usual and the
    summary names the reference."""
    facades = str(drive / "gis" / "facades.csv")
    run = _slam_run(drive, tmp_path / "run", "--buildings", facades, "--colour-transfer", "card")
    assert main(run) == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["colour_transfer"] == "card" and summary["association"] == "bayes"
    assert summary["associated_points"] > 100
