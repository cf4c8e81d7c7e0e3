"""Segmenter (checkpoint and ONNX), checkpoints, and `geoseg export` / `geoseg infer` end to end."""

import cv2
import numpy as np
import pytest
import torch

from geoseg.errors import GeosegError
from geoseg.infer import (
    Segmenter,
    load_model_checkpoint,
    normals_to_rgb,
    save_model_checkpoint,
)
from geoseg.integrity import seal
from geoseg.models import get_model
from geoseg_cli.cli import main

NORM = {"mean": [0.5, 0.4, 0.3], "std": [0.2, 0.25, 0.3]}  # conftest.JOINT_NORM


# joint_files (tests/conftest.py): a joint checkpoint stored with NORM and its export through
# `geoseg export --checkpoint`, shared with test_export.py.


def _images(n: int, h: int = 37, w: int = 50) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (n, h, w, 3), dtype=np.uint8)


def test_checkpoint_round_trip_and_atomic_write(joint_files) -> None:
    ckpt, _ = joint_files
    assert not list(ckpt.parent.glob(".*.tmp"))
    model, meta = load_model_checkpoint(ckpt)
    assert meta["model_name"] == "joint" and meta["normalization"] == NORM
    assert not model.training


def test_segmenter_torch_and_onnx_agree(joint_files) -> None:
    ckpt, onnx_path = joint_files
    images = _images(2)
    a = Segmenter.from_checkpoint(ckpt, device="cpu")(images)
    b = Segmenter.from_onnx(onnx_path, providers=["CPUExecutionProvider"])(images)
    for r in (a, b):
        assert r.probabilities.shape == (2, 8, 37, 50) and r.labels.shape == (2, 37, 50)
        assert r.normals.shape == (2, 3, 37, 50) and r.features.shape == (2, 128, 5, 7)
        np.testing.assert_allclose(r.probabilities.sum(1), 1.0, atol=1e-5)
    assert (a.labels == b.labels).mean() >= 0.999
    cos = np.clip((a.normals * b.normals).sum(1), -1, 1)
    assert np.degrees(np.arccos(cos)).mean() <= 0.5
    single = Segmenter.from_checkpoint(ckpt)(images[0])
    assert single.labels.shape == (1, 37, 50)
    np.testing.assert_array_equal(single.labels[0], a.labels[0])


def test_segmenter_fixed_to_a_frame_size_matches_the_dynamic_session(joint_files) -> None:
    _, onnx_path = joint_files
    images = _images(2)
    dynamic = Segmenter.from_onnx(onnx_path, providers=["CPUExecutionProvider"], frame_size=None)(
        images[:1]
    )
    fixed = Segmenter.from_onnx(
        onnx_path, providers=["CPUExecutionProvider"], frame_size=(37, 50), threads=1
    )
    got = fixed(images[:1])
    np.testing.assert_allclose(got.probabilities, dynamic.probabilities, atol=1e-5)
    np.testing.assert_array_equal(got.labels, dynamic.labels)
    with pytest.raises(GeosegError, match="size 1 in dim 0"):  # fixed to one frame
        fixed(images)
    with pytest.raises(GeosegError, match="size 50 in dim 3"):
        fixed(_images(1, 37, 52))
    with pytest.raises(GeosegError, match="frame_size"):
        Segmenter.from_onnx(onnx_path, frame_size=(37,))
    default = Segmenter.from_onnx(onnx_path, providers=["CPUExecutionProvider"])  # "auto"
    np.testing.assert_allclose(default(images[:1]).probabilities, dynamic.probabilities, atol=1e-5)
    assert len(default.backend._fixed_sessions) == 1


def test_segmenter_uses_stored_normalization(joint_files) -> None:
    ckpt, onnx_path = joint_files
    assert Segmenter.from_checkpoint(ckpt).normalization == NORM
    assert Segmenter.from_onnx(onnx_path).normalization == NORM


def test_naive_checkpoint_segments_densely(tmp_path) -> None:
    torch.manual_seed(1)
    ckpt = save_model_checkpoint(get_model("naive_cnn"), tmp_path / "n.pt", model_name="naive_cnn")
    r = Segmenter.from_checkpoint(ckpt)(_images(1, 20, 9))
    assert r.probabilities.shape == (1, 8, 20, 9) and r.normals is None and r.features is None


def test_bad_images_raise(joint_files) -> None:
    seg = Segmenter.from_checkpoint(joint_files[0])
    with pytest.raises(GeosegError, match="uint8"):
        seg(np.zeros((8, 8, 3), np.float32))
    with pytest.raises(GeosegError, match="images"):
        seg(np.zeros((8, 8, 4), np.uint8))
    with pytest.raises(GeosegError, match="images"):
        seg(np.zeros((1, 8, 8, 2), np.uint8))
    with pytest.raises(GeosegError, match="too small"):  # one grey image, 6 pixels wide
        seg(np.zeros((8, 6), np.uint8))


def test_corrupt_and_mismatched_checkpoints_name_the_file(tmp_path) -> None:
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"\x00garbage" * 10)
    with pytest.raises(GeosegError, match="corrupt.pt"):
        Segmenter.from_checkpoint(corrupt)
    other = save_model_checkpoint(get_model("enet"), tmp_path / "other.pt", model_name="enet")
    payload = torch.load(other, weights_only=True)
    payload["model_name"] = "joint"
    torch.save(seal(payload), tmp_path / "mismatch.pt")
    with pytest.raises(GeosegError, match="mismatch.pt.*joint"):
        Segmenter.from_checkpoint(tmp_path / "mismatch.pt")
    payload["model_name"] = "unet"
    torch.save(seal(payload), tmp_path / "unknown.pt")
    with pytest.raises(GeosegError, match="unknown.pt.*known models"):
        load_model_checkpoint(tmp_path / "unknown.pt")
    torch.save({"weights": 1}, tmp_path / "nokeys.pt")
    with pytest.raises(GeosegError, match="nokeys.pt.*missing"):
        load_model_checkpoint(tmp_path / "nokeys.pt")
    with pytest.raises(GeosegError, match="absent.pt"):
        load_model_checkpoint(tmp_path / "absent.pt")


def test_onnx_that_is_not_a_segmenter(tmp_path) -> None:
    from geoseg.export import export_onnx

    class Head(torch.nn.Module):
        def forward(self, x):
            return {"embedding": x.mean((2, 3))}

    path = export_onnx(Head(), tmp_path / "head.onnx", example_inputs=torch.randn(1, 3, 8, 8))
    with pytest.raises(GeosegError, match="head.onnx.*not a segmentation"):
        Segmenter.from_onnx(path)


def test_normals_to_rgb() -> None:
    n = np.zeros((3, 2, 2), np.float32)
    n[2] = 1.0
    rgb = normals_to_rgb(n)
    assert rgb.shape == (2, 2, 3) and tuple(rgb[0, 0]) == (128, 128, 255)


def test_cli_infer_end_to_end(joint_files, tmp_path, capsys) -> None:
    ckpt, onnx_path = joint_files
    img = tmp_path / "frame.png"
    cv2.imwrite(str(img), _images(1, 24, 40)[0])
    for model, out in ((onnx_path, tmp_path / "onnx_out"), (ckpt, tmp_path / "ckpt_out")):
        assert main(["infer", str(img), "--model", str(model), "--out", str(out)]) == 0
        for suffix in ("labels", "overlay", "normals"):
            written = cv2.imread(str(out / f"frame_{suffix}.png"))
            assert written is not None and written.shape == (24, 40, 3), suffix
    a = cv2.imread(str(tmp_path / "onnx_out" / "frame_labels.png"))
    b = cv2.imread(str(tmp_path / "ckpt_out" / "frame_labels.png"))
    assert (a == b).all(-1).mean() >= 0.99
    assert (
        main(
            [
                "infer",
                str(tmp_path / "nope.png"),
                "--model",
                str(ckpt),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "nope.png" in capsys.readouterr().err


def test_cli_export_random_model_and_bad_checkpoint(tmp_path, capsys) -> None:
    out = tmp_path / "naive.onnx"
    assert (
        main(
            ["export", "--model", "naive_cnn", "--out", str(out), "--height", "16", "--width", "16"]
        )
        == 0
    )
    assert out.is_file() and "naive_cnn" in capsys.readouterr().out
    bad = tmp_path / "bad.pt"
    bad.write_text("nope")
    assert main(["export", "--checkpoint", str(bad), "--out", str(tmp_path / "x.onnx")]) == 2
    assert "bad.pt" in capsys.readouterr().err
    assert main(["export", "--model", "nonet", "--out", str(tmp_path / "y.onnx")]) == 2
    assert "known models" in capsys.readouterr().err


def test_one_reader_for_model_files_and_run_directories(tmp_path) -> None:
    """Inference and training read weights through geoseg.infer.read_model_state."""
    from geoseg.infer import read_model_state
    from geoseg.models.registry import get_model
    from training import common

    model = get_model("enet")
    save_model_checkpoint(model, tmp_path / "run" / "model.pt", model_name="enet")
    loaded, _ = load_model_checkpoint(tmp_path / "run")  # a run directory: its model.pt
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v)
    state, ckpt = common.load_state(tmp_path / "run", expected_model="enet")
    assert ckpt["model_name"] == "enet" and state.keys() == model.state_dict().keys()
    with pytest.raises(GeosegError, match="trunk_checkpoint: .*'enet'.*expected 'joint'"):
        common.load_state(tmp_path / "run", expected_model="joint", option="trunk_checkpoint")
    with pytest.raises(GeosegError, match="no model.pt, best.pt, last.pt"):
        read_model_state(tmp_path)
