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

The suite runs on pytest-xdist's workers (``-n``/``--dist loadfile`` in pyproject's addopts):
:func:`built_once` shares what several test files read between the workers, and the bad-input
suite's closing table (``tests/bad_inputs``) is gathered from the workers and printed here.
"""

from __future__ import annotations

import copy
import hashlib
import os
import shutil
import sys
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


def built_once(tmp_path_factory, name: str, build) -> Path:
    """The folder ``name``, filled by ``build(folder)`` once per test run: pytest-xdist's workers
    share it (the first one builds it under a file lock, the others wait and read it)."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # the run's folder, above the workers' own
    folder = base / f"shared-{name}"
    with FileLock(str(base / f"shared-{name}.lock")):
        if not (folder / ".built").is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            (folder / ".built").touch()
    return folder


@pytest.fixture(scope="session")
def exported_model(tmp_path_factory):
    """``exported_model(name, **cfg)``: ``(model, onnx_path)``, exported once per test run."""
    import torch

    from geoseg.export import export_onnx
    from geoseg.models import get_model

    cache: dict = {}

    def get(name: str, **cfg):
        key = (name, repr(sorted(cfg.items())))
        if key not in cache:
            torch.manual_seed(0)  # the same weights in every worker
            model = get_model(name, **cfg).eval()
            tag = name + (hashlib.sha256(key[1].encode()).hexdigest()[:12] if cfg else "")
            folder = built_once(
                tmp_path_factory,
                f"onnx-{tag}",
                lambda d: export_onnx(
                    model, d / f"{name}.onnx", metadata={"model_name": name, "model_config": cfg}
                ),
            )
            cache[key] = (model, folder / f"{name}.onnx")
        return cache[key]

    return get


#: the normalisation stored with ``joint_files`` (not the default one; tests/geoseg/test_infer.py
#: checks it is read back)
JOINT_NORM = {"mean": [0.5, 0.4, 0.3], "std": [0.2, 0.25, 0.3]}


def _build_joint_files(root: Path) -> None:
    import torch

    from geoseg.infer import save_model_checkpoint
    from geoseg.models import get_model
    from geoseg_cli.cli import main

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
    assert main(["export", "--checkpoint", str(ckpt), "--out", str(root / "joint.onnx")]) == 0


@pytest.fixture(scope="session")
def joint_files(tmp_path_factory) -> tuple[Path, Path]:
    """A joint checkpoint and its ONNX export (through `geoseg export --checkpoint`)."""
    root = built_once(tmp_path_factory, "joint", _build_joint_files)
    return root / "joint.pt", root / "joint.onnx"


def pytest_collection_modifyitems(config, items) -> None:
    """On pytest-xdist's workers, the files that hold ``slow`` tests go first (in their order):
    whole files are handed out in collection order, and the longest ones started last would
    leave one worker running them alone at the end."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        slow_files = {item.path for item in items if item.get_closest_marker("slow")}
        items.sort(key=lambda item: item.path not in slow_files)  # a stable sort


# ---------------------------------------------------------------- the bad-input suite's table

_WORKER_BAD_INPUTS: list[dict] = []  # the counts pytest-xdist's workers sent back


def _bad_input_counts() -> dict | None:
    """This process's counts of tests/bad_inputs (``harness``), or None when it ran none."""
    harness = sys.modules.get("harness")
    if harness is None or not hasattr(harness, "OUTCOMES"):
        return None
    return {
        "reported": list(harness.REPORTED),
        "table": {k: dict(v) for k, v in harness.OUTCOMES.items()},
        "generated": {k: dict(v) for k, v in harness.GENERATED.items()},
    }


def pytest_sessionfinish(session) -> None:
    workeroutput = getattr(session.config, "workeroutput", None)  # on a pytest-xdist worker
    counts = _bad_input_counts()
    if workeroutput is not None and counts:
        workeroutput["bad_inputs"] = counts


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error) -> None:
    counts = getattr(node, "workeroutput", {}).get("bad_inputs")
    if counts:
        _WORKER_BAD_INPUTS.append(counts)


def pytest_terminal_summary(terminalreporter) -> None:
    """The counts per command (tried; outcomes A-D, tests/bad_inputs/harness.py)."""
    from collections import Counter

    parts = [*_WORKER_BAD_INPUTS]
    if getattr(terminalreporter.config, "workeroutput", None) is None:
        parts.append(_bad_input_counts() or {})
    reported: list[str] = []
    merged: dict[str, dict[str, Counter]] = {"table": {}, "generated": {}}
    for part in parts:
        reported += [c for c in part.get("reported", []) if c not in reported]
        for kind, table in merged.items():
            for command, counts in part.get(kind, {}).items():
                table.setdefault(command, Counter()).update(counts)
    rows = []
    for command in reported:
        for kind in ("table", "generated"):
            c = merged[kind].get(command)
            if c:
                rows.append(
                    f"{command:<11} {kind:>9} {sum(c.values()):>5} {c['A']:>5} {c['B']:>3} "
                    f"{c['C']:>3} {c['D']:>3}"
                )
    if rows:
        terminalreporter.write_sep(
            "-",
            "bad inputs and faults tried (A clear error, B traceback, "
            "C silent wrong result, D data loss)",
        )
        terminalreporter.write_line(
            f"{'command':<11} {'':>9} {'tried':>5} {'A':>5} {'B':>3} {'C':>3} {'D':>3}"
        )
        for row in rows:
            terminalreporter.write_line(row)
