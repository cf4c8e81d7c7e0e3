"""The block normal equations of the bundle adjustment (thesis eqs. 1.25-1.28).

:func:`assemble` sums the whitened, robustly weighted rows of the factor families
(:mod:`slam_bridge.ba.factor`) into ``H = [[U + U_offdiag, W], [W^T, V]]`` and the gradient
``g`` (half the gradient and half the Gauss-Newton Hessian of the cost), in blocks: camera
diagonal ``U (Cf, 6, 6)``, camera pairs ``(pairs (Q, 2), U_pairs (Q, 6, 6))`` from rows with
two cameras only, camera-point ``W (N, 6, 3)``, point diagonal ``V (Pf, 3, 3)``, ``g_c (Cf, 6)``,
``g_p (Pf, 3)``. Vectorised over rows (cached padded layouts and segment sums), or, with
``numba``, compiled passes and a family's own ``_normal_equations``; both give the same blocks
up to rounding. The state and its increments: :mod:`slam_bridge.ba.state`. The equations and
the layouts: ``docs/solvers.md`` ("The block normal equations").
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from slam_bridge.ba.compiled import _njit, numba_enabled
from slam_bridge.ba.factor import Factor, FactorBlock
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.geometry.sums import _segment_sum

logger = logging.getLogger(__name__)

__all__ = [
    "NormalEquations",
    "assemble",
    "camera_only_blocks",
    "pair_normal_equations",
    "total_cost",
]


@dataclass
class NormalEquations:
    """Block normal equations of ``0.5 * cost`` (see the module docstring).

    Attributes:
        U: ``(Cf, 6, 6)`` camera diagonal blocks.
        pairs: ``(Q, 2)`` int free camera indices ``(i, j)``, ``i < j``, unique.
        U_pairs: ``(Q, 6, 6)`` off-diagonal blocks ``H[i, j]``.
        W: ``(N, 6, 3)`` camera-point blocks.
        W_cameras: ``(N,)`` int free camera index of each ``W`` block.
        W_points: ``(N,)`` int free point index of each ``W`` block.
        V: ``(Pf, 3, 3)`` point diagonal blocks.
        g_c: ``(Cf, 6)`` camera gradient (of ``0.5 * cost``).
        g_p: ``(Pf, 3)`` point gradient.
        cost: ``sum rho(||r||^2)`` over all valid rows.
        n_invalid: number of invalid rows (e.g. points behind cameras).
        costs: per-family costs, ``{name: cost}``.
    """

    U: np.ndarray
    pairs: np.ndarray
    U_pairs: np.ndarray
    W: np.ndarray
    W_cameras: np.ndarray
    W_points: np.ndarray
    V: np.ndarray
    g_c: np.ndarray
    g_p: np.ndarray
    cost: float
    n_invalid: int = 0
    costs: dict[str, float] = field(default_factory=dict)

    @property
    def num_free_cameras(self) -> int:
        """``Cf``."""
        return self.U.shape[0]

    @property
    def num_free_points(self) -> int:
        """``Pf``."""
        return self.V.shape[0]

    def camera_offdiag(self) -> dict[tuple[int, int], np.ndarray]:
        """The camera-camera off-diagonal blocks as ``{(i, j): (6, 6)}``, ``i < j``."""
        return {(int(i), int(j)): b for (i, j), b in zip(self.pairs, self.U_pairs)}

    def dense(self) -> tuple[np.ndarray, np.ndarray]:
        """Dense ``H`` ``(6Cf + 3Pf, 6Cf + 3Pf)`` and ``g`` ``(6Cf + 3Pf,)``, cameras first.

        For tests and small problems only.
        """
        Cf, Pf = self.num_free_cameras, self.num_free_points
        n = 6 * Cf + 3 * Pf
        H = np.zeros((n, n))
        for i in range(Cf):
            H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += self.U[i]
        for (i, j), b in zip(self.pairs, self.U_pairs):
            H[6 * i : 6 * i + 6, 6 * j : 6 * j + 6] += b
            H[6 * j : 6 * j + 6, 6 * i : 6 * i + 6] += b.T
        o = 6 * Cf
        for p in range(Pf):
            H[o + 3 * p : o + 3 * p + 3, o + 3 * p : o + 3 * p + 3] += self.V[p]
        for c, p, b in zip(self.W_cameras, self.W_points, self.W):
            H[6 * c : 6 * c + 6, o + 3 * p : o + 3 * p + 3] += b
            H[o + 3 * p : o + 3 * p + 3, 6 * c : 6 * c + 6] += b.T
        g = np.concatenate([self.g_c.reshape(-1), self.g_p.reshape(-1)])
        return H, g


def total_cost(factors: Iterable[Factor], state: BAState) -> float:
    """``sum`` of the families' ``cost(state)`` (no Jacobians)."""
    return float(sum(f.cost(state) for f in factors))


_LAYOUT_CACHE: OrderedDict[tuple, tuple[np.ndarray, np.ndarray, int]] = OrderedDict()


def _group_layout(idx: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Padded per-group layout of rows: ``(dest (K,), rows (K,), nmax)`` (cached).

    Row ``rows[q]`` goes to slot ``dest[q]`` of an ``(n * nmax)`` array, groups of ``nmax``
    slots per index; rows with ``idx < 0`` are dropped.
    """
    key = (n, idx.tobytes())
    hit = _LAYOUT_CACHE.get(key)
    if hit is not None:
        _LAYOUT_CACHE.move_to_end(key)
        return hit
    keep = idx >= 0
    rows = np.flatnonzero(keep)
    ki = idx[rows]
    counts = np.bincount(ki, minlength=n)
    nmax = int(counts.max()) if ki.size else 0
    order = np.argsort(ki, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.empty(ki.size, dtype=np.int64)
    slot[order] = np.arange(ki.size) - starts[ki[order]]
    out = (ki * nmax + slot, rows, nmax)
    _LAYOUT_CACHE[key] = out
    if len(_LAYOUT_CACHE) > 32:
        _LAYOUT_CACHE.popitem(last=False)
    return out


def _gram_sum(idx: np.ndarray, X: np.ndarray, a: int, n: int) -> np.ndarray:
    """``out[i] = sum_{m: idx[m] == i} X[m, :, :a]^T X[m]``: ``X (M, k, d)`` -> ``(n, a, d)``.

    Rows are laid out per group (padded to the largest group) so that each group's sum is one
    GEMM; falls back to per-row products + segment sum when padding would more than triple the
    data.
    """
    M, k, d = X.shape
    dest, rows, nmax = _group_layout(idx, n)
    if nmax == 0:
        return np.zeros((n, a, d))
    if n * nmax > 3 * max(rows.size, 1):
        return _segment_sum(idx, np.swapaxes(X[:, :, :a], 1, 2) @ X, n)
    P = np.zeros((n * nmax, k, d))
    P[dest] = X if rows.size == M else X[rows]
    P = P.reshape(n, nmax * k, d)
    return np.swapaxes(P[:, :, :a], 1, 2) @ P


@_njit
def _mirror_kernel(U, V):  # pragma: no cover - compiled
    """Copy the upper triangles of the ``U`` and ``V`` blocks onto their lower ones."""
    for c in range(U.shape[0]):
        for a in range(6):
            for b in range(a):
                U[c, a, b] = U[c, b, a]
    for p in range(V.shape[0]):
        for a in range(3):
            for b in range(a):
                V[p, a, b] = V[p, b, a]


@_njit
def _one_cam_one_point_kernel(Jc, Jp, r, w, ci, pj, U, g_c, V, g_p, W, Wc, Wp):  # pragma: no cover
    """Compiled fast path of :func:`assemble` for ``k = 2`` rows with one camera and one point.

    ``Jc (M, 2, 6)``, ``Jp (M, 2, 3)``, ``r (M, 2)``, ``w (M,)``, free indices ``ci``/``pj (M,)``
    (``-1`` = fixed); adds ``w J^T J`` / ``w J^T r`` into ``U (Cf, 6, 6)``, ``g_c``, ``V (Pf, 3,
    3)``, ``g_p`` (upper triangles, mirrored at the end: ``U`` and ``V`` must start at zero) and
    writes one ``W`` block ``w Jc^T Jp`` per row whose camera and point are both free, in row
    order. ``k`` is fixed at 2 and the loop body is written out (a helper function, even inlined,
    is 3x slower) so that the compiler unrolls the small loops.
    """
    n = 0
    for m in range(r.shape[0]):
        wm = w[m]
        c = ci[m]
        p = pj[m]
        if c >= 0:
            for a in range(6):
                ja0 = Jc[m, 0, a] * wm
                ja1 = Jc[m, 1, a] * wm
                g_c[c, a] += ja0 * r[m, 0] + ja1 * r[m, 1]
                for b in range(a, 6):
                    U[c, a, b] += ja0 * Jc[m, 0, b] + ja1 * Jc[m, 1, b]
        if p >= 0:
            for a in range(3):
                ja0 = Jp[m, 0, a] * wm
                ja1 = Jp[m, 1, a] * wm
                g_p[p, a] += ja0 * r[m, 0] + ja1 * r[m, 1]
                for b in range(a, 3):
                    V[p, a, b] += ja0 * Jp[m, 0, b] + ja1 * Jp[m, 1, b]
            if c >= 0:
                for a in range(6):
                    ja0 = Jc[m, 0, a] * wm
                    ja1 = Jc[m, 1, a] * wm
                    for b in range(3):
                        W[n, a, b] = ja0 * Jp[m, 0, b] + ja1 * Jp[m, 1, b]
                Wc[n] = c
                Wp[n] = p
                n += 1
    _mirror_kernel(U, V)
    return n


def _one_cam_one_point_numba(
    Jc: np.ndarray,
    Jp: np.ndarray,
    r: np.ndarray,
    w: np.ndarray,
    ci: np.ndarray,
    pj: np.ndarray,
    Cf: int,
    Pf: int,
) -> tuple[np.ndarray, ...]:
    """``U, g_c, V, g_p, W, Wc, Wp`` of ``k = 2`` rows with one camera and one point (compiled)."""
    U, g_c = np.zeros((Cf, 6, 6)), np.zeros((Cf, 6))
    V, g_p = np.zeros((Pf, 3, 3)), np.zeros((Pf, 3))
    N = int(np.count_nonzero((ci >= 0) & (pj >= 0)))
    W = np.empty((N, 6, 3))
    Wc = np.empty(N, dtype=np.int64)
    Wp = np.empty(N, dtype=np.int64)
    f64 = np.float64
    _one_cam_one_point_kernel(
        np.ascontiguousarray(Jc, dtype=f64),
        np.ascontiguousarray(Jp, dtype=f64),
        np.ascontiguousarray(r, dtype=f64),
        np.ascontiguousarray(w, dtype=f64),
        np.ascontiguousarray(ci, dtype=np.int64),
        np.ascontiguousarray(pj, dtype=np.int64),
        U,
        g_c,
        V,
        g_p,
        W,
        Wc,
        Wp,
    )
    return U, g_c, V, g_p, W, Wc, Wp


@_njit
def _pair_scatter_kernel(H, g, fi, fj, U, g_c, U_pair):  # pragma: no cover - compiled
    """Per pair ``q`` of free indices ``(fi, fj)`` (``-1`` = fixed): ``U[fi] += H[q, :6, :6]``,
    ``U[fj] += H[q, 6:, 6:]``, the gradients likewise, and ``U_pair[q]`` = the off-diagonal
    block of the lower free index (``H[q, :6, 6:]``, transposed when ``fi > fj``); a pair of one
    camera adds both cross blocks to its diagonal block."""
    for q in range(H.shape[0]):
        a = fi[q]
        b = fj[q]
        for i in range(6):
            if a >= 0:
                g_c[a, i] += g[q, i]
            if b >= 0:
                g_c[b, i] += g[q, 6 + i]
            for j in range(6):
                if a >= 0:
                    U[a, i, j] += H[q, i, j]
                if b >= 0:
                    U[b, i, j] += H[q, 6 + i, 6 + j]
                if a >= 0 and a == b:
                    U[a, i, j] += H[q, i, 6 + j] + H[q, j, 6 + i]
                U_pair[q, i, j] = H[q, i, 6 + j] if a <= b else H[q, j, 6 + i]


def pair_normal_equations(
    cost: float,
    n_invalid: int,
    H: np.ndarray,
    g: np.ndarray,
    cameras: np.ndarray,
    cmap: np.ndarray,
    Cf: int,
    Pf: int,
) -> tuple:
    """The ``_normal_equations`` blocks (see :func:`assemble`) of a point-free family whose rows
    each involve one camera pair, from its per-pair sums.

    Args:
        cost: the family's cost.
        n_invalid: its invalid rows.
        H: ``(Q, 12, 12)`` per pair ``sum w J^T J``, ``J = [J_i | J_j]``.
        g: ``(Q, 12)`` per pair ``sum w J^T r``.
        cameras: ``(Q, 2)`` state indices ``(i, j)`` of each pair.
        cmap: ``(C,)`` free index of each camera (``-1`` = fixed).
        Cf: free cameras.
        Pf: free points.

    Returns:
        ``(cost, n_invalid, U (Cf, 6, 6), g_c (Cf, 6), V (Pf, 3, 3), g_p (Pf, 3), W (0, 6, 3),
        W_cameras (0,), W_points (0,), pairs (Q', 2), U_pairs (Q', 6, 6))``: the off-diagonal
        blocks of the pairs whose two cameras are free, ``pairs[:, 0] < pairs[:, 1]``.
    """
    fi, fj = cmap[cameras[:, 0]], cmap[cameras[:, 1]]
    U, g_c = np.zeros((Cf, 6, 6)), np.zeros((Cf, 6))
    H = np.ascontiguousarray(H, dtype=np.float64)
    U_all = np.empty((H.shape[0], 6, 6))
    _pair_scatter_kernel(H, np.ascontiguousarray(g, dtype=np.float64), fi, fj, U, g_c, U_all)
    both = (fi >= 0) & (fj >= 0) & (fi != fj)
    pairs = np.stack([np.minimum(fi, fj)[both], np.maximum(fi, fj)[both]], axis=1)
    return camera_only_blocks(cost, n_invalid, U, g_c, Pf) + (pairs, U_all[both])


def camera_only_blocks(
    cost: float, n_invalid: int, U: np.ndarray, g_c: np.ndarray, Pf: int
) -> tuple:
    """The ``_normal_equations`` tuple (see :func:`assemble`) of a family without points:
    ``(cost, n_invalid, U, g_c, V = 0 (Pf, 3, 3), g_p = 0 (Pf, 3), W (0, 6, 3), W_cameras (0,),
    W_points (0,))``."""
    no_index = np.zeros(0, dtype=np.int64)
    return (
        cost,
        n_invalid,
        U,
        g_c,
        np.zeros((Pf, 3, 3)),
        np.zeros((Pf, 3)),
        np.zeros((0, 6, 3)),
        no_index,
        no_index,
    )


def assemble(factors: Sequence[Factor] | Iterable[Factor], state: BAState) -> NormalEquations:
    """Evaluate every factor family and assemble the block normal equations.

    Args:
        factors: factor families (objects following :class:`slam_bridge.ba.factor.Factor`).
        state: the current :class:`BAState`.

    Returns:
        The :class:`NormalEquations` of ``0.5 * cost`` restricted to the free parameters.
    """
    cmap, pmap = state.camera_index_map, state.point_index_map
    Cf, Pf = state.free_cameras.size, state.free_points.size
    U = np.zeros((Cf, 6, 6))
    V = np.zeros((Pf, 3, 3))
    g_c = np.zeros((Cf, 6))
    g_p = np.zeros((Pf, 3))
    pair_keys: list[np.ndarray] = []
    pair_blocks: list[np.ndarray] = []
    W_list: list[np.ndarray] = []
    Wc_list: list[np.ndarray] = []
    Wp_list: list[np.ndarray] = []
    cost = 0.0
    n_invalid = 0
    costs: dict[str, float] = {}
    for factor in factors:
        fused = getattr(factor, "_normal_equations", None) if numba_enabled() else None
        out = fused(state, cmap, pmap, Cf, Pf) if fused is not None else None
        if out is not None:  # compiled family: blocks without materialised Jacobians
            c, n_bad, Ub, gcb, Vb, gpb, Wb, Wcb, Wpb = out[:9]
            if len(out) == 11 and out[9].shape[0]:  # two-camera rows: off-diagonal blocks
                pair_keys.append(out[9])
                pair_blocks.append(out[10])
            if not np.isfinite(c):
                raise SlamError(f"{factor.name}: non-finite cost (NaN/inf residuals)")
            cost += c
            costs[factor.name] = costs.get(factor.name, 0.0) + c
            n_invalid += n_bad
            U += Ub
            g_c += gcb
            V += Vb
            g_p += gpb
            if Wb.shape[0]:
                W_list.append(Wb)
                Wc_list.append(Wcb)
                Wp_list.append(Wpb)
            continue
        blk = factor.evaluate(state)
        if not isinstance(blk, FactorBlock):
            raise SlamError(f"{type(factor).__name__}.evaluate must return a FactorBlock")
        s = blk.squared_norms()
        rho = blk.kernel.rho(s)
        w = blk.kernel.weight(s)
        if blk.valid is not None:
            rho = np.where(blk.valid, rho, 0.0)
            w = np.where(blk.valid, w, 0.0)
        c = float(np.sum(rho))
        if not np.isfinite(c):
            raise SlamError(f"{blk.name}: non-finite cost (NaN/inf residuals)")
        cost += c
        costs[blk.name] = costs.get(blk.name, 0.0) + c
        n_invalid += blk.n_invalid
        r = blk.residuals[:, :, None]  # (M, k, 1)
        a = blk.cameras.shape[1]
        if a == 1 and blk.points is not None:
            # fast path for one camera and one point per row (reprojection-like factors)
            ci, pj = cmap[blk.cameras[:, 0]], pmap[blk.points]
            Jc, Jp = blk.J_cameras[:, 0], blk.J_points
            if (
                numba_enabled() and r.shape[1] == 2
            ):  # one pass over the rows instead of ~10 NumPy passes
                Ub, gcb, Vb, gpb, Wb, Wcb, Wpb = _one_cam_one_point_numba(
                    Jc, Jp, blk.residuals, w, ci, pj, Cf, Pf
                )
                U += Ub
                g_c += gcb
                V += Vb
                g_p += gpb
                if Wb.shape[0]:
                    W_list.append(Wb)
                    Wc_list.append(Wcb)
                    Wp_list.append(Wpb)
                continue
            sw = np.sqrt(w)[:, None, None]
            if np.any(ci >= 0):  # [U | g_c] = sum [Jc r]^T w [Jc r] per camera, one GEMM each
                G = _gram_sum(ci, np.concatenate([Jc, r], axis=2) * sw, 6, Cf)
                U += G[:, :, :6]
                g_c += G[:, :, 6]
            if np.any(pj >= 0):  # [V | g_p] per point
                G = _gram_sum(pj, np.concatenate([Jp, r], axis=2) * sw, 3, Pf)
                V += G[:, :, :3]
                g_p += G[:, :, 3]
            JcT_w = np.swapaxes(Jc, 1, 2) * w[:, None, None]  # (M, 6, k)
            keep = (ci >= 0) & (pj >= 0)
            if np.any(keep):
                if np.all(keep):
                    W_list.append(JcT_w @ Jp)
                else:
                    W_list.append(JcT_w[keep] @ Jp[keep])
                Wc_list.append(ci[keep])
                Wp_list.append(pj[keep])
            continue
        free_c = [cmap[blk.cameras[:, s_]] for s_ in range(a)]
        # w-weighted transposed camera Jacobians, (M, 6, k)
        JcT_w = [np.swapaxes(blk.J_cameras[:, s_], 1, 2) * w[:, None, None] for s_ in range(a)]
        for sa in range(a):
            ci = free_c[sa]
            if not np.any(ci >= 0):
                continue
            Jc = blk.J_cameras[:, sa]
            # diagonal block and gradient share one segment sum: (M, 36 + 6)
            both = np.concatenate(
                [(JcT_w[sa] @ Jc).reshape(-1, 36), (JcT_w[sa] @ r).reshape(-1, 6)], axis=1
            )
            summed = _segment_sum(ci, both, Cf)
            U += summed[:, :36].reshape(Cf, 6, 6)
            g_c += summed[:, 36:]
            for sb in range(a):
                if sb == sa:
                    continue
                cj = free_c[sb]
                pair = (ci >= 0) & (cj >= 0)
                if not np.any(pair):
                    continue
                Jab = JcT_w[sa][pair] @ blk.J_cameras[pair, sb]
                cib, cjb = ci[pair], cj[pair]
                same = cib == cjb
                if np.any(same):
                    U += _segment_sum(cib[same], Jab[same], Cf)
                # keep only the i < j orientation (the other slot order gives the transpose)
                lower = cib < cjb
                if np.any(lower):
                    pair_keys.append(np.stack([cib[lower], cjb[lower]], axis=1))
                    pair_blocks.append(Jab[lower])
        if blk.points is not None:
            pj = pmap[blk.points]
            if np.any(pj >= 0):
                Jp = blk.J_points
                JpT_w = np.swapaxes(Jp, 1, 2) * w[:, None, None]
                both = np.concatenate(
                    [(JpT_w @ Jp).reshape(-1, 9), (JpT_w @ r).reshape(-1, 3)], axis=1
                )
                summed = _segment_sum(pj, both, Pf)
                V += summed[:, :9].reshape(Pf, 3, 3)
                g_p += summed[:, 9:]
                for sa in range(a):
                    ci = free_c[sa]
                    keep = (pj >= 0) & (ci >= 0)
                    if not np.any(keep):
                        continue
                    Wm = JcT_w[sa] @ Jp  # (M, 6, 3); rows selected after the product
                    if np.all(keep):
                        W_list.append(Wm)
                        Wc_list.append(ci)
                        Wp_list.append(pj)
                    else:
                        W_list.append(Wm[keep])
                        Wc_list.append(ci[keep])
                        Wp_list.append(pj[keep])
    if pair_keys:
        keys = np.concatenate(pair_keys)
        blocks = np.concatenate(pair_blocks)
        uniq, inv = np.unique(keys[:, 0] * max(Cf, 1) + keys[:, 1], return_inverse=True)
        U_pairs = _segment_sum(inv.reshape(-1), blocks, uniq.size)
        pairs = np.stack([uniq // max(Cf, 1), uniq % max(Cf, 1)], axis=1).astype(np.int64)
    else:
        pairs = np.zeros((0, 2), dtype=np.int64)
        U_pairs = np.zeros((0, 6, 6))
    if W_list:
        W = np.concatenate(W_list) if len(W_list) > 1 else W_list[0]
        Wc = np.concatenate(Wc_list)
        Wp = np.concatenate(Wp_list)
    else:
        W = np.zeros((0, 6, 3))
        Wc = np.zeros(0, dtype=np.int64)
        Wp = np.zeros(0, dtype=np.int64)
    return NormalEquations(
        U=U,
        pairs=pairs,
        U_pairs=U_pairs,
        W=W,
        W_cameras=Wc,
        W_points=Wp,
        V=V,
        g_c=g_c,
        g_p=g_p,
        cost=cost,
        n_invalid=n_invalid,
        costs=costs,
    )
