"""The GIS building model as the bridge sees it: vertical facade rectangles.

A facade ``i`` is the rectangle above the footprint edge ``p0_i -> p1_i`` between the altitudes
``z_min_i`` and ``z_max_i``, on the plane ``n_i . X = d_i`` (``n_i`` the outward unit normal,
horizontal). ``geoseg render`` writes such a table as ``gis/facades.csv`` (columns ``x0, y0,
x1, y1, z_min, z_max, nx, ny, nz, d``; others, such as ``plane_id`` or the synthetic world's
``true_facade_id``, are read when present and never used by the association), and a user's own
GIS model can be exported to the same columns.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from geoseg.errors import check_shape
from slam_bridge.csv_columns import read_columns
from slam_bridge.errors import SlamError

__all__ = ["Facades"]

COLUMNS = ["x0", "y0", "x1", "y1", "z_min", "z_max", "nx", "ny", "nz", "d"]
NORMAL_TOL = 1e-3  # |n| must be 1 within this
PLANE_TOL_M = 0.05  # the footprint edge must lie on its plane within this


@dataclass(frozen=True)
class Facades:
    """Facade rectangles of a building model (module docstring); ``F`` rows.

    Attributes:
        p0: ``(F, 2)`` start of each bottom edge, world metres.
        p1: ``(F, 2)`` its end.
        z_min: ``(F,)`` bottom altitude.
        z_max: ``(F,)`` top altitude.
        normal: ``(F, 3)`` outward unit normal.
        d: ``(F,)`` plane offset, ``normal . X = d``.
        true_facade_id: ``(F,)`` the world's facade each row models (-1: none), for evaluation
            only; -1 everywhere when the table does not say.
    """

    p0: np.ndarray
    p1: np.ndarray
    z_min: np.ndarray
    z_max: np.ndarray
    normal: np.ndarray
    d: np.ndarray
    true_facade_id: np.ndarray

    def __post_init__(self) -> None:
        F = self.d.shape[0]
        for name, tail in (("p0", (2,)), ("p1", (2,)), ("normal", (3,))):
            check_shape(name, getattr(self, name), (F, *tail))
        for name in ("p0", "p1", "z_min", "z_max", "normal", "d"):
            bad = ~np.isfinite(np.asarray(getattr(self, name), dtype=np.float64))
            if bad.any():
                row = int(np.flatnonzero(bad.reshape(F, -1).any(axis=1))[0])
                raise SlamError(f"facade {row}: {name} is not a finite number")
        norm = np.linalg.norm(self.normal, axis=1)
        if np.any(np.abs(norm - 1.0) > NORMAL_TOL):
            row = int(np.argmax(np.abs(norm - 1.0)))
            raise SlamError(f"facade {row}: its normal has length {norm[row]:.4f}, expected 1")
        if np.any(np.linalg.norm(self.p1 - self.p0, axis=1) <= 0):
            raise SlamError("a facade has a bottom edge of zero length")
        if np.any(self.z_max <= self.z_min):
            raise SlamError("a facade has z_max <= z_min")
        off = np.abs(self.plane_residual(self.p0))
        if np.any(off > PLANE_TOL_M):
            row = int(np.argmax(off))
            raise SlamError(f"facade {row}: its edge lies {off[row]:.3f} m off its plane n . X = d")

    def __len__(self) -> int:
        return int(self.d.shape[0])

    def plane_residual(self, xy: np.ndarray) -> np.ndarray:
        """``n_xy . xy - d`` of each facade's own point ``xy`` ``(F, 2)`` (0 on the plane)."""
        return np.einsum("fi,fi->f", self.normal[:, :2], xy) - self.d

    @classmethod
    def read_csv(cls, path: str | Path) -> Facades:
        """Read a facade table (module docstring).

        Raises:
            SlamError: no such file, missing columns, non-numeric cells, no facade, non-finite
                or non-unit normals, an edge off its plane, an empty rectangle.
        """
        cols = read_columns(path, COLUMNS, optional=["true_facade_id"])
        if cols["d"].size == 0:
            raise SlamError(f"{path}: no facade")
        truth = cols.get("true_facade_id")
        try:
            return cls(
                p0=np.column_stack([cols["x0"], cols["y0"]]),
                p1=np.column_stack([cols["x1"], cols["y1"]]),
                z_min=cols["z_min"],
                z_max=cols["z_max"],
                normal=np.column_stack([cols["nx"], cols["ny"], cols["nz"]]),
                d=cols["d"],
                true_facade_id=(
                    np.full(cols["d"].size, -1, np.int64)
                    if truth is None
                    else np.nan_to_num(truth, nan=-1).astype(np.int64)
                ),
            )
        except SlamError as err:
            raise SlamError(f"{path}: {err}") from None

    @cached_property
    def _index(self) -> tuple[cKDTree, float]:
        """A k-d tree of the bottom edges' midpoints and the longest half edge."""
        half = 0.5 * np.linalg.norm(self.p1 - self.p0, axis=1)
        return cKDTree(0.5 * (self.p0 + self.p1)), float(half.max())

    def near(
        self, points: np.ndarray, radius_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The (point, facade) pairs closer than ``radius_m``, through a k-d tree of the facades
        (a facade lies within its half length of its midpoint), not the full ``(N, F)`` table.

        Args:
            points: ``(N, 3)`` world points (NaN rows: none).
            radius_m: the largest distance.

        Returns:
            ``(point (K,), facade (K,), distance (K,))``, sorted by point.
        """
        points = np.asarray(points, dtype=np.float64)
        check_shape("points", points, (None, 3))
        ok = np.flatnonzero(np.isfinite(points).all(axis=1))
        tree, half = self._index
        lists = tree.query_ball_point(points[ok, :2], radius_m + half)
        counts = np.fromiter((len(c) for c in lists), np.int64, ok.size)
        pt = np.repeat(ok, counts)
        fc = np.fromiter((f for c in lists for f in c), np.int64, int(counts.sum()))
        if pt.size == 0:
            return pt, fc, np.zeros(0)
        d = self._pair_distances(points[pt], fc)
        keep = d <= radius_m
        return pt[keep], fc[keep], d[keep]

    def _pair_distances(self, X: np.ndarray, facade: np.ndarray) -> np.ndarray:
        """``(K,)`` distance of each point ``X (K, 3)`` to its facade ``(K,)``."""
        p0, edge = self.p0[facade], self.p1[facade] - self.p0[facade]
        rel = X[:, :2] - p0
        s = np.clip(np.einsum("ki,ki->k", rel, edge) / np.einsum("ki,ki->k", edge, edge), 0, 1)
        h = rel - s[:, None] * edge
        z = X[:, 2]
        dz = np.maximum(np.maximum(self.z_min[facade] - z, z - self.z_max[facade]), 0.0)
        return np.sqrt(np.einsum("ki,ki->k", h, h) + dz**2)

    def distances(self, points: np.ndarray, chunk: int = 512) -> np.ndarray:
        """Euclidean distance of each point to each facade rectangle (the full table; the
        association uses :meth:`near`).

        Args:
            points: ``(N, 3)`` world points.

        Returns:
            ``(N, F)`` metres (the distance to the plane where the point faces the rectangle).
        """
        points = np.asarray(points, dtype=np.float64)
        check_shape("points", points, (None, 3))
        F = len(self)
        out = np.empty((points.shape[0], F))
        for a in range(0, points.shape[0], chunk):
            X = points[a : a + chunk]
            pairs = self._pair_distances(np.repeat(X, F, axis=0), np.tile(np.arange(F), len(X)))
            out[a : a + chunk] = pairs.reshape(len(X), F)
        return out
