"""geoseg.atomic: whole-or-nothing writes with the permissions open() would give."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from geoseg.atomic import atomic_output


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
    with pytest.raises(FileNotFoundError), atomic_output(tmp_path / "nope" / "x"):
        pass
