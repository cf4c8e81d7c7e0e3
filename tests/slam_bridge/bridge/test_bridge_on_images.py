"""The whole chain on a tiny rendered drive: the shipped joint network labels the keyframes, the
points gather its evidence, eq. 4.14 associates them with the GIS model's facades and the fusion
uses them, beside the image SLAM's GPS, DEM and odometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geoseg.classes import BUILDING, NUM_CLASSES
from geoseg.infer import Segmenter
from geoseg.pretrained import pretrained_file
from geoseg.synth.export import render_sequence
from slam_bridge.bridge.association import associate_bayes
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.bridge.facades import Facades
from slam_bridge.bridge.worker import BridgeWorker, segmenter_outputs
from slam_bridge.image_slam import ImageSlamConfig, load_inputs, run_on_images


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


def _true_facades(folder, result, inputs, facades) -> np.ndarray:
    """``(P,)`` the model facade under each point's first observation (renderer instance ids),
    -1 where it is not on a modelled facade."""
    m = result.map
    frame_of = np.searchsorted(inputs.frames.timestamps, m.timestamps)
    truth = np.full(m.num_points, -1)
    points, first = np.unique(m.obs_point, return_index=True)  # observations are in order
    for f in np.unique(frame_of[m.obs_keyframe[first]]):
        here = first[frame_of[m.obs_keyframe[first]] == f]
        instance = np.load(folder / "geometry" / f"{f:06d}.npz")["instance"]
        label = cv2.imread(str(folder / "labels" / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE)
        u, v = np.rint(m.obs_uv[here]).astype(int).T
        for o, inst, lab in zip(here, instance[v, u], label[v, u], strict=True):
            rows = np.flatnonzero(facades.true_facade_id == inst)
            if lab == BUILDING and rows.size:
                truth[m.obs_point[o]] = rows[0]
    return truth


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
    truth = _true_facades(drive, result, inputs, facades)
    precision = np.mean(final.facade[got] == truth[got])
    print(f"{got.size} associated, precision {precision:.3f}, fused {fused}/{len(result.records)}")
    assert result.tracking_failures == 0
    assert len(worker.stats.inference_seconds) >= 0.8 * len(result.records)
    assert got.size >= 200 and precision >= 0.8
    assert fused >= 0.4 * len(result.records)
