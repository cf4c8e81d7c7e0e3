"""Nearest-centreline queries: :class:`StreetIndex`, a raster of candidate street segments.

The distance of a point to the nearest street centreline tells road, sidewalk and terrain
apart (:meth:`~geoseg.synth.world.World.ground_class`, so curved kerbs are exact at any
resolution), keeps building lots clear of the streets, and gives the renderer each ground
hit's street, side and arc length (kerbs, markings, parking bays). It is asked about every
ground pixel, hence the precomputed raster and the float32 query.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from geoseg.synth.world_records import Street


class StreetIndex:
    """Nearest-centreline queries through a 1 m raster of candidate segments.

    Each raster cell keeps the (up to) 4 nearest centreline segments within reach of its centre;
    a query computes exact point-segment distances to those 4.

    Args:
        streets: the streets.
        origin: `(2,)` raster corner, world xy.
        shape: raster `(rows, cols)`; row = y, col = x.
        reach: segments further than this from a cell centre are ignored, metres.
    """

    CELL = 1.0
    K = 4

    def __init__(self, streets: list[Street], origin: np.ndarray, shape: tuple[int, int], reach):
        self.origin = np.asarray(origin, dtype=np.float64)
        self.shape = shape
        self.reach = float(reach)
        a_list, b_list, street_list, s0_list = [], [], [], []
        for i, street in enumerate(streets):
            c = street.centerline
            a_list.append(c[:-1])
            b_list.append(c[1:])
            street_list.append(np.full(len(c) - 1, i))
            s0_list.append(street.arclength[:-1])
        self.seg_a = np.concatenate(a_list)
        self.seg_ab = np.concatenate(b_list) - self.seg_a
        self.seg_len2 = np.maximum((self.seg_ab**2).sum(1), 1e-12)
        self.seg_street = np.concatenate(street_list).astype(np.int64)
        self.seg_s0 = np.concatenate(s0_list)
        self.street_length = np.array([s.length for s in streets])
        rows, cols = shape
        best_d = np.full((rows, cols, self.K), np.inf)
        best_i = np.full((rows, cols, self.K), -1, dtype=np.int64)
        for j in range(len(self.seg_a)):
            a, b = self.seg_a[j], self.seg_a[j] + self.seg_ab[j]
            lo = np.floor((np.minimum(a, b) - self.reach - self.origin) / self.CELL).astype(int)
            hi = np.ceil((np.maximum(a, b) + self.reach - self.origin) / self.CELL).astype(int)
            c0, r0 = np.maximum(lo, 0)
            c1, r1 = min(hi[0], cols), min(hi[1], rows)
            if c1 <= c0 or r1 <= r0:
                continue
            cx = self.origin[0] + (np.arange(c0, c1) + 0.5) * self.CELL
            cy = self.origin[1] + (np.arange(r0, r1) + 0.5) * self.CELL
            px, py = np.meshgrid(cx, cy)
            d = self._dist_to(np.stack([px, py], -1), j)
            d = np.where(d <= self.reach, d, np.inf)
            block_d = best_d[r0:r1, c0:c1]
            block_i = best_i[r0:r1, c0:c1]
            all_d = np.concatenate([block_d, d[..., None]], axis=-1)
            all_i = np.concatenate([block_i, np.full(d.shape + (1,), j)], axis=-1)
            order = np.argsort(all_d, axis=-1, kind="stable")[..., : self.K]
            best_d[r0:r1, c0:c1] = np.take_along_axis(all_d, order, -1)
            best_i[r0:r1, c0:c1] = np.take_along_axis(all_i, order, -1)
        for border in (best_d[0], best_d[-1], best_d[:, 0], best_d[:, -1]):
            border[...] = np.inf  # clipped out-of-raster queries land here: nothing in reach
        self.candidates = np.where(np.isfinite(best_d), best_i, -1)
        # candidates that can be the nearest anywhere in the cell (|d(p) - d(centre)| <= 0.71 m)
        slack = np.sqrt(2.0) * self.CELL + 1e-6
        near = (best_d <= best_d[..., :1] + slack) & np.isfinite(best_d)
        self.n_relevant = near.sum(-1).astype(np.int8)

    def _dist_to(self, p: np.ndarray, j: int) -> np.ndarray:
        rel = p - self.seg_a[j]
        t = np.clip((rel @ self.seg_ab[j]) / self.seg_len2[j], 0.0, 1.0)
        return np.linalg.norm(rel - t[..., None] * self.seg_ab[j], axis=-1)

    def query(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Nearest centreline to each point.

        Args:
            xy: `(N, 2)` world xy.

        Returns:
            dist `(N,)` distance (inf beyond reach), side `(N,)` signed distance (> 0 left of the
            street direction; +-inf beyond reach), s `(N,)` arc length along the street (0 beyond
            reach), street `(N,)` int64 index (-1 beyond reach). Distances are float32-exact
            (~0.1 mm).
        """
        xy = np.asarray(xy)
        n = len(xy)
        if xy.dtype == np.float32:  # renderer hits: stay in float32 (~0.1 mm at 1 km)
            local = xy - self.origin.astype(np.float32)
        else:
            local = (np.asarray(xy, dtype=np.float64) - self.origin).astype(np.float32)
        rows, cols = self.shape
        # the raster's border cells are beyond every street's reach: clip into them
        cx = np.clip(np.floor(local[:, 0] / np.float32(self.CELL)), 0, cols - 1).astype(np.int64)
        cy = np.clip(np.floor(local[:, 1] / np.float32(self.CELL)), 0, rows - 1).astype(np.int64)
        flat = cy * cols + cx
        relevant = self._relevant_flat[flat]
        candidates = self._candidates_flat
        best_d2 = np.full(n, np.inf, dtype=np.float32)
        best_seg = np.zeros(n, dtype=np.int64)
        best_t = np.zeros(n, dtype=np.float32)
        best_cross = np.zeros(n, dtype=np.float32)
        table = self._table
        for k in range(self.K):
            rows_k = np.nonzero(relevant > k)[0]
            if len(rows_k) == 0:
                break
            seg = candidates[flat[rows_k], k]
            row = table[seg]
            rx = local[rows_k, 0] - row[:, 0]
            ry = local[rows_k, 1] - row[:, 1]
            t = np.clip((rx * row[:, 2] + ry * row[:, 3]) * row[:, 4], 0.0, 1.0)
            ox = rx - t * row[:, 2]
            oy = ry - t * row[:, 3]
            d2 = ox * ox + oy * oy
            better = d2 < best_d2[rows_k]
            upd = rows_k[better]
            best_d2[upd] = d2[better]
            best_seg[upd] = seg[better]
            best_t[upd] = t[better]
            best_cross[upd] = (row[:, 2] * ry - row[:, 3] * rx)[better]
        dist = np.sqrt(best_d2).astype(np.float64)
        found = np.isfinite(dist)
        side = np.where(best_cross >= 0, dist, -dist)
        s = np.where(found, self.seg_s0[best_seg] + best_t * self._seg_len[best_seg], 0.0)
        street = np.where(found, self.seg_street[best_seg], -1)
        return dist, side, s, street

    @cached_property
    def _table(self) -> np.ndarray:
        """`(S, 5)` float32 per segment: start (raster-local x, y), direction ab, 1/|ab|^2."""
        a = (self.seg_a - self.origin).astype(np.float32)
        return np.concatenate(
            [a, self.seg_ab.astype(np.float32), (1.0 / self.seg_len2)[:, None].astype(np.float32)],
            axis=1,
        )

    @cached_property
    def _candidates_flat(self) -> np.ndarray:
        return self.candidates.reshape(-1, self.K)

    @cached_property
    def _relevant_flat(self) -> np.ndarray:
        return self.n_relevant.ravel()

    @cached_property
    def _seg_len(self) -> np.ndarray:
        return np.sqrt(self.seg_len2)
