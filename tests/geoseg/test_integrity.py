"""Corrupted weights never load: every weights file carries a SHA-256 checked on load.

The class of fault: bytes flipped on disk in a ``.pt``, ``.onnx`` or filter JSON still load in
torch / onnxruntime and give a silently different network. Each file kind, and each command
that reads one, must refuse it with a message naming the file.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from geoseg.dirichlet import DirichletFilter, load_filter
from geoseg.errors import GeosegError
from geoseg.export import OnnxModel, verify_onnx_file
from geoseg.infer import Segmenter, load_model_checkpoint
from geoseg.integrity import content_sha256, read_torch_file, seal
from geoseg.pretrained import PRETRAINED, USER_ONLY, WEIGHTS_DIR
from geoseg_cli.cli import main
from training.checkpoint import build_checkpoint, load_checkpoint, save_checkpoint


def flip_bytes(path: Path, n: int = 64, seed: int = 0, lo: float = 0.3, hi: float = 0.7) -> None:
    """Flip ``n`` random bytes in the middle of a file (where its weights are)."""
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(seed)
    for i in rng.choice(np.arange(int(lo * len(data)), int(hi * len(data))), n, replace=False):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def files(enet_files, tmp_path_factory):
    root = tmp_path_factory.mktemp("weights")
    pt, onnx_path = enet_files
    model, _ = load_model_checkpoint(pt)
    opt = torch.optim.Adam(model.parameters())
    last = save_checkpoint(build_checkpoint(model, optimizer=opt, epoch=1), root / "last.pt")
    return root, pt, onnx_path, last


def _copy(src: Path, dst_dir: Path) -> Path:
    dst = dst_dir / src.name
    shutil.copyfile(src, dst)
    return dst


def test_intact_files_verify(files) -> None:
    _, pt, onnx_path, last = files
    assert read_torch_file(pt)["sha256"] == content_sha256(torch.load(pt, weights_only=True))
    verify_onnx_file(onnx_path)
    assert load_checkpoint(last)["epoch"] == 1


@pytest.mark.parametrize("kind", ["model", "checkpoint", "onnx"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_flipped_bytes_are_refused_naming_the_file(files, tmp_path, kind, seed) -> None:
    src = {"model": files[1], "checkpoint": files[3], "onnx": files[2]}[kind]
    bad = _copy(src, tmp_path)
    flip_bytes(bad, seed=seed)
    with pytest.raises(GeosegError, match=rf"{bad.name}.*(corrupt|not a valid|truncated)"):
        if kind == "model":
            load_model_checkpoint(bad)
        elif kind == "checkpoint":
            load_checkpoint(bad)
        else:
            OnnxModel(bad, providers=["CPUExecutionProvider"])


def test_commands_refuse_corrupt_weights_and_write_nothing(files, tmp_path, capsys) -> None:
    _, pt, onnx_path, _ = files
    bad_pt, bad_onnx = _copy(pt, tmp_path), _copy(onnx_path, tmp_path)
    flip_bytes(bad_pt)
    flip_bytes(bad_onnx)
    out = tmp_path / "exported.onnx"
    assert main(["export", "--checkpoint", str(bad_pt), "--out", str(out)]) == 2
    assert bad_pt.name in capsys.readouterr().err and not out.exists()
    image = tmp_path / "in.png"
    import cv2

    cv2.imwrite(str(image), np.zeros((16, 16, 3), np.uint8))
    for model in (bad_pt, bad_onnx):
        assert main(["infer", str(image), "--model", str(model), "--out", str(tmp_path / "o")]) == 2
        assert "corrupt" in capsys.readouterr().err


def test_filter_json_carries_and_checks_its_digest(tmp_path) -> None:
    alpha = np.linspace(0.5, 3.0, 8)
    f = DirichletFilter(alpha=alpha)
    f.threshold = 1.5
    path = f.save(tmp_path / "dirichlet.json")
    data = json.loads(path.read_text())
    assert data["sha256"] == content_sha256(data)
    data["alpha"][0] += 1e-9  # a valid value, but not the one written
    path.write_text(json.dumps(data))
    with pytest.raises(GeosegError, match="dirichlet.json.*corrupt"):
        load_filter(path)


def test_files_without_a_digest_load_with_a_warning_or_check_the_card(files, tmp_path, caplog):
    _, pt, onnx_path, _ = files
    legacy = tmp_path / "model.pt"
    payload = torch.load(pt, weights_only=True)
    payload.pop("sha256")
    torch.save(payload, legacy)
    with caplog.at_level(logging.WARNING, logger="geoseg.integrity"):
        load_model_checkpoint(legacy)
    assert "no SHA-256 recorded" in caplog.text
    # with a model card next to it, the card's digest is checked
    from geoseg.integrity import file_sha256

    card = tmp_path / "model_card.json"
    card.write_text(json.dumps({"sha256": {"model.pt": file_sha256(legacy)}}))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="geoseg.integrity"):
        load_model_checkpoint(legacy)
    assert "no SHA-256" not in caplog.text
    card.write_text(json.dumps({"sha256": {"model.pt": "0" * 64}}))
    with pytest.raises(GeosegError, match="model.pt.*corrupt.*model_card.json"):
        load_model_checkpoint(legacy)


@pytest.mark.parametrize("name", sorted(set(PRETRAINED) - USER_ONLY))  # every shipped name
def test_shipped_weights_are_recorded_in_their_cards_and_a_corrupt_copy_is_refused(name, tmp_path):
    folder = WEIGHTS_DIR / name
    card = json.loads((folder / "model_card.json").read_text())
    files = sorted(card["sha256"])
    assert files, name
    copy = tmp_path / name
    shutil.copytree(folder, copy)
    target = copy / files[0]
    if target.suffix == ".json":  # a digit changed: still valid JSON, still a valid filter
        text = target.read_text()
        i = text.index('"threshold": ') + len('"threshold": ') + 3
        target.write_text(text[:i] + str((int(text[i]) + 1) % 10) + text[i + 1 :])
    else:
        flip_bytes(target, n=4)
    with pytest.raises(GeosegError, match="corrupt"):
        if target.suffix == ".pt":
            load_model_checkpoint(target)
        elif target.suffix == ".onnx":
            verify_onnx_file(target)
        else:
            load_filter(target)


def test_seal_ignores_its_own_key_and_sees_every_change() -> None:
    payload = seal({"a": [1, 2.5, None], "t": torch.arange(4.0), "k": {3: "x"}})
    again = seal(payload)
    assert again["sha256"] == payload["sha256"]
    for change in ({"a": [1, 2.5]}, {"t": torch.arange(4.0) + 1e-6}, {"k": {3: "y"}}):
        assert seal({**payload, **change})["sha256"] != payload["sha256"]
    assert seal({"x": 1})["sha256"] != seal({"x": 1.0})["sha256"]  # types count


def test_segmenter_checks_onnx_too(files, tmp_path) -> None:
    bad = _copy(files[2], tmp_path)
    flip_bytes(bad, seed=5)
    with pytest.raises(GeosegError, match=rf"{bad.name}.*corrupt"):
        Segmenter.from_onnx(bad)


@pytest.mark.parametrize("name", sorted({n for n in set(PRETRAINED) - USER_ONLY
                                         if (WEIGHTS_DIR / n / "model.onnx").is_file()}))  # fmt: skip
def test_a_shipped_onnx_copy_verifies_on_its_own(name, tmp_path):
    """Copied away from its model card, a shipped ONNX file still verifies: its digest is in
    its own metadata, so flipped weights are refused, not loaded with a warning."""
    copy = _copy(WEIGHTS_DIR / name / "model.onnx", tmp_path)
    verify_onnx_file(copy)
    flip_bytes(copy, n=4)
    with pytest.raises(GeosegError, match="corrupt.*metadata"):
        verify_onnx_file(copy)
