"""A full disk (simulated by a file size limit) during every command that writes: a clear error
naming the file, no partial file, no temporary file left, and a re-run that completes.

Each case runs the command in a child process under ``RLIMIT_FSIZE`` (writes beyond the limit
fail with ``EFBIG``, as they fail with ``ENOSPC`` on a full disk), from torch's checkpoint
writer, OpenCV's PNG encoder, trimesh's mesh export and the ONNX exporter alike.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import geoseg
from geoseg.atomic import TEMP_PATTERN
from geoseg_cli.cli import main

ROOT = Path(geoseg.__file__).resolve().parent.parent
# ``geoseg ARGV`` (or, with ``--script FILE``, that Python file) under a file size limit
CHILD = """
import resource, signal, sys
limit = int(sys.argv[1])
from geoseg_cli.cli import main
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
if sys.argv[2] == "--script":
    exec(open(sys.argv[3]).read())
raise SystemExit(main(sys.argv[2:]))
"""


def _limited(limit: int, argv: list[str]) -> subprocess.CompletedProcess:
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    )
    return subprocess.run(
        [sys.executable, "-c", CHILD, str(limit), *argv],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


def _no_partial_files(folder: Path, limit: int) -> None:
    files = [p for p in folder.rglob("*") if p.is_file()]
    assert not [p for p in files if TEMP_PATTERN.match(p.name)], "temporary files left"
    assert not [p for p in files if p.stat().st_size == limit], "a file cut at the limit"


def _clean_error(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert "cannot write" in proc.stderr and "file too large" in proc.stderr, proc.stderr[-2000:]
    return proc.stderr


@pytest.fixture()
def tiny_world(tmp_path) -> Path:
    path = tmp_path / "world.yaml"
    path.write_text("seed: 4\npreset: light\nblocks_x: 1\nblocks_y: 1\n")
    return path


def test_render_on_a_full_disk(tmp_path, tiny_world) -> None:
    out = tmp_path / "seq"
    argv = ["render", "--config", str(tiny_world), "--out", str(out), "--frames", "2"]
    argv += ["--size", "32x24"]
    limit = 4000
    _clean_error(_limited(limit, argv))
    _no_partial_files(out, limit)
    assert not (out / "meta.json").exists()  # unfinished: the next run redoes it
    assert main(argv) == 0 and (out / "meta.json").is_file()


def test_training_on_a_full_disk(tmp_path) -> None:
    out = tmp_path / "run"
    snippet = (
        "import sys; sys.path.insert(0, {tests!r}); from tiny_run import tiny_cfg, tiny_run; "
        "from geoseg.errors import GeosegError\n"
        "try:\n    tiny_run(tiny_cfg({out!r}, epochs=1))\n"
        "except GeosegError as err:\n    print(f'error: {{err}}', file=sys.stderr); sys.exit(2)\n"
    ).format(tests=str(ROOT / "tests" / "training"), out=str(out))
    script = tmp_path / "train.py"
    script.write_text(snippet)
    limit = 6000
    proc = _limited(limit, ["--script", str(script)])
    err = _clean_error(proc)
    assert "last.pt" in err
    _no_partial_files(out, limit)
    assert not (out / "last.pt").exists()


def test_export_on_a_full_disk(tmp_path) -> None:
    out = tmp_path / "naive.onnx"
    argv = ["export", "--model", "naive_cnn", "--out", str(out), "--height", "16", "--width", "16"]
    limit = 100_000
    err = _clean_error(_limited(limit, argv))
    assert "naive.onnx" in err and not out.exists()
    _no_partial_files(tmp_path, limit)


def test_infer_on_a_full_disk(tmp_path) -> None:
    image = tmp_path / "in" / "street.png"
    image.parent.mkdir()
    rng = np.random.default_rng(0)
    cv2.imwrite(str(image), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    out = tmp_path / "out"
    limit = 2000
    err = _clean_error(_limited(limit, ["infer", str(image), "--out", str(out)]))
    assert str(out) in err and "file too large" in err  # names the file (the legend comes first)
    _no_partial_files(out, limit)
