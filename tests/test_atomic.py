"""geoseg.atomic: whole-or-nothing writes with the permissions open() would give."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

import pytest

from geoseg.atomic import atomic_output, atomic_write, clean_temp_files
from geoseg.errors import OutputError


def test_written_file_has_umask_permissions_not_mkstemp_0600(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        path = tmp_path / "model.onnx"
        with atomic_output(path) as handle:
            handle.write(b"\x00\x01")
    finally:
        os.umask(old)
    assert path.read_bytes() == b"\x00\x01"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644


def test_text_mode_replaces_existing_file(tmp_path: Path) -> None:
    path = tmp_path / "filter.json"
    path.write_text("old")
    with atomic_output(path, "w") as handle:
        handle.write('{"alpha": [1.5]}')
    assert path.read_text() == '{"alpha": [1.5]}'
    assert [p.name for p in tmp_path.iterdir()] == ["filter.json"]


def test_failure_keeps_old_file_and_removes_temporary(tmp_path: Path) -> None:
    path = tmp_path / "last.pt"
    path.write_bytes(b"previous")
    with pytest.raises(RuntimeError, match="crash"), atomic_output(path) as handle:
        handle.write(b"half of the new")
        raise RuntimeError("crash while writing")
    assert path.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


def test_bad_mode_and_missing_folder_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="mode"), atomic_output(tmp_path / "x", "a"):
        pass
    with pytest.raises(OutputError, match="folder does not exist") as info:
        with atomic_output(tmp_path / "nope" / "x"):
            pass
    assert isinstance(info.value, OSError) and "nope" in str(info.value)


def test_a_folder_in_the_way_is_an_output_error(tmp_path: Path) -> None:
    (tmp_path / "model.onnx").mkdir()
    with pytest.raises(OutputError, match="model.onnx"):
        atomic_write(tmp_path / "model.onnx", b"x")
    assert [p.name for p in tmp_path.iterdir()] == ["model.onnx"]


@pytest.mark.parametrize(
    ("code", "words"),
    [(errno.ENOSPC, "no space left"), (errno.EROFS, "read-only"), (errno.EACCES, "permission")],
)
def test_failed_writes_name_the_file_and_the_cause(
    tmp_path: Path, monkeypatch, code, words
) -> None:
    path = tmp_path / "metrics.json"
    path.write_text("old")

    def fail(fd):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OutputError, match=words) as info:
        atomic_write(path, "new")
    assert str(path) in str(info.value) and info.value.errno == code
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["metrics.json"]


def test_clean_temp_files_removes_only_leftovers_of_atomic_writes(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    leftovers = [tmp_path / ".last.pt.k2j4_x9a.tmp", tmp_path / "sub" / ".a.png.abcdefgh.tmp"]
    kept = [tmp_path / "notes.tmp", tmp_path / ".hidden.tmp", tmp_path / "last.pt"]
    for f in leftovers + kept:
        f.write_text("x")
    assert sorted(clean_temp_files(tmp_path)) == sorted(leftovers)
    assert all(f.exists() for f in kept) and not any(f.exists() for f in leftovers)
