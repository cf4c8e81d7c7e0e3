"""Atomic file writes: a temporary file in the target's folder, flushed, then renamed over it.

Every file geoseg writes that a crash must not truncate (checkpoints, ONNX models, filters,
caches, frames, tables, figures) goes through :func:`atomic_output` or :func:`atomic_write`: a
reader sees the old file or the complete new one, never half of it, and a failed write leaves
the old file untouched and no temporary behind. A write that fails (full disk, read-only
folder, a folder in the way) raises :class:`~geoseg.errors.OutputError`, which names the file,
the cause and what to do.

A process killed between the temporary write and the rename leaves its temporary file
(``.NAME.XXXXXXXX.tmp``, :data:`TEMP_PATTERN`); :func:`clean_temp_files` removes such
leftovers, and every stage that writes into a folder calls it when it starts
(:func:`geoseg.output_dir.prepare_output_dir`).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from geoseg.errors import GeosegError, OutputError

logger = logging.getLogger(__name__)

# ".last.pt.k2j4_x9a.tmp": the names tempfile.mkstemp gives with the prefix and suffix below.
TEMP_PATTERN = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp$")

_CAUSES = {
    errno.ENOSPC: ("no space left on device", "free some space or choose another folder"),
    errno.EDQUOT: ("disk quota exceeded", "free some space or choose another folder"),
    errno.EFBIG: ("file too large (file system or process limit)", "choose another folder"),
    errno.EACCES: ("permission denied", "choose a folder you can write to"),
    errno.EPERM: ("permission denied", "choose a folder you can write to"),
    errno.EROFS: ("read-only file system", "choose a folder you can write to"),
    errno.EISDIR: ("a folder is in the way", "remove it or choose another name"),
    errno.ENOTDIR: ("a file is in the way of a folder", "remove it or choose another path"),
    errno.ENOENT: ("the folder does not exist", "create it or choose another path"),
    errno.EIO: ("the write failed", "check the disk (full, or a file size limit?)"),
}


def describe_os_error(err: OSError) -> tuple[str, str]:
    """``(cause, what to do)`` in words for an ``OSError`` of a write."""
    cause, todo = _CAUSES.get(err.errno or -1, (None, "check the path and the disk"))
    return cause or (err.strerror or str(err) or type(err).__name__), todo


def write_error(path: str | os.PathLike, err: OSError, *, what: str = "") -> OutputError:
    """An :class:`~geoseg.errors.OutputError` for a failed write of ``path``.

    Args:
        path: the file that could not be written.
        err: the error the write raised.
        what: a prefix naming the option or the stage (e.g. ``"--out"``), optional.
    """
    if isinstance(err, OutputError):
        return err
    cause, todo = describe_os_error(err)
    prefix = f"{what}: " if what else ""
    return OutputError(f"{prefix}cannot write {path}: {cause}; {todo}", errno=err.errno)


def _default_file_mode() -> int:
    # mkstemp creates 0600 files; give the result the mode open() would have (0666 & ~umask).
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, mode: str = "wb", *, fsync: bool = True) -> Iterator[IO]:
    """Open a temporary file next to ``path``; on a clean exit it replaces ``path``.

    Args:
        path: the file to write (its folder must exist).
        mode: ``"wb"`` or ``"w"`` (text, UTF-8, line endings written as given).
        fsync: flush the data (and the folder entry) to disk before returning.

    Yields:
        The open temporary file.

    Raises:
        OutputError: creating, writing or renaming failed (full disk, read-only or missing
            folder, a folder in the way); the temporary file is removed and any previous file at
            ``path`` is left untouched. Other exceptions of the ``with`` body pass unchanged
            (after the same clean-up).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"mode: expected 'wb' or 'w', got {mode!r}")
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise write_error(path, err) from err
    try:
        text = {"encoding": "utf-8", "newline": ""} if mode == "w" else {}  # "\n" as written
        with os.fdopen(fd, mode, **text) as handle:
            yield handle
            handle.flush()
            if fsync:
                os.fsync(handle.fileno())
        os.chmod(tmp, _default_file_mode())
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(err, OSError) and not isinstance(err, GeosegError):
            raise write_error(path, err) from err
        raise
    if fsync:
        _fsync_dir(path.parent)


def atomic_write(path: str | os.PathLike, data: bytes | str, *, fsync: bool = True) -> Path:
    """Write ``data`` (bytes, or text as UTF-8) to ``path`` atomically; returns ``path``.

    Raises:
        OutputError: see :func:`atomic_output`.
    """
    with atomic_output(path, "w" if isinstance(data, str) else "wb", fsync=fsync) as handle:
        handle.write(data)
    return Path(path)


def atomic_savefig(fig: Any, path: str | os.PathLike, **kwargs: Any) -> Path:
    """``fig.savefig`` (a matplotlib figure) to ``path`` atomically, in the format of its
    suffix (PNG by default); ``kwargs`` go to ``savefig`` (e.g. ``dpi``).

    Raises:
        OutputError: see :func:`atomic_output`.
    """
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".").lower() or "png")
    with atomic_output(path, fsync=False) as handle:
        fig.savefig(handle, **kwargs)
    return path


def atomic_imwrite(path: str | os.PathLike, image: Any, *, fsync: bool = False) -> Path:
    """Encode an image with OpenCV in the format of ``path``'s suffix (``.png``, ``.jpg``...)
    and write it atomically.

    Args:
        path: the image file.
        image: `(H, W)` or `(H, W, 3)` uint8, OpenCV channel order (BGR).
        fsync: flush to disk before returning (off by default: frames come in thousands).

    Raises:
        OutputError: see :func:`atomic_output`; GeosegError: OpenCV cannot encode the image.
    """
    import cv2
    import numpy as np

    path = Path(path)
    ok, data = cv2.imencode(path.suffix or ".png", np.ascontiguousarray(image))
    if not ok:
        raise GeosegError(f"{path}: OpenCV cannot encode this image as {path.suffix or '.png'}")
    return atomic_write(path, data.tobytes(), fsync=fsync)


def clean_temp_files(folder: str | os.PathLike, *, recursive: bool = True) -> list[Path]:
    """Remove the temporary files interrupted atomic writes left in ``folder``.

    Only names of :data:`TEMP_PATTERN` (``.NAME.XXXXXXXX.tmp``, what :func:`atomic_output`
    creates) are removed; anything else is left alone.

    Returns:
        The removed files.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    files = folder.rglob(".*.tmp") if recursive else folder.glob(".*.tmp")
    removed = []
    for file in files:
        if TEMP_PATTERN.match(file.name) and file.is_file() and not file.is_symlink():
            with contextlib.suppress(OSError):
                file.unlink()
                removed.append(file)
    if removed:
        logger.info(
            "removed %d temporary file(s) of interrupted writes in %s", len(removed), folder
        )
    return removed


def _fsync_dir(folder: Path) -> None:
    # Makes the rename itself durable; not every platform lets a folder be opened.
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
