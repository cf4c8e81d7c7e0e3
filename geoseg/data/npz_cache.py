"""On-disk cache entries as compressed ``.npz`` files: atomic writes, forgiving reads.

The synthetic datasets cache rendered frames and network features. A cache must never cost a
run: a write that fails (e.g. a full disk) is logged and skipped, and an entry that cannot be
read back (truncated, corrupted, missing a field) is reported as absent so the caller recomputes
it.
"""

from __future__ import annotations

import logging
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from geoseg.atomic import atomic_output

logger = logging.getLogger(__name__)

# What np.load raises on a truncated or corrupted archive, or a missing field.
UNREADABLE = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


def write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> bool:
    """Write ``arrays`` to ``path`` atomically (temp file + rename); False (logged) on failure."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path, fsync=False) as handle:  # a cache: losing it costs a recompute
            np.savez_compressed(handle, **arrays)
        return True
    except OSError as err:
        logger.warning("cannot write cache entry %s (%s); continuing without it", path, err)
        return False


def read_npz(path: Path | None, fields: Sequence[str]) -> dict[str, np.ndarray] | None:
    """The named arrays of a cache entry, or None when it is absent or unreadable (logged)."""
    if path is None or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in fields}
    except UNREADABLE as err:
        logger.warning("cache entry %s is unreadable (%s); recomputing it", path, err)
        return None
