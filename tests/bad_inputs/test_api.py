"""Public Python entries on bad inputs: a GeosegError naming the problem, never a traceback
from inside NumPy, torch or onnxruntime, never a silently accepted value, never a changed input.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from harness import OUTCOMES, Env, snapshot, user_folder


def _api_cases():
    """``(id, call(env), words)``: public library entries on bad inputs."""
    from geoseg.atomic import atomic_write
    from geoseg.config import load_config
    from geoseg.dirichlet import load_filter
    from geoseg.export import OnnxModel
    from geoseg.infer import Segmenter, load_model_checkpoint
    from geoseg.models.registry import get_model as build
    from geoseg.output_dir import prepare_output_dir
    from geoseg.reloc.essential_baseline import estimate_relative_pose
    from geoseg.reloc.image_base import load_image_base, read_camera
    from geoseg.reloc.retrieval import (
        RetrievalIndex,
        fuse_gps_distance,
        intersect_rays,
        locate_from_ranged_rays,
    )
    from geoseg.reloc.route_filter import RouteFilter
    from geoseg.synth.export import render_sequence
    from geoseg.synth.world import WorldConfig
    from slam_bridge.testing.bal import read_bal
    from training.checkpoint import load_checkpoint
    from training.config import TrainConfig

    def write(e: Env, name: str, data: bytes | str) -> Path:
        path = e.root / "api" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data.encode() if isinstance(data, str) else data)
        return path

    def filter_with(e: Env, **changes) -> Path:
        doc = json.loads((e.inputs / "dirichlet.json").read_text())
        doc.pop("sha256")
        doc.update(changes)
        return write(e, "filter.json", json.dumps(doc))

    seg = lambda e: Segmenter.from_onnx(e.onnx)  # noqa: E731
    eye = np.eye(3)
    # fmt: off
    return [
        ("load_filter-nan-threshold", lambda e: load_filter(filter_with(e, threshold=math.nan)), "threshold"),
        ("load_filter-inf-threshold", lambda e: load_filter(filter_with(e, threshold=math.inf)), "threshold"),
        ("load_filter-window-float", lambda e: load_filter(filter_with(e, window=8.9)), "window"),
        ("load_filter-classes-bool", lambda e: load_filter(filter_with(e, num_classes=True)), "num_classes"),
        ("load_filter-window-string", lambda e: load_filter(filter_with(e, window="8")), "window"),
        ("load_filter-nan-calibration", lambda e: load_filter(filter_with(e, calibration=[0.0, math.nan])), "calibration"),
        ("read_bal-negative", lambda e: read_bal(write(e, "neg.txt", "-2 1 1\n")), "negative"),
        ("read_bal-trailing", lambda e: read_bal(write(e, "t.txt", "0 1 0\n1 2 3\n4\n")), "trailing"),
        ("read_bal-binary", lambda e: read_bal(write(e, "b.txt", bytes(range(256)))), "binary"),
        ("read_bal-bad-bz2", lambda e: read_bal(write(e, "c.bz2", b'BZh9' + b'\x00' * 30)), "corrupt"),
        ("load_checkpoint-text", lambda e: load_checkpoint(e.inputs / "text.pt"), "text file"),
        ("load_checkpoint-model-file", lambda e: load_checkpoint(e.pt), "not a geoseg checkpoint"),
        ("load_model_checkpoint-corrupt", lambda e: load_model_checkpoint(e.inputs / "corrupt.pt"), "corrupt"),
        ("OnnxModel-unknown-provider", lambda e: OnnxModel(e.onnx, providers=["TPU"]), "unknown"),
        ("OnnxModel-threads-negative", lambda e: OnnxModel(e.onnx, threads=-3), "threads"),
        ("Segmenter-1x1", lambda e: seg(e)(np.zeros((1, 1, 3), np.uint8)), "too small"),
        ("Segmenter-float-image", lambda e: seg(e)(np.zeros((16, 16, 3), np.float32)), "uint8"),
        ("RouteFilter-nan-position", lambda e: RouteFilter([[0.0, math.nan]]), "positions"),
        ("RouteFilter-sigma-0", lambda e: RouteFilter([[0.0, 0.0], [5.0, 0.0]]).filter(np.ones((1, 2)), gps=[[0.0, 0.0]], gps_sigma_m=0.0), "gps_sigma_m"),
        ("RetrievalIndex-nan", lambda e: RetrievalIndex([[0.0, math.nan]]), "embeddings"),
        ("RetrievalIndex-k-0", lambda e: RetrievalIndex([[0.0, 1.0]]).query([[0.0, 1.0]], k=0), "k"),
        ("intersect_rays-one-ray", lambda e: intersect_rays([[0.0, 0, 0]], [[1.0, 0, 0]]), "2 rays"),
        ("intersect_rays-zero-direction", lambda e: intersect_rays([[0.0, 0, 0], [1, 0, 0]], [[0.0, 0, 0], [1, 0, 0]]), "zero"),
        ("ranged-rays-range-0", lambda e: locate_from_ranged_rays([[0.0, 0, 0]], [[1.0, 0, 0]], [0.0]), "ranges"),
        ("fuse_gps_distance-negative", lambda e: fuse_gps_distance([-1.0], [2.0], relative_sigma=0.3, gps_sigma_m=2.0), "positive"),
        ("load_image_base-missing", lambda e: load_image_base(e.inputs / "nobase"), "nobase"),
        ("read_camera-list", lambda e: read_camera(write(e, "camera.json", "[1, 2]")), "JSON object"),
        ("estimate_relative_pose-sizes", lambda e: estimate_relative_pose(np.zeros((48, 64, 3), np.uint8), np.zeros((96, 128, 3), np.uint8), eye), "one K"),
        ("render_sequence-frames-0", lambda e: render_sequence(WorldConfig(), e.out("api_r"), frames=0), "frames"),
        ("render_sequence-fps-nan", lambda e: render_sequence(WorldConfig(), e.out("api_r"), fps=math.nan), "fps"),
        ("render_sequence-size-0", lambda e: render_sequence(WorldConfig(), e.out("api_r"), image_size=(0, 0)), "size"),
        ("render_sequence-user-folder", lambda e: render_sequence(WorldConfig(), user_folder(e, "api_user")), "--overwrite"),
        ("load_config-nan", lambda e: load_config(TrainConfig, {"optim": {"lr": math.nan}}), "optim.lr"),
        ("load_config-unknown", lambda e: load_config(TrainConfig, {"optim": {"lrr": 1}}), "optim.lrr"),
        ("prepare_output_dir-file", lambda e: prepare_output_dir(e.inputs / "notes.txt", producer="x"), "is a file"),
        ("get_model-bad-option", lambda e: build("enet", num_classes=2.5), "num_classes"),
        ("WorldConfig-seed-negative", lambda e: WorldConfig(seed=-1), "seed"),
        ("atomic_write-folder-in-the-way", lambda e: atomic_write(e.inputs / "a", b'x'), "folder is in the way"),
    ]
    # fmt: on


API_CASES = _api_cases()


@pytest.mark.parametrize("case", API_CASES, ids=[c[0] for c in API_CASES])
def test_python_entries_on_bad_inputs(case, env: Env) -> None:
    from geoseg.errors import GeosegError

    name, call, words = case
    before = snapshot(env.inputs)
    try:
        call(env)
    except GeosegError as err:
        outcome = "A" if words in str(err) else "C"
        detail = str(err)
    except Exception as exc:  # noqa: BLE001 - a traceback from inside a library
        outcome, detail = "B", f"{type(exc).__name__}: {exc}"
    else:
        outcome, detail = "C", "accepted"
    if snapshot(env.inputs) != before:
        outcome = "D"
    OUTCOMES["python API"][outcome] += 1
    assert outcome == "A", f"{name}: {outcome}: {detail} (expected the words {words!r})"
