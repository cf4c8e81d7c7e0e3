"""Training curves as PNG files (matplotlib's Agg canvas, no global backend switch).

``history`` everywhere is a list of per-epoch rows such as
``{"epoch": 1, "train_loss": 0.8, "val_loss": 0.9, "val_miou": 0.4, "lr": 5e-4}``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from geoseg.atomic import atomic_savefig

logger = logging.getLogger(__name__)

_SKIP = {"epoch", "lr", "time_s", "global_step", "n_samples"}


def _series(history: Sequence[Mapping[str, Any]], key: str) -> tuple[list[float], list[float]]:
    xs, ys = [], []
    for row in history:
        value = row.get(key)
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            xs.append(float(row.get("epoch", len(xs) + 1)))
            ys.append(float(value))
    return xs, ys


def plot_history(history: Sequence[Mapping[str, Any]], out_dir: str | Path) -> list[Path]:
    """Write ``loss.png`` (every ``*loss*`` column) and ``metrics.png`` (every other numeric
    column except epoch/lr/time) into ``out_dir``; return the written paths.

    Files are written to a temporary name and renamed, so a reader never sees half a PNG.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    out_dir = Path(out_dir)
    keys: list[str] = []
    for row in history:
        keys.extend(k for k in row if k not in keys)
    numeric = [
        k for k in keys if k not in _SKIP and not k.endswith("n_pixels") and _series(history, k)[0]
    ]
    groups = {
        "loss.png": [k for k in numeric if "loss" in k],
        "metrics.png": [k for k in numeric if "loss" not in k],
    }
    written = []
    for name, cols in groups.items():
        if not cols:
            continue
        fig = Figure(figsize=(6, 4), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        for key in cols:
            xs, ys = _series(history, key)
            ax.plot(xs, ys, marker="o", markersize=3, label=key)
        ax.set_xlabel("epoch")
        ax.set_ylabel("loss" if name == "loss.png" else "metric")
        ax.grid(True, alpha=0.3)
        if len(cols) <= 12:
            ax.legend(fontsize=7)
        fig.tight_layout()
        written.append(atomic_savefig(fig, out_dir / name))
    return written
