"""Numeric CSV tables with a fixed header line, as the GIS products are written."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from geoseg.atomic import atomic_output
from geoseg.errors import GeosegError


def write_table(path: str | Path, table: np.ndarray, fmt: Sequence[str], header: str) -> Path:
    """Write `(R, C)` ``table`` as CSV under the ``header`` line, atomically (a full disk leaves
    no partial file; :class:`~geoseg.errors.OutputError` names it).

    Args:
        path: the CSV file.
        table: `(R, C)` numbers.
        fmt: C ``printf`` formats.
        header: the comma-separated column names.

    Returns:
        ``path``.
    """
    path = Path(path)
    with atomic_output(path, "w", fsync=False) as handle:
        np.savetxt(handle, table, fmt=list(fmt), delimiter=",", header=header, comments="")
    return path


def read_table(path: str | Path, header: str) -> np.ndarray:
    """Read a numeric CSV whose first line is exactly ``header``.

    Args:
        path: the CSV file.
        header: the expected comma-separated column names.

    Returns:
        `(R, C)` float64 table, C = number of columns in ``header`` (``nan`` cells kept).

    Raises:
        GeosegError: missing file or other columns.
    """
    path = Path(path)
    if not path.is_file():
        raise GeosegError(f"{path}: no such file")
    with path.open() as f:
        found = f.readline().strip()
    if found != header:
        raise GeosegError(f"{path}: expected the columns {header!r}, got {found!r}")
    table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if table.size == 0:
        table = np.zeros((0, len(header.split(","))))
    return table
