"""Numeric CSV tables with a fixed header line, as the GIS products are written."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geoseg.errors import GeosegError


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
