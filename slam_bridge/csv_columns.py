"""Named numeric columns of a CSV file, the one reader behind every log and table slam_bridge
reads (sensor logs, facade maps, ground-truth poses)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from slam_bridge.errors import SlamError

__all__ = ["read_columns"]


def read_columns(
    path: str | Path, required: list[str], optional: list[str] = ()
) -> dict[str, np.ndarray]:
    """The named numeric columns of a CSV file (empty cells read as NaN).

    Args:
        path: the file.
        required: columns that must be present.
        optional: columns read when present.

    Returns:
        ``{name: (R,) float64}`` for the required and the present optional columns.

    Raises:
        SlamError: no such file, no data row, missing columns, a cell that is not a number.
    """
    path = Path(path)
    if not path.is_file():
        raise SlamError(f"{path}: no such file")
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as err:
        raise SlamError(f"{path}: cannot be read as a CSV text file ({err})") from None
    if not rows:
        raise SlamError(f"{path}: empty file (expected a header line {','.join(required)})")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise SlamError(f"{path}: missing column(s) {missing} (found {header})")
    rows = [r for r in rows[1:] if any(cell.strip() for cell in r)]
    if not rows:
        raise SlamError(f"{path}: no data rows")
    out = {}
    for name in [*required, *(c for c in optional if c in header)]:
        j = header.index(name)
        col = np.empty(len(rows))
        for i, r in enumerate(rows):
            cell = r[j].strip() if j < len(r) else ""
            try:
                col[i] = float(cell) if cell else np.nan
            except ValueError:
                raise SlamError(
                    f"{path}: row {i + 2}, column {name!r}: {cell!r} is not a number"
                ) from None
        out[name] = col
    return out
