"""A render killed at any write, then run again: the second run completes and its outputs are
those of an uninterrupted render; nothing half-written survives."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import geoseg
from geoseg.atomic import TEMP_PATTERN
from geoseg_cli.cli import main

ROOT = Path(geoseg.__file__).resolve().parent.parent
# geoseg ARGV, SIGKILLed before (or after) the N-th rename onto a file named TARGET
CHILD = """
import os, signal, sys
from pathlib import Path
target, when, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
real, seen = os.replace, [0]
def replace(src, dst, *a, **k):
    hit = Path(dst).name == target
    if hit:
        seen[0] += 1
    if hit and seen[0] == n and when == "before":
        os.kill(os.getpid(), signal.SIGKILL)
    real(src, dst, *a, **k)
    if hit and seen[0] == n and when == "after":
        os.kill(os.getpid(), signal.SIGKILL)
os.replace = replace
from geoseg_cli.cli import main
raise SystemExit(main(sys.argv[4:]))
"""
COMPARED = ("rgb", "labels", "labels_color", "geometry", "gis", "poses.csv", "camera.json")


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("world") / "world.yaml"
    path.write_text("seed: 4\npreset: light\nblocks_x: 1\nblocks_y: 1\n")
    return path


def _argv(world: Path, out: Path) -> list[str]:
    return ["render", "--config", str(world), "--out", str(out), "--frames", "3", "--size", "32x24"]


@pytest.fixture(scope="module")
def reference(world, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ref") / "seq"
    assert main(_argv(world, out)) == 0
    return out


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for name in COMPARED
        for p in ([folder / name] if (folder / name).is_file() else (folder / name).rglob("*"))
        if p.is_file()
    }


@pytest.mark.parametrize(
    ("target", "when", "n"),
    [
        ("000001.png", "before", 1),
        ("000001.npz", "after", 1),
        ("gps.csv", "before", 1),
        ("meta.json", "before", 1),
    ],
)
def test_a_killed_render_is_redone_whole(tmp_path, world, reference, target, when, n) -> None:
    out = tmp_path / "seq"
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    )
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, target, when, str(n), *_argv(world, out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert not (out / "meta.json").exists()  # an unfinished render is recognisable
    assert main(_argv(world, out)) == 0
    assert _files(out) == _files(reference)
    assert not [p for p in out.rglob("*") if TEMP_PATTERN.match(p.name)]


def test_a_shorter_rerender_removes_only_its_own_stale_frames(tmp_path, world) -> None:
    out = tmp_path / "seq"
    assert main(_argv(world, out)) == 0
    (out / "rgb" / "000009.png").write_bytes(b"a user's picture")  # not the render's
    assert main([*_argv(world, out)[:-4], "--frames", "1", "--size", "32x24"]) == 0
    assert not (out / "rgb" / "000002.png").exists()  # the render's own stale frame
    assert (out / "rgb" / "000009.png").read_bytes() == b"a user's picture"


def test_a_render_folder_from_before_markers_is_adopted(tmp_path, world) -> None:
    out = tmp_path / "seq"
    assert main(_argv(world, out)) == 0
    (out / ".geoseg-output.json").unlink()
    assert main([*_argv(world, out), "--force"]) == 0
