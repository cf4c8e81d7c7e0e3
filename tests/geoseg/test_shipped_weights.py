"""The trained weights shipped in geoseg/weights: present, documented, and they work.

These check behaviour on a frame of the validation city (seed 13), which no network trained on;
the accuracy figures themselves come from bench/accuracy_seg.py on the held-out city.
"""

import cv2
import numpy as np
import pytest

from geoseg.classes import BUILDING
from geoseg.data.synthetic import SyntheticDataset, synthetic_config
from geoseg.dirichlet import DirichletFilter, load_filter
from geoseg.pretrained import (
    PRETRAINED,
    USER_ONLY,
    model_card,
    pretrained_file,
    pretrained_segmenter,
)
from geoseg_cli.cli import main


@pytest.fixture(scope="module")
def frame():
    """One 320x240 validation-city frame: uint8 RGB, labels, normals, normal mask."""
    sample = SyntheticDataset(synthetic_config({}, split="val"), size=(240, 320))[0]
    rgb = (sample["image"].numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
    return rgb, sample["labels"].numpy(), sample["normals"].numpy(), sample["normal_valid"].numpy()


@pytest.mark.parametrize("name", sorted(set(PRETRAINED) - USER_ONLY))  # every shipped name
def test_every_shipped_model_has_a_card_with_its_command(name):
    card = model_card(name)
    command = str(card.get("command", ""))
    if "averaged_from" in card:  # weights averaged from trained runs (training/average.py)
        assert command.startswith("python -m training.average")
        sources = card["averaged_from"]
        assert len(sources) >= 2 and all(len(s["sha256"]) == 64 for s in sources)
    else:
        assert "geoseg train" in command, card.keys()


def test_shipped_joint_network_segments_and_orients_an_unseen_frame(frame):
    rgb, labels, normals, valid = frame
    result = pretrained_segmenter("normals", backend="onnx")(rgb)
    assert (result.labels[0] == labels).mean() > 0.85
    building = (labels == BUILDING) & valid
    cos = (result.normals[0] * normals).sum(0)[building]
    assert np.median(np.degrees(np.arccos(np.clip(cos, -1, 1)))) < 20.0


def test_shipped_onnx_and_torch_agree(frame):
    rgb = frame[0]
    ort = pretrained_segmenter("normals", backend="onnx")(rgb)
    pt = pretrained_segmenter("normals", backend="torch")(rgb)
    assert (ort.labels == pt.labels).mean() >= 0.999
    cos = np.clip((ort.normals * pt.normals).sum(1), -1, 1)
    assert np.degrees(np.arccos(cos)).mean() <= 0.5


def test_real_image_weights_label_an_unseen_frame_and_their_backends_agree(frame):
    rgb, labels = frame[0], frame[1]
    ort = pretrained_segmenter("seg_real", backend="onnx")(rgb)
    pt = pretrained_segmenter("seg_real", backend="torch")(rgb)
    assert ort.normals is None and ort.probabilities.shape == (1, 8, 240, 320)
    assert (ort.labels[0] == labels).mean() > 0.8
    assert (ort.labels == pt.labels).mean() >= 0.999


def test_real_image_joint_network_is_seg_real_with_normals(frame):
    rgb, labels, normals, valid = frame
    joint = pretrained_segmenter("normals_real", backend="onnx")(rgb)
    labels_only = pretrained_segmenter("seg_real", backend="onnx")(rgb)
    # the frozen seg_real trunk and label head: the same labels, and normals beside them
    assert (joint.labels == labels_only.labels).mean() >= 0.999
    building = (labels == BUILDING) & valid
    cos = (joint.normals[0] * normals).sum(0)[building]
    assert np.median(np.degrees(np.arccos(np.clip(cos, -1, 1)))) < 20.0
    torch_normals = pretrained_segmenter("normals_real", backend="torch")(rgb).normals
    cos = np.clip((joint.normals * torch_normals).sum(1), -1, 1)
    assert np.degrees(np.arccos(cos)).mean() <= 0.5


def test_real_image_naive_cnn_labels_an_unseen_frame_and_its_backends_agree(frame):
    rgb, labels = frame[0], frame[1]
    ort = pretrained_segmenter("naive_real", backend="onnx")(rgb)
    assert ort.normals is None and ort.probabilities.shape == (1, 8, 240, 320)
    assert (ort.labels[0] == labels).mean() > 0.85
    assert (ort.labels[0][labels == BUILDING] == BUILDING).mean() > 0.85
    pt = pretrained_segmenter("naive_real", backend="torch")(rgb)
    assert (ort.labels == pt.labels).mean() >= 0.999


@pytest.mark.parametrize("name", [n for n in sorted(PRETRAINED) if n.startswith("dirichlet")])
def test_shipped_dirichlet_filter_is_calibrated(name):
    flt = load_filter(pretrained_file(name, "dirichlet.json"))
    assert isinstance(flt, DirichletFilter) and flt.threshold is not None
    assert np.all(flt.alpha > 0)


def test_infer_defaults_to_the_shipped_network(frame, tmp_path):
    image = tmp_path / "street.png"
    cv2.imwrite(str(image), cv2.cvtColor(frame[0], cv2.COLOR_RGB2BGR))
    assert main(["infer", str(image), "--out", str(tmp_path / "out")]) == 0
    for suffix in ("labels", "overlay", "normals"):
        assert (tmp_path / "out" / f"street_{suffix}.png").is_file(), suffix
