"""Integrity of weights files: SHA-256 digests recorded when written, verified when read.

A flipped byte in a weights file usually still loads (torch and onnxruntime check no checksum)
and gives a network that agrees with the intact one on a fraction of the pixels. Every weights
file geoseg writes therefore carries a SHA-256 digest of its content, checked on every load:

* torch files (training checkpoints ``last.pt``/``best.pt``, model checkpoints ``model.pt``):
  the key ``"sha256"`` holds :func:`content_sha256` of the rest of the mapping (tensors by
  dtype, shape and bytes; plain data by type and value), added by :func:`seal`;
* ONNX files: the metadata property ``geoseg.sha256`` holds the SHA-256 of the model's
  deterministic serialisation without that property (:mod:`geoseg.export`);
* JSON filters (:mod:`geoseg.dirichlet`): the key ``"sha256"``, as for torch files;
* model cards (``model_card.json``) list the SHA-256 of each file of the run (``"sha256":
  {"model.pt": ..., "model.onnx": ...}``): files written before digests were embedded (the
  shipped weights) are checked against the card next to them.

A file with neither an embedded digest nor a card entry loads with a logged warning (weights
written by an older geoseg). A mismatch is a :class:`~geoseg.errors.GeosegError` naming the
file. :func:`read_torch_file` is the one place torch weights files are read: ``weights_only``,
clear messages for text files, truncated archives and missing CUDA, and the digest check.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from geoseg.errors import GeosegError

logger = logging.getLogger(__name__)

DIGEST_KEY = "sha256"
CARD_FILE = "model_card.json"
_CHUNK = 1 << 20


# ----------------------------------------------------------------------------- digests
def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def _feed(h: Any, value: Any) -> None:
    """Feed ``value`` to the hash ``h`` in a canonical, type-tagged form."""
    if value is None:
        h.update(b"N")
    elif isinstance(value, bool):
        h.update(b"B1" if value else b"B0")
    elif isinstance(value, int):
        text = str(value).encode()
        h.update(b"I" + struct.pack("<Q", len(text)) + text)
    elif isinstance(value, float):
        h.update(b"F" + struct.pack("<d", value))
    elif isinstance(value, str):
        data = value.encode("utf-8", "surrogatepass")
        h.update(b"S" + struct.pack("<Q", len(data)) + data)
    elif isinstance(value, bytes | bytearray):
        h.update(b"Y" + struct.pack("<Q", len(value)) + bytes(value))
    elif isinstance(value, Mapping):
        items = sorted(value.items(), key=lambda kv: (type(kv[0]).__name__, repr(kv[0])))
        h.update(b"D" + struct.pack("<Q", len(items)))
        for key, item in items:
            _feed(h, key)
            _feed(h, item)
    elif isinstance(value, list | tuple):
        h.update(b"L" + struct.pack("<Q", len(value)))
        for item in value:
            _feed(h, item)
    elif hasattr(value, "detach") and hasattr(value, "dtype"):  # torch tensor
        import torch

        t = value.detach().cpu().contiguous()
        h.update(b"T" + str(t.dtype).encode() + repr(tuple(t.shape)).encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif hasattr(value, "dtype") and hasattr(value, "tobytes"):  # NumPy array or scalar
        import numpy as np

        a = np.ascontiguousarray(value)
        h.update(b"A" + str(a.dtype).encode() + repr(a.shape).encode() + a.tobytes())
    else:
        raise GeosegError(f"content_sha256: cannot digest a {type(value).__name__}")


def content_sha256(payload: Mapping[str, Any]) -> str:
    """Hex SHA-256 of a mapping of plain data and tensors, without its ``"sha256"`` key."""
    h = hashlib.sha256(b"geoseg-content-v1")
    _feed(h, {k: v for k, v in payload.items() if k != DIGEST_KEY})
    return h.hexdigest()


def seal(payload: Mapping[str, Any]) -> dict[str, Any]:
    """``payload`` with ``"sha256"`` set to :func:`content_sha256` of the rest."""
    out = {k: v for k, v in payload.items() if k != DIGEST_KEY}
    out[DIGEST_KEY] = content_sha256(out)
    return out


def card_sha256(path: str | os.PathLike) -> str | None:
    """The SHA-256 the ``model_card.json`` next to ``path`` records for it (None: none)."""
    path = Path(path)
    card = path.parent / CARD_FILE
    if not card.is_file():
        return None
    try:
        data = json.loads(card.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    digests = data.get(DIGEST_KEY) if isinstance(data, dict) else None
    value = digests.get(path.name) if isinstance(digests, dict) else None
    return value if isinstance(value, str) else None


def corrupt_error(
    path: str | os.PathLike, recorded: str, actual: str, *, where: str
) -> GeosegError:
    """The error for a file whose content does not match its recorded digest."""
    return GeosegError(
        f"{path}: the file is corrupt: its content does not match the SHA-256 recorded {where} "
        f"({recorded[:12]}... expected, {actual[:12]}... found); restore it from a backup or "
        "re-create it (retrain / re-export)"
    )


def verify_payload(payload: Mapping[str, Any], path: str | os.PathLike) -> None:
    """Check a loaded torch/JSON payload against its embedded digest, else against the model
    card next to ``path`` (whole-file hash), else log a warning.

    Raises:
        GeosegError: a digest does not match (names the file).
    """
    recorded = payload.get(DIGEST_KEY)
    if isinstance(recorded, str):
        actual = content_sha256(payload)
        if actual != recorded:
            raise corrupt_error(path, recorded, actual, where="in it")
        return
    verify_file_against_card(path)


def verify_file_against_card(path: str | os.PathLike) -> None:
    """Check ``path``'s bytes against the SHA-256 its sibling model card records; without a
    record, log a warning (a file written by an older geoseg).

    Raises:
        GeosegError: the card's digest does not match.
    """
    recorded = card_sha256(path)
    if recorded is None:
        logger.warning(
            "%s: no SHA-256 recorded (written by an older geoseg?): its integrity is not verified",
            path,
        )
        return
    actual = file_sha256(path)
    if actual != recorded:
        raise corrupt_error(path, recorded, actual, where=f"in {Path(path).parent / CARD_FILE}")


# ----------------------------------------------------------------------------- torch files
_TORCH_WRITE_FAILURES = ("inline_container", "PytorchStreamWriter", "unexpected pos")


def save_torch_file(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save(obj)`` to ``path`` atomically (:func:`geoseg.atomic.atomic_output`).

    torch reports a failed write (full disk, file size limit) as a ``RuntimeError`` ("unexpected
    pos ..."); it is turned into an :class:`~geoseg.errors.OutputError` naming the file.

    Raises:
        OutputError: the file cannot be written; a previous file at ``path`` is kept and no
            temporary file is left.
    """
    import errno as errnos

    import torch

    from geoseg.atomic import atomic_output, write_error

    path = Path(path)
    try:
        with atomic_output(path) as handle:
            torch.save(obj, handle)
    except RuntimeError as err:
        if not any(marker in str(err) for marker in _TORCH_WRITE_FAILURES):
            raise
        code = errnos.EIO
        try:
            stats = os.statvfs(path.parent)
            if stats.f_bavail * stats.f_frsize < 1 << 20:
                code = errnos.ENOSPC
        except OSError:
            pass
        failure = OSError(code, "the write failed (disk full or a file size limit?)")
        raise write_error(path, failure) from err
    return path


def _looks_like_text(head: bytes) -> bool:
    if not head:
        return True
    printable = sum(32 <= b < 127 or b in (9, 10, 13) for b in head)
    return printable / len(head) > 0.95


def _wants_cuda(map_location: Any) -> bool:
    text = str(map_location) if map_location is not None else ""
    return text.startswith("cuda")


def read_torch_file(
    path: str | os.PathLike, *, map_location: Any = "cpu", verify: bool = True
) -> dict[str, Any]:
    """Read a torch weights file (a mapping) with ``torch.load(weights_only=True)``.

    Args:
        path: the ``.pt`` file.
        map_location: where tensors go (``"cpu"``, ``"cuda"``, a device).
        verify: check the embedded digest (or the model card's) with :func:`verify_payload`.

    Returns:
        The loaded mapping.

    Raises:
        GeosegError: missing file; CUDA asked for but unavailable; a text file, a truncated or
            corrupt archive, or anything else that is not a torch mapping; a digest mismatch.
            Every message names the file.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise GeosegError(f"{path}: no such checkpoint file")
    if _wants_cuda(map_location) and not torch.cuda.is_available():
        raise GeosegError(
            f"{path}: device {map_location} requested but CUDA is not available on this "
            "machine; use the CPU (--device cpu)"
        )
    try:
        with open(path, "rb") as handle:
            head = handle.read(512)
    except OSError as err:
        raise GeosegError(f"{path}: cannot read ({err.strerror or err})") from None
    try:
        data = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # torch raises many types for a bad file
        first = str(err).strip().splitlines()[0][:160] if str(err).strip() else ""
        if head.startswith(b"PK\x03\x04"):
            what = f"a corrupt or truncated torch checkpoint ({type(err).__name__}: {first})"
        elif _looks_like_text(head):
            what = "a text file, not a torch checkpoint"
        else:
            what = "not a torch checkpoint (unknown binary format)"
        raise GeosegError(f"{path}: {what}") from None
    if not isinstance(data, dict):
        raise GeosegError(f"{path}: expected a checkpoint mapping, got {type(data).__name__}")
    if verify:
        verify_payload(data, path)
    return data
