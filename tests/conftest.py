"""Fixtures shared across the test folders.

``tiny_world_dict`` / ``make_tiny_world``: the tiny synthetic city most SLAM tests drive
through, as plain values (what a YAML preset holds) and as a
:class:`geoseg.synth.world.WorldConfig` factory with overrides
(``make_tiny_world(preset="dense_occlusion")``): a 2 x 2 block city ~140 m across with a short
terrain skirt, built in well under a second.

``enet_files``: an ENet ``model.pt`` and ``model.onnx`` with embedded SHA-256 digests, made from
the shipped ``seg`` weights without running the ONNX exporter (~20 s per ENet export): the
checkpoint is re-saved with :func:`geoseg.infer.save_model_checkpoint` and the shipped ONNX file
gets its ``geoseg.sha256`` metadata as :func:`geoseg.export.export_onnx` writes it.

``exported_model``: ``exported_model(name, **cfg)`` gives ``(model, path)``, a registry model
(``torch.manual_seed(0)``, eval mode) and its :func:`geoseg.export.export_onnx` file, exported
once per session (an ENet-sized export takes 20-40 s on 2 CPU cores) and shared by the tests
that read it. Tests must not change the model or the file (copy the file to change it).

``joint_files``: a joint checkpoint with non-default batch-norm statistics and its ONNX export
through ``geoseg export --checkpoint``, once per session.
"""

from __future__ import annotations

import copy
from pathlib import Path

import pytest

TINY_WORLD = {
    "seed": 5,
    "preset": "light",
    "blocks_x": 2,
    "blocks_y": 2,
    "block_size": 70.0,
    "node_jitter": 4.0,
    "removed_street_share": 0.0,
    "terrain": {"skirt": 60.0, "mesh_spacing": 6.0},
}


def tiny_world_config(**overrides):
    """The tiny city's :class:`WorldConfig`, with keys overridden."""
    from geoseg.config import from_dict
    from geoseg.synth.world import WorldConfig

    return from_dict(WorldConfig, {**copy.deepcopy(TINY_WORLD), **overrides})


@pytest.fixture(scope="session")
def tiny_world_dict() -> dict:
    """The tiny city's configuration as plain values (a fresh copy)."""
    return copy.deepcopy(TINY_WORLD)


@pytest.fixture(scope="session")
def make_tiny_world():
    """The :func:`tiny_world_config` factory (test modules cannot import conftest by name)."""
    return tiny_world_config


@pytest.fixture(scope="session")
def enet_files(tmp_path_factory) -> tuple[Path, Path]:
    import onnx

    from geoseg.export import DIGEST_PROP, META_PREFIX, onnx_content_sha256
    from geoseg.infer import load_model_checkpoint, save_model_checkpoint
    from geoseg.pretrained import pretrained_file

    root = tmp_path_factory.mktemp("enet_files")
    model, ckpt = load_model_checkpoint(pretrained_file("seg", "model.pt"))
    pt = save_model_checkpoint(
        model,
        root / "enet.pt",
        model_name="enet",
        model_config=ckpt.get("model_config") or {},
        normalization=ckpt.get("normalization"),
    )
    proto = onnx.load(str(pretrained_file("seg", "model.onnx")))
    entry = proto.metadata_props.add()
    entry.key = META_PREFIX + DIGEST_PROP
    entry.value = onnx_content_sha256(proto)
    onnx_path = root / "enet.onnx"
    onnx_path.write_bytes(proto.SerializeToString())
    return pt, onnx_path


@pytest.fixture(scope="session")
def exported_model(tmp_path_factory):
    """``exported_model(name, **cfg)``: ``(model, onnx_path)``, exported once per session."""
    import torch

    from geoseg.export import export_onnx
    from geoseg.models import get_model

    cache: dict = {}

    def get(name: str, **cfg):
        key = (name, repr(sorted(cfg.items())))
        if key not in cache:
            torch.manual_seed(0)
            model = get_model(name, **cfg).eval()
            path = tmp_path_factory.mktemp("onnx") / f"{name}.onnx"
            export_onnx(model, path, metadata={"model_name": name, "model_config": cfg})
            cache[key] = (model, path)
        return cache[key]

    return get


#: the normalisation stored with ``joint_files`` (not the default one; tests/geoseg/test_infer.py
#: checks it is read back)
JOINT_NORM = {"mean": [0.5, 0.4, 0.3], "std": [0.2, 0.25, 0.3]}


@pytest.fixture(scope="session")
def joint_files(tmp_path_factory) -> tuple[Path, Path]:
    """A joint checkpoint and its ONNX export (through `geoseg export --checkpoint`)."""
    import torch

    from geoseg.cli import main
    from geoseg.infer import save_model_checkpoint
    from geoseg.models import get_model

    root = tmp_path_factory.mktemp("joint")
    torch.manual_seed(0)
    model = get_model("joint", num_classes=8)
    model.train()
    model(torch.randn(2, 3, 32, 32))  # non-default BN statistics
    ckpt = save_model_checkpoint(
        model,
        root / "joint.pt",
        model_name="joint",
        model_config={"num_classes": 8},
        normalization=JOINT_NORM,
    )
    onnx_path = root / "joint.onnx"
    assert main(["export", "--checkpoint", str(ckpt), "--out", str(onnx_path)]) == 0
    return ckpt, onnx_path
