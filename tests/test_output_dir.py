"""geoseg.output_dir: commands write only into empty folders or their own, never delete others'."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from geoseg.errors import GeosegError, OutputError
from geoseg.output_dir import (
    MARKER,
    output_producer,
    prepare_output_dir,
    prepare_output_file,
    record_outputs,
    recorded_outputs,
    remove_outputs,
)


def test_new_and_empty_folders_are_accepted_and_marked(tmp_path: Path) -> None:
    out = prepare_output_dir(tmp_path / "a" / "b", producer="render")
    assert out.is_dir() and output_producer(out) == "render"
    (tmp_path / "empty").mkdir()
    assert output_producer(prepare_output_dir(tmp_path / "empty", producer="infer")) == "infer"
    # a second run of the same producer is welcome
    (out / "poses.csv").write_text("ours")
    assert prepare_output_dir(out, producer="render") == out


def test_a_folder_with_foreign_files_is_refused_and_left_untouched(tmp_path: Path) -> None:
    user = tmp_path / "photos"
    (user / "rgb").mkdir(parents=True)
    (user / "rgb" / "000007.png").write_bytes(b"user's")
    (user / "poses.csv").write_text("user's")
    with pytest.raises(GeosegError, match="--overwrite") as info:
        prepare_output_dir(user, producer="render")
    assert "poses.csv" in str(info.value) and "rgb/" in str(info.value)
    assert sorted(p.name for p in user.iterdir()) == ["poses.csv", "rgb"]
    # with overwrite: taken over, nothing deleted, and remove_outputs keeps what it did not record
    prepare_output_dir(user, producer="render", overwrite=True)
    record_outputs(user, ["rgb/000000.png"])
    (user / "rgb" / "000000.png").write_bytes(b"ours")
    removed = remove_outputs(user, ["rgb/000000.png", "rgb/000007.png", user / "poses.csv"])
    assert removed == [user / "rgb" / "000000.png"]
    assert (user / "rgb" / "000007.png").read_bytes() == b"user's"
    assert (user / "poses.csv").read_text() == "user's"
    assert recorded_outputs(user) == set()


def test_another_producers_folder_is_refused(tmp_path: Path) -> None:
    out = prepare_output_dir(tmp_path / "seq", producer="render")
    with pytest.raises(GeosegError, match="geoseg render"):
        prepare_output_dir(out, producer="infer")
    assert output_producer(prepare_output_dir(out, producer="infer", overwrite=True)) == "infer"


def test_nested_outputs_and_leftover_temporaries_are_not_foreign(tmp_path: Path) -> None:
    run = tmp_path / "run"
    prepare_output_dir(run / "encoder", producer="train")
    (run / ".last.pt.abcd1234.tmp").write_bytes(b"half")
    assert prepare_output_dir(run, producer="train") == run
    assert not (run / ".last.pt.abcd1234.tmp").exists()


def test_adopt_recognises_unmarked_earlier_outputs(tmp_path: Path) -> None:
    old = tmp_path / "old"
    old.mkdir()
    (old / "meta.json").write_text("{}")
    prepare_output_dir(old, producer="render", adopt=lambda p: (p / "meta.json").is_file())
    assert output_producer(old) == "render"


def test_files_and_unwritable_folders_are_output_errors(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match="is a file"):
        prepare_output_dir(blocker, producer="infer")
    with pytest.raises(OutputError, match="not writable"):
        prepare_output_dir(blocker / "sub", producer="infer")
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            with pytest.raises(OutputError, match="not writable"):
                prepare_output_dir(ro, producer="infer")
        finally:
            ro.chmod(0o700)


def test_record_outputs_needs_a_prepared_folder_inside_it(tmp_path: Path) -> None:
    with pytest.raises(GeosegError, match="prepare_output_dir"):
        record_outputs(tmp_path, ["x"])
    out = prepare_output_dir(tmp_path / "o", producer="render")
    with pytest.raises(GeosegError, match="not inside"):
        record_outputs(out, ["../x"])
    record_outputs(out, [out / "a.png", "b/c.png"])
    assert recorded_outputs(out) == {"a.png", "b/c.png"}
    assert json.loads((out / MARKER).read_text())["producer"] == "render"


def test_prepare_output_file(tmp_path: Path) -> None:
    with pytest.raises(OutputError, match="is a folder"):
        prepare_output_file(tmp_path)
    target = tmp_path / "new" / "model.onnx"
    assert prepare_output_file(target) == target and target.parent.is_dir()
    target.write_text("someone's")
    with pytest.raises(GeosegError, match="--overwrite"):
        prepare_output_file(target)
    assert prepare_output_file(target, owned=lambda p: True) == target
    assert prepare_output_file(target, overwrite=True) == target


def test_prepare_output_file_removes_leftovers_of_an_interrupted_write(tmp_path: Path) -> None:
    target = tmp_path / "model.onnx"
    leftover = tmp_path / ".model.onnx.ab12cd34.tmp"  # what a kill before the rename leaves
    unrelated = tmp_path / ".other.onnx.ab12cd34.tmp"
    leftover.write_bytes(b"half")
    unrelated.write_bytes(b"half")
    prepare_output_file(target)
    assert not leftover.exists() and unrelated.exists()
