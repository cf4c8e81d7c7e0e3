"""Pictures of the chapter-4 experiment (thesis figs. 4.11, 4.13, 4.14), from its saved runs.

* ``trajectories_<model>.png``: every method's keyframes over the building model, beside the
  true path (figs. 4.11 / 4.13);
* ``association_<model>.png``: the map points of each bridge method, gold where associated
  with a facade, green elsewhere (the ray-cast baseline gilds the trees);
* ``reprojection_<model>.png``: the building model drawn into a few keyframes with the poses
  estimated without and with building constraints (fig. 4.14).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

#: each method in the README's words, for what a person reads (prints, legends, the report)
METHOD_NAMES = {
    "nobuild": "no buildings",
    "raycast": "geometric rule (ray cast)",
    "dirichlet": "2015 CNN + Dirichlet",
    "bayes": "network (eq. 4.14)",
    "oracle": "oracle (true facades)",
}

__all__ = ["write_pictures"]

COLOURS = {
    "nobuild": "tab:red",
    "raycast": "tab:orange",
    "dirichlet": "tab:purple",
    "bayes": "tab:blue",
    "oracle": "tab:green",
}
GOLD, GREEN = "#d4a017", "#3a9d4a"


def write_pictures(out: Path, folder: Path, facades: dict, methods, models) -> list[Path]:
    """Every picture of the module docstring whose runs exist in ``out/runs``.

    Args:
        out: the experiment's folder.
        folder: the rendered drive (``poses.csv``, ``rgb/``).
        facades: model name -> :class:`~slam_bridge.bridge.facades.Facades`.

    Returns:
        The files written.
    """
    import matplotlib

    matplotlib.use("Agg")
    from slam_bridge.csv_columns import read_columns

    poses = read_columns(folder / "poses.csv", ["timestamp", "tx", "ty"])
    truth_xy = np.column_stack([poses["tx"], poses["ty"]])
    written = []
    for model in models:
        runs = {m: _load(out / "runs" / f"{m}_{model}.npz") for m in methods}
        runs = {m: r for m, r in runs.items() if r is not None}
        if not runs:
            continue
        written.append(_trajectories(out, model, runs, truth_xy, facades[model]))
        bridged = {m: r for m, r in runs.items() if m != "nobuild"}
        if bridged:
            written.append(_associations(out, model, bridged, facades[model]))
        pair = [m for m in ("nobuild", "bayes") if m in runs]
        if pair:
            written.append(_reprojections(out, model, {m: runs[m] for m in pair}, folder,
                                          facades[model], poses["timestamp"]))  # fmt: skip
    return [path for path in written if path is not None]


def _load(path: Path) -> dict | None:
    if not path.is_file():
        return None
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _draw_facades(ax, facades, colour="0.6") -> None:
    for p0, p1 in zip(facades.p0, facades.p1, strict=True):
        ax.plot([p0[0], p1[0]], [p0[1], p1[1]], color=colour, lw=0.6)


def _zoom(ax, xy: np.ndarray, pad_m: float) -> None:
    """Axis limits around the finite rows of ``xy (N, 2)`` (2nd to 98th percentile, padded):
    a short drive covers a corner of the city, and at the city's scale its points vanish."""
    xy = xy[np.isfinite(xy).all(1)]
    if len(xy):
        lo, hi = np.percentile(xy, [2, 98], axis=0)
        ax.set_xlim(lo[0] - pad_m, hi[0] + pad_m)
        ax.set_ylim(lo[1] - pad_m, hi[1] + pad_m)


def _trajectories(out: Path, model: str, runs: dict, truth_xy: np.ndarray, facades) -> Path:
    """The keyframes over the model (left) and their horizontal error along the drive (right:
    at the map's scale the methods' centimetres to decimetres do not show)."""
    import matplotlib.pyplot as plt

    fig, (ax, ax_err) = plt.subplots(1, 2, figsize=(16, 7.5), width_ratios=(1, 1.2))
    _draw_facades(ax, facades)
    ax.plot(truth_xy[:, 0], truth_xy[:, 1], "k-", lw=2.0, label="true path")
    for method, r in runs.items():
        xy = np.where(r["in_world"][:, None], r["t_wc"][:, :2], np.nan)
        err = np.nanmean(r["error_m"]) if np.isfinite(r["error_m"]).any() else np.nan
        label = f"{METHOD_NAMES.get(method, method)} (mean error {err:.3f} m)"
        ax.plot(xy[:, 0], xy[:, 1], "-", lw=1.0, color=COLOURS.get(method), label=label)
        ax_err.plot(r["error_m"], "-", lw=1.0, color=COLOURS.get(method), label=label)
    _zoom(ax, truth_xy, 40.0)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"keyframe positions, {model} building model (grey: its facades)")
    ax.legend(loc="best", fontsize=8)
    ax_err.set_xlabel("keyframe")
    ax_err.set_ylabel("horizontal error (m)")
    ax_err.set_yscale("log")
    ax_err.grid(True, which="both", alpha=0.3)
    ax_err.set_title("horizontal error of each keyframe against the truth")
    ax_err.legend(loc="best", fontsize=8)
    path = out / f"trajectories_{model}.png"
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def _associations(out: Path, model: str, runs: dict, facades) -> Path:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(runs), figsize=(6 * len(runs), 6), squeeze=False)
    for ax, (method, r) in zip(axes[0], runs.items(), strict=True):
        pts, on = r["points"], r["facade"] >= 0
        ok = np.isfinite(pts).all(1)
        _draw_facades(ax, facades, "0.4")
        ax.scatter(*pts[ok & ~on, :2].T, s=1, c=GREEN, label="not associated")
        ax.scatter(*pts[ok & on, :2].T, s=2, c=GOLD, label="on a facade")
        # the experiment's precision: on the facade its pixels show, or one it lies on (runs
        # saved before "right" was kept: the pixels' facade alone)
        right_mask = r["right"] if "right" in r else r["facade"] == r["true_facade"]
        right = np.mean(right_mask[ok & on]) if on.any() else 0
        # one title per panel, no figure title: with equal axes a figure title floats above a
        # blank band
        ax.set_title(f"{METHOD_NAMES.get(method, method)}, {model} building model\n"
                     f"{int((ok & on).sum())} of {int(ok.sum())} map points on facades, "
                     f"precision {100 * right:.0f} %", fontsize=10)  # fmt: skip
        _zoom(ax, pts[ok, :2], 15.0)
        ax.set_aspect("equal")
        ax.set_xlabel("x east (m)")
        ax.set_ylabel("y north (m)")
        ax.legend(loc="upper right", fontsize=7, markerscale=4)
    path = out / f"association_{model}.png"
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def _reprojections(out: Path, model: str, runs: dict, folder: Path, facades, frame_times,
                   count: int = 3) -> Path | None:  # fmt: skip
    """The facades' outlines projected with each run's pose into ``count`` keyframes spread
    over the drive (the images under them): keyframes that every run placed in the world, so
    each tile of a row has its outline (the runs choose their keyframes themselves). None when
    the runs share no such keyframe."""
    common = None
    for r in runs.values():
        placed_mask = np.asarray(r["in_world"], dtype=bool) & np.isfinite(r["t_wc"]).all(1)
        placed = np.asarray(r["timestamps"])[placed_mask]
        common = placed if common is None else np.intersect1d(common, placed)
    if not len(common):
        return None
    common = np.sort(common)
    picks = common[np.linspace(len(common) // 6, len(common) - 1, count).astype(int)]
    rows = []
    for t in picks:
        frame = int(np.argmin(np.abs(frame_times - t)))
        rgb = cv2.imread(str(folder / "rgb" / f"{frame:06d}.png"))
        tiles = []
        for method, r in runs.items():
            j = int(np.flatnonzero(r["timestamps"] == t)[0])
            tile = rgb.copy()
            _draw_model(tile, facades, r["R_wc"][j], r["t_wc"][j], r["K"])
            for line, text in enumerate(
                [
                    f"{METHOD_NAMES.get(method, method)}, frame {frame}",
                    "yellow: the building model seen from this pose",
                ]
            ):
                for colour, width in (((0, 0, 0), 5), ((255, 255, 255), 2)):  # outlined
                    cv2.putText(tile, text, (10, 28 + 26 * line), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                                colour, width, cv2.LINE_AA)  # fmt: skip
            tiles.append(tile)
        rows.append(np.concatenate(tiles, axis=1))
    path = out / f"reprojection_{model}.png"
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
    return path


NEAR_M = 1.0  # the near plane the facade outlines are clipped at, metres in front of the camera


def clip_near(polygon: np.ndarray, near: float = NEAR_M) -> np.ndarray:
    """The part of a camera-frame polygon in front of the plane ``z = near``
    (Sutherland-Hodgman against that one plane).

    Args:
        polygon: ``(N, 3)`` vertices in order, camera frame.

    Returns:
        ``(M, 3)`` vertices of the clipped polygon (``M = 0`` when it lies wholly behind).
    """
    kept = []
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        if a[2] >= near:
            kept.append(a)
        if (a[2] >= near) != (b[2] >= near):  # the edge crosses the plane
            kept.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(kept).reshape(-1, 3)


def _draw_model(image: np.ndarray, facades, R_wc: np.ndarray, t_wc: np.ndarray, K,
                max_range_m: float = 60.0) -> None:  # fmt: skip
    """Each facade's rectangle (bottom edge, top edge, sides) in yellow, clipped at the near
    plane: the facades along the street start beside or behind the camera."""
    corners = np.stack(
        [
            np.column_stack([facades.p0, facades.z_min]),
            np.column_stack([facades.p1, facades.z_min]),
            np.column_stack([facades.p1, facades.z_max]),
            np.column_stack([facades.p0, facades.z_max]),
        ],
        axis=1,
    )  # (F, 4, 3)
    X_c = (corners - t_wc) @ R_wc  # R_cw X = R_wc^T X
    K = np.asarray(K)
    for quad in X_c[np.linalg.norm(X_c, axis=2).min(1) < max_range_m]:
        clipped = clip_near(quad)
        if len(clipped) < 3:
            continue
        uv = clipped @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        if np.all(np.abs(uv) < 1e5):  # OpenCV clips the lines to the image
            cv2.polylines(image, [np.round(uv).astype(np.int32)], True, (0, 215, 255), 2,
                          cv2.LINE_AA)  # fmt: skip
