"""Output folders: a command writes only into a folder that is empty or already its own.

Every command that writes into a folder (``geoseg render --out DIR``, ``train``, ``infer``,
``demo``, ...) starts with :func:`prepare_output_dir`. It creates the folder, checks that it can
be written, and refuses (:class:`~geoseg.errors.GeosegError`) a folder that holds files this
producer did not write, unless the caller passes ``overwrite=True`` (the commands' ``--overwrite``).
It marks the folder as the producer's with a small JSON file, :data:`MARKER`::

    {"format": "geoseg-output", "version": 1, "producer": "render", "files": [...]}

``files`` lists what the producer recorded with :func:`record_outputs`; :func:`remove_outputs`
deletes only recorded files, so nothing geoseg did not write is ever deleted, even with
``overwrite``. Leftover temporary files of interrupted atomic writes are removed at the start
(:func:`geoseg.atomic.clean_temp_files`).

Typical use in a command::

    out = prepare_output_dir(args.out, producer="render", overwrite=args.overwrite)
    record_outputs(out, ["poses.csv", "rgb/000000.png"])   # before (or while) writing them
    ...
    remove_outputs(out, stale_names)                        # never touches unrecorded files

A subfolder holding its own marker is another geoseg output (e.g. a training run's encoder
stage) and counts as geoseg's, not as a foreign file. Folders written by geoseg versions that
had no marker can be adopted through ``adopt``, a test of the producer's own signature files.

Single output files (``geoseg export --out FILE.onnx``, ``localize --out FILE.json``) go
through :func:`prepare_output_file`.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from geoseg.atomic import TEMP_PATTERN, atomic_write, clean_temp_files, write_error
from geoseg.errors import GeosegError, OutputError

logger = logging.getLogger(__name__)

MARKER = ".geoseg-output.json"
FORMAT = "geoseg-output"
FORMAT_VERSION = 1
_WRITE_TEST_PREFIX = ".geoseg-write-test-"


def ensure_writable_dir(path: str | os.PathLike, *, option: str = "--out") -> Path:
    """Create ``path`` (and parents) and check that a file can be written there.

    Raises:
        OutputError: ``path`` is a file, or cannot be created or written (names the option,
            the folder and the cause).
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{option}: {path} is a file, not a folder; choose a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=_WRITE_TEST_PREFIX):
            pass
    except OSError as err:
        raise OutputError(
            f"{option}: output folder {path} is not writable: {err.strerror or err}; "
            "choose a folder you can write to",
            errno=err.errno,
        ) from None
    return path


def read_marker(path: str | os.PathLike) -> dict[str, Any] | None:
    """The marker of folder ``path`` (None when it has none or it is unreadable)."""
    file = Path(path) / MARKER
    if not file.is_file():
        return None
    try:
        data = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        logger.warning("%s: unreadable output marker; the folder counts as foreign", file)
        return None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        return None
    return data


def output_producer(path: str | os.PathLike) -> str | None:
    """The producer recorded in folder ``path`` (None: not a geoseg output folder)."""
    marker = read_marker(path)
    return None if marker is None else str(marker.get("producer"))


def _write_marker(path: Path, producer: str, files: Iterable[str]) -> None:
    from geoseg import __version__

    doc = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "producer": producer,
        "geoseg": __version__,
        "files": sorted(set(files)),
    }
    atomic_write(path / MARKER, json.dumps(doc, indent=1) + "\n", fsync=False)


def _foreign_entries(path: Path) -> list[str]:
    """Top-level entries of ``path`` that are not geoseg's: not the marker, not a leftover
    temporary file, not a subfolder that is itself a geoseg output."""
    out = []
    for entry in sorted(path.iterdir()):
        name = entry.name
        if name == MARKER or TEMP_PATTERN.match(name) or name.startswith(_WRITE_TEST_PREFIX):
            continue
        if entry.is_dir() and not entry.is_symlink() and read_marker(entry) is not None:
            continue
        out.append(name + ("/" if entry.is_dir() else ""))
    return out


def prepare_output_dir(
    path: str | os.PathLike,
    *,
    producer: str,
    overwrite: bool = False,
    option: str = "--out",
    adopt: Callable[[Path], bool] | None = None,
) -> Path:
    """Make ``path`` ready for ``producer``'s outputs, or refuse it.

    Accepted: a missing or empty folder; a folder marked by ``producer``; a folder without a
    marker that ``adopt`` recognises as an earlier output of ``producer``. Anything else
    (files geoseg did not write, or another producer's outputs) is refused unless
    ``overwrite``; then the folder is taken over, files of the same names are replaced as they
    are written, and nothing else is deleted.

    Args:
        path: the output folder (created with its parents).
        producer: who writes there, e.g. ``"render"``, ``"train"``, ``"slam run"``.
        overwrite: accept a folder holding other files.
        option: the option that named the folder, for messages (``"--out"``, ``"out_dir"``).
        adopt: ``adopt(folder) -> bool``: True when an unmarked folder is an earlier output
            of ``producer`` (written before markers existed).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        GeosegError: the folder holds files ``producer`` did not write (names a few and says
            to pass ``--overwrite`` or choose another folder).
        OutputError: ``path`` is a file, or the folder cannot be created or written.
    """
    path = Path(path)
    existed = path.is_dir()
    ensure_writable_dir(path, option=option)
    clean_temp_files(path)
    marker = read_marker(path)
    files: list[str] = [] if marker is None else list(marker.get("files") or [])
    if marker is not None and marker.get("producer") == producer:
        return path
    foreign: list[str] = []
    if marker is not None:
        foreign = [f"the outputs of `geoseg {marker.get('producer')}`"]
    elif existed:
        foreign = _foreign_entries(path)
        if foreign and adopt is not None and adopt(path):
            logger.info("%s: adopted as an earlier output of %s", path, producer)
            foreign = []
    if foreign and not overwrite:
        shown = ", ".join(foreign[:5]) + (
            f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
        )
        raise GeosegError(
            f"{option}: {path} holds files geoseg {producer} did not write ({shown}); choose "
            "another folder, or pass --overwrite to write there anyway (files of the same "
            "names are replaced; nothing else is deleted)"
        )
    if foreign:
        logger.warning(
            "%s: writing into a folder that holds other files (%s); they are kept",
            path,
            ", ".join(foreign[:5]),
        )
    try:
        _write_marker(path, producer, files)
    except OSError as err:
        raise write_error(path / MARKER, err, what=option) from err
    return path


def record_outputs(path: str | os.PathLike, files: Iterable[str | os.PathLike]) -> None:
    """Record ``files`` (relative to folder ``path``, or absolute inside it) as written by the
    folder's producer, so that :func:`remove_outputs` may delete them later.

    Raises:
        GeosegError: ``path`` was not prepared by :func:`prepare_output_dir`, or a file lies
            outside it.
    """
    path = Path(path)
    marker = read_marker(path)
    if marker is None:
        raise GeosegError(f"{path}: not an output folder (call prepare_output_dir first)")
    names = set(marker.get("files") or [])
    names.update(_relative(path, f) for f in files)
    _write_marker(path, str(marker.get("producer")), names)


def recorded_outputs(path: str | os.PathLike) -> set[str]:
    """The files recorded in folder ``path`` (relative POSIX paths; empty when unmarked)."""
    marker = read_marker(path)
    return set() if marker is None else set(marker.get("files") or [])


def remove_outputs(path: str | os.PathLike, files: Iterable[str | os.PathLike]) -> list[Path]:
    """Delete those of ``files`` that the folder's producer recorded; keep (and log) the others.

    Returns:
        The deleted files.
    """
    path = Path(path)
    recorded = recorded_outputs(path)
    removed, kept = [], []
    for f in files:
        rel = _relative(path, f)
        target = path / rel
        if not target.is_file():
            continue
        if rel in recorded:
            target.unlink()
            removed.append(target)
        else:
            kept.append(rel)
    if kept:
        logger.warning(
            "%s: kept %d file(s) geoseg did not write (%s)", path, len(kept), ", ".join(kept[:5])
        )
    if removed:
        record = set(recorded) - {_relative(path, f) for f in removed}
        _write_marker(path, output_producer(path) or "geoseg", record)
    return removed


def prepare_output_file(
    path: str | os.PathLike,
    *,
    option: str = "--out",
    overwrite: bool = False,
    owned: Callable[[Path], bool] | None = None,
) -> Path:
    """Check that a single output file can be written at ``path`` (its folder is created).

    An existing file is replaced only when ``owned(path)`` says geoseg wrote it (e.g. an ONNX
    file with geoseg metadata), or with ``overwrite``. Temporary files an interrupted earlier
    write of ``path`` left are removed.

    Raises:
        GeosegError: ``path`` is a folder, or an existing file geoseg did not write (without
            ``overwrite``).
        OutputError: its folder cannot be created or written.
    """
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{option}: {path} is a folder; give a file name")
    ensure_writable_dir(path.parent, option=option)
    for leftover in path.parent.glob(f".{path.name}.*.tmp"):  # of an interrupted earlier write
        if TEMP_PATTERN.match(leftover.name) and leftover.is_file():
            leftover.unlink()
    if path.exists() and not overwrite and not (owned is not None and owned(path)):
        raise GeosegError(
            f"{option}: {path} exists and was not written by geoseg; choose another name or "
            "pass --overwrite to replace it"
        )
    return path


def _relative(root: Path, file: str | os.PathLike) -> str:
    f = Path(file)
    if f.is_absolute():
        for base in (root, root.resolve()):
            try:
                f = f.relative_to(base)
                break
            except ValueError:
                continue
        else:
            raise GeosegError(f"{file}: not inside the output folder {root}")
    rel = f.as_posix()
    if rel == ".." or rel.startswith("../"):
        raise GeosegError(f"{file}: not inside the output folder {root}")
    return rel
