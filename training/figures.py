"""Qualitative panels of the held-out evaluation, after the thesis's figures 4.20 and 4.8.

- :func:`labels_normals_figure` (fig. 4.20, "RGB images, segmented images, normals predicted by
  the network"): one row per frame, columns RGB | predicted labels | predicted normals, then the
  ground truth labels | normals when ``ground_truth``.
- :func:`filter_figure` (fig. 4.8): one row per frame, columns RGB | building by the naive CNN's
  argmax | building kept by the Dirichlet filter | ground-truth building, building pixels in red
  over the dimmed image.

Both draw the :class:`~training.evaluate_seg.PanelFrame` objects of
:func:`training.evaluate_seg.evaluate` on matplotlib's Agg canvas (no global backend switch) and
write the PNG atomically (temporary file + rename).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from geoseg.atomic import atomic_savefig
from geoseg.classes import BUILDING, CLASS_NAMES, PALETTE, colorize
from geoseg.errors import GeosegError
from geoseg.infer import normals_to_rgb

logger = logging.getLogger(__name__)

_RED = np.array([230, 25, 25], dtype=np.float32)


def normals_image(normals: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Normals as RGB, ``(n + 1) / 2``, black where not ``valid``.

    Args:
        normals: `(3, H, W)` normals.
        valid: `(H, W)` bool (default: vectors of norm > 0.5).

    Returns:
        `(H, W, 3)` uint8.
    """
    rgb = normals_to_rgb(np.asarray(normals, dtype=np.float32))
    if valid is None:
        valid = np.linalg.norm(normals, axis=0) > 0.5
    rgb[~valid] = 0
    return rgb


def overlay_mask(rgb: np.ndarray, mask: np.ndarray, *, alpha: float = 0.65) -> np.ndarray:
    """Mask pixels in red over a dimmed grey copy of the image (thesis fig. 4.8).

    Args:
        rgb: `(H, W, 3)` uint8.
        mask: `(H, W)` bool.
        alpha: weight of the red on masked pixels.

    Returns:
        `(H, W, 3)` uint8.
    """
    grey = np.asarray(rgb, dtype=np.float32).mean(axis=2, keepdims=True).repeat(3, axis=2) * 0.6
    out = grey.copy()
    m = np.asarray(mask, dtype=bool)
    out[m] = (1 - alpha) * grey[m] + alpha * _RED
    return np.clip(out, 0, 255).round().astype(np.uint8)


def _save(fig: Any, path: Path, dpi: int) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_savefig(fig, path, dpi=dpi)
    logger.info("wrote %s", path)
    return path


def _grid(panels: Sequence[Any], columns: Sequence[str], cell_w: float) -> tuple[Any, Any]:
    from matplotlib.figure import Figure

    h, w = panels[0].rgb.shape[:2]
    rows = len(panels)
    cell_h = cell_w * h / w
    fig = Figure(figsize=(cell_w * len(columns), cell_h * rows + 0.6), layout="constrained")
    axes = np.atleast_2d(fig.subplots(rows, len(columns), squeeze=False))
    for j, title in enumerate(columns):
        axes[0, j].set_title(title, fontsize=9)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    return fig, axes


def labels_normals_figure(
    panels: Sequence[Any],
    path: str | os.PathLike,
    *,
    ground_truth: bool = True,
    cell_width_in: float = 3.0,
    dpi: int = 110,
) -> Path:
    """Fig. 4.20-like panel: RGB | predicted labels | predicted normals (| ground truth).

    Args:
        panels: :class:`~training.evaluate_seg.PanelFrame` objects (``rgb (H, W, 3)``,
            ``labels_pred (H, W)``, ``normals_pred (3, H, W)``, ``labels_true``,
            ``normals_true``); a missing prediction leaves its cell blank.
        path: output PNG.
        ground_truth: add the ground-truth labels and normals columns.
        cell_width_in: width of one image, inches.
        dpi: resolution.

    Returns:
        The written path.

    Raises:
        GeosegError: no frame.
    """
    if not panels:
        raise GeosegError("panels: no frame to draw")
    columns = ["RGB", "predicted labels", "predicted normals"]
    if ground_truth:
        columns += ["ground-truth labels", "ground-truth normals"]
    fig, axes = _grid(panels, columns, cell_width_in)
    for i, p in enumerate(panels):
        cells: list[np.ndarray | None] = [
            p.rgb,
            None if p.labels_pred is None else colorize(p.labels_pred),
            None if p.normals_pred is None else normals_to_rgb(p.normals_pred),
        ]
        if ground_truth:
            cells += [colorize(p.labels_true), normals_image(p.normals_true)]
        for j, img in enumerate(cells):
            if img is not None:
                axes[i, j].imshow(img, interpolation="nearest")
        axes[i, 0].set_ylabel(f"#{p.index} {p.condition}", fontsize=8)
    handles = _legend_handles()
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8)
    return _save(fig, Path(path), dpi)


def _legend_handles() -> list[Any]:
    from matplotlib.patches import Patch

    return [Patch(color=PALETTE[k] / 255.0, label=name) for k, name in enumerate(CLASS_NAMES)]


def filter_figure(
    panels: Sequence[Any],
    path: str | os.PathLike,
    *,
    cell_width_in: float = 3.0,
    dpi: int = 110,
) -> Path:
    """Fig. 4.8-style panel: RGB | argmax building | after the Dirichlet filter | ground truth.

    Args:
        panels: :class:`~training.evaluate_seg.PanelFrame` objects with ``building_argmax`` and
            ``building_filtered`` `(H, W)` bool masks (frames without them are skipped).
        path: output PNG.
        cell_width_in: width of one image, inches.
        dpi: resolution.

    Returns:
        The written path.

    Raises:
        GeosegError: no frame carries the filter masks.
    """
    rows = [p for p in panels if p.building_argmax is not None and p.building_filtered is not None]
    if not rows:
        raise GeosegError("panels: no frame carries the naive CNN / Dirichlet filter masks")
    columns = ["RGB", "argmax building", "after Dirichlet filter", "ground-truth building"]
    fig, axes = _grid(rows, columns, cell_width_in)
    for i, p in enumerate(rows):
        truth = p.labels_true == BUILDING
        argmax = np.asarray(p.building_argmax, bool)
        kept = np.asarray(p.building_filtered, bool)
        axes[i, 0].imshow(p.rgb)
        axes[i, 1].imshow(overlay_mask(p.rgb, argmax), interpolation="nearest")
        axes[i, 2].imshow(overlay_mask(p.rgb, kept), interpolation="nearest")
        axes[i, 3].imshow(overlay_mask(p.rgb, truth), interpolation="nearest")
        fp_a, fp_k = int((argmax & ~truth).sum()), int((kept & ~truth).sum())
        axes[i, 1].set_xlabel(f"false positives: {fp_a} px", fontsize=8)
        axes[i, 2].set_xlabel(f"false positives: {fp_k} px", fontsize=8)
        axes[i, 0].set_ylabel(f"#{p.index} {p.condition}", fontsize=8)
    return _save(fig, Path(path), dpi)


__all__ = ["filter_figure", "labels_normals_figure", "normals_image", "overlay_mask"]
