"""Pictures of a synthetic sequence: the top-down map and the contact sheet (matplotlib, Agg).

Figures are built with :class:`matplotlib.figure.Figure` and the Agg canvas directly, never
through ``pyplot``: no global state, no display needed, nothing selected at import.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from geoseg.atomic import atomic_savefig
from geoseg.errors import GeosegError

logger = logging.getLogger(__name__)

_TRACK_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


def _figure(width_in: float, height_in: float, dpi: int):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def contact_sheet(
    rows: Sequence[Sequence[np.ndarray]],
    path: str | Path,
    *,
    row_labels: Sequence[str] | None = None,
    col_labels: Sequence[str] | None = None,
    title: str | None = None,
    tile_width: int = 240,
    dpi: int = 100,
) -> Path:
    """Write a grid of images as one PNG.

    Args:
        rows: rows of `(H, W, 3)` uint8 RGB images (any sizes; each is resized to
            ``tile_width`` wide, keeping its aspect ratio; short rows are padded with white).
        path: output PNG.
        row_labels: one label per row, written left of it.
        col_labels: one label per column, written above the first row.
        title: figure title.
        tile_width: width of one tile, pixels.
        dpi: figure resolution.

    Returns:
        ``path``.
    """
    import cv2

    if not rows or not any(len(r) for r in rows):
        raise GeosegError("rows: expected at least one image, got none")
    n_cols = max(len(r) for r in rows)
    tile_h = 0
    resized: list[list[np.ndarray]] = []
    for r, row in enumerate(rows):
        out = []
        for c, img in enumerate(row):
            img = np.asarray(img)
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise GeosegError(
                    f"rows[{r}][{c}]: expected an (H, W, 3) uint8 image, got "
                    f"{img.shape} {img.dtype}"
                )
            h = max(1, int(round(img.shape[0] * tile_width / img.shape[1])))
            grow = tile_width > img.shape[1]  # upscale small frames without blurring labels
            interp = cv2.INTER_NEAREST if grow else cv2.INTER_AREA
            out.append(cv2.resize(img, (tile_width, h), interpolation=interp))
            tile_h = max(tile_h, h)
        resized.append(out)
    gap = 4
    mosaic = np.full(
        (len(rows) * (tile_h + gap) - gap, n_cols * (tile_width + gap) - gap, 3), 255, np.uint8
    )
    for r, row in enumerate(resized):
        for c, img in enumerate(row):
            y, x = r * (tile_h + gap), c * (tile_width + gap)
            mosaic[y : y + img.shape[0], x : x + tile_width] = img
    left = 1.6 if row_labels else 0.1
    top = 0.5 if (title or col_labels) else 0.1
    w_in = mosaic.shape[1] / dpi + left + 0.1
    h_in = mosaic.shape[0] / dpi + top + 0.1
    fig = _figure(w_in, h_in, dpi)
    ax = fig.add_axes(
        (left / w_in, 0.1 / h_in, mosaic.shape[1] / dpi / w_in, mosaic.shape[0] / dpi / h_in)
    )
    ax.imshow(mosaic, interpolation="nearest")
    ax.set_axis_off()
    for r, label in enumerate(row_labels or ()):
        ax.text(-8, r * (tile_h + gap) + tile_h / 2, label, ha="right", va="center", fontsize=8)
    for c, label in enumerate(col_labels or ()):
        ax.text(
            c * (tile_width + gap) + tile_width / 2, -6, label, ha="center", va="bottom", fontsize=8
        )
    if title:
        fig.suptitle(title, fontsize=10, y=1.0 - 0.05 / h_in, va="top")
    return atomic_savefig(fig, path, dpi=dpi)


def plot_map(
    path: str | Path,
    *,
    true_footprints: Sequence[np.ndarray] = (),
    building_model: Any = None,
    dem: Any = None,
    streets: Sequence[Any] = (),
    tracks: Mapping[str, np.ndarray] | None = None,
    gps: Mapping[str, Any] | None = None,
    title: str | None = None,
    zoom_margin_m: float | None = 40.0,
    size_in: float = 9.0,
    dpi: int = 110,
) -> Path:
    """Top-down map of a world and its GIS products.

    Args:
        path: output PNG.
        true_footprints: true building footprints, each `(N, 2)` (filled grey), indexed by
            building id (as ``World.buildings``).
        building_model: a :class:`~geoseg.synth.buildings.BuildingModel` (outlined: blue
            present, red dashed extra; missing true buildings hatched).
        dem: a :class:`~geoseg.synth.dem.DemModel` (segments coloured by model altitude).
        streets: streets with ``centerline`` `(M, 2)` (drawn as light bands).
        tracks: name -> `(T, 2)` true trajectory.
        gps: name -> :class:`~geoseg.synth.gps.GpsLog` (valid fixes as crosses, each linked to
            the true position).
        title: figure title.
        zoom_margin_m: when there are tracks, a second panel zooms on them with this margin;
            None for the whole-world panel only.
        size_in: height of one panel, inches.
        dpi: resolution.

    Returns:
        ``path``.
    """
    tracks = dict(tracks or {})
    gps = dict(gps or {})
    zoom = zoom_margin_m is not None and bool(tracks)
    panels = 2 if zoom else 1
    fig = _figure(size_in * (1.15 + 0.85 * (panels - 1)), size_in * 0.85, dpi)
    axes = [fig.add_subplot(1, panels, k + 1) for k in range(panels)]
    layers = dict(
        true_footprints=true_footprints, building_model=building_model, dem=dem,
        streets=streets, tracks=tracks, gps=gps,
    )  # fmt: skip
    handles, dem_coll = _draw_layers(axes[0], **layers)
    axes[0].autoscale_view()
    axes[0].set_title(title or "world", fontsize=10)
    if zoom:
        _draw_layers(axes[1], **layers)
        pts = np.concatenate([np.asarray(xy)[:, :2] for xy in tracks.values()])
        center = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        half = 0.5 * (pts.max(axis=0) - pts.min(axis=0)).max() + zoom_margin_m
        lo, hi = center - half, center + half  # a square window
        axes[1].set_xlim(lo[0], hi[0])
        axes[1].set_ylim(lo[1], hi[1])
        axes[1].set_title("zoom on the routes: GPS fixes linked to the true positions", fontsize=9)
        axes[0].indicate_inset(
            (lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1]), edgecolor="k", alpha=0.8
        )
    for ax in axes:
        ax.set_aspect("equal", adjustable="datalim" if ax is axes[0] else "box")
        ax.set_xlabel("x east (m)")
        ax.set_ylabel("y north (m)")
    if handles:
        axes[0].legend(handles=handles, loc="upper left", fontsize=7, framealpha=0.85)
    if dem_coll is not None:
        cbar = fig.colorbar(dem_coll, ax=axes[0], shrink=0.6, pad=0.02)
        cbar.set_label("DEM road altitude (m)")
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.07, top=0.94, wspace=0.12)
    return atomic_savefig(fig, path, dpi=dpi)


def _draw_layers(ax, *, true_footprints, building_model, dem, streets, tracks, gps):
    """Draw every layer of :func:`plot_map` on ``ax``; returns (legend handles, DEM artist)."""
    from matplotlib.collections import LineCollection, PolyCollection

    handles = []
    for s in streets:
        line = np.asarray(s.centerline)
        ax.plot(line[:, 0], line[:, 1], color="#e6e6e6", lw=3.0, solid_capstyle="round", zorder=0)
    if len(true_footprints):
        coll = PolyCollection(
            [np.asarray(f) for f in true_footprints], facecolors="#bdbdbd", edgecolors="none",
            zorder=1, label="true buildings",
        )  # fmt: skip
        ax.add_collection(coll)
        handles.append(coll)
    if building_model is not None:
        present = [b.footprint for b in building_model.buildings if b.status == "present"]
        extra = [b.footprint for b in building_model.buildings if b.status == "extra"]
        if present:
            coll = PolyCollection(
                present, facecolors="none", edgecolors="#1f4e9c", lw=0.8, zorder=3,
                label="building model (GIS)",
            )  # fmt: skip
            ax.add_collection(coll)
            handles.append(coll)
        if extra:
            coll = PolyCollection(
                extra, facecolors="none", edgecolors="#d62728", lw=1.2, linestyles="--",
                zorder=3, label="extra in GIS (demolished)",
            )  # fmt: skip
            ax.add_collection(coll)
            handles.append(coll)
        missing = [i for i in sorted(building_model.missing_ids) if i < len(true_footprints)]
        if missing:
            coll = PolyCollection(
                [np.asarray(true_footprints[i]) for i in missing],
                facecolors="none", edgecolors="#ff7f0e", hatch="////", lw=0.6, zorder=2,
                label="missing from GIS",
            )  # fmt: skip
            ax.add_collection(coll)
            handles.append(coll)
    dem_coll = None
    if dem is not None and len(dem):
        segs = np.stack([dem.p0, dem.p1], axis=1)
        dem_coll = LineCollection(
            segs, array=0.5 * (dem.z0 + dem.z1), cmap="viridis", lw=2.0, zorder=4
        )
        ax.add_collection(dem_coll)
    for k, (name, xy) in enumerate(tracks.items()):
        xy = np.asarray(xy)
        (line,) = ax.plot(
            xy[:, 0], xy[:, 1], color=_TRACK_COLORS[k % len(_TRACK_COLORS)], lw=1.8, zorder=5,
            label=f"trajectory: {name}",
        )  # fmt: skip
        ax.plot(xy[0, 0], xy[0, 1], "o", color=line.get_color(), ms=5, zorder=6)
        handles.append(line)
    for k, (name, log) in enumerate(gps.items()):
        v = log.valid
        color = _TRACK_COLORS[k % len(_TRACK_COLORS)]
        links = np.stack([log.true_xyz[v, :2], log.xy[v]], axis=1)
        ax.add_collection(LineCollection(links, colors=color, lw=0.6, alpha=0.7, zorder=6))
        dots = ax.scatter(
            log.xy[v, 0], log.xy[v, 1], s=14, marker="x", color=color, zorder=7,
            label=f"GPS fixes: {name} ({int(v.sum())}/{len(v)} valid)",
        )  # fmt: skip
        handles.append(dots)
    return handles, dem_coll


def normals_to_rgb(normals: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame unit normals as a colour image (``(n + 1) / 2``, invalid pixels black).

    Args:
        normals: `(3, H, W)` unit normals.
        valid: `(H, W)` bool mask, or None.

    Returns:
        `(H, W, 3)` uint8 RGB.
    """
    n = np.nan_to_num(np.asarray(normals, dtype=np.float32))
    rgb = np.clip((np.moveaxis(n, 0, -1) + 1.0) * 127.5, 0, 255).astype(np.uint8)
    if valid is not None:
        rgb[~np.asarray(valid, dtype=bool)] = 0
    return rgb


def depth_to_rgb(depth: np.ndarray, max_depth: float = 80.0) -> np.ndarray:
    """Depth as a colour image (turbo colormap, near = red; invalid or far pixels black).

    Args:
        depth: `(H, W)` metres (NaN, inf or <= 0 invalid).
        max_depth: depth mapped to the end of the colormap.

    Returns:
        `(H, W, 3)` uint8 RGB.
    """
    from matplotlib import colormaps

    d = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    x = np.clip(np.where(valid, d, max_depth) / max_depth, 0.0, 1.0)
    rgb = (colormaps["turbo"](1.0 - x)[..., :3] * 255).astype(np.uint8)
    rgb[~valid] = 0
    return rgb
