"""Fixtures shared across the test folders.

``enet_files``: an ENet ``model.pt`` and ``model.onnx`` with embedded SHA-256 digests, made from
the shipped ``seg`` weights without running the ONNX exporter (~20 s per ENet export): the
checkpoint is re-saved with :func:`geoseg.infer.save_model_checkpoint` and the shipped ONNX file
gets its ``geoseg.sha256`` metadata as :func:`geoseg.export.export_onnx` writes it.
"""

from __future__ import annotations

from pathlib import Path

import pytest


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
