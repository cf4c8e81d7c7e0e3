"""The reduced camera system (thesis eqs. 1.28-1.32), solved by Cholesky.

The points are eliminated from the block normal equations (:mod:`slam_bridge.ba.normal_equations`,
``S = A - W V^-1 W^T``), ``S`` is summed by point chunks with one batched GEMM per chunk size
and factorised densely, banded, or with a banded pose-graph chain split off (:class:`_ChainSplit`);
:class:`SchurFactorization` keeps the factor for several right-hand sides (the barrier solver
needs two per step). Damping ``"additive"`` (``H + lambda I``) or ``"marquardt"``
(``H + lambda diag(H)``, the diagonal clipped below at ``1e-12``); :func:`camera_covariance`
gives the diagonal blocks of ``S^-1`` (eq. 1.32). With ``numba``
(:data:`slam_bridge.ba.compiled.USE_NUMBA`) compiled kernels do the per-block work, with the same
results up to rounding. The elimination, the chunk layout and the choice of factorisation:
``docs/solvers.md`` ("The reduced camera system").
"""

from __future__ import annotations

import functools
import logging
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from slam_bridge.ba.compiled import _njit, numba_enabled
from slam_bridge.ba.normal_equations import NormalEquations
from slam_bridge.errors import SlamError
from slam_bridge.geometry.sums import _segment_sum

logger = logging.getLogger(__name__)

__all__ = [
    "SchurFactorization",
    "schur_solve",
    "reduced_camera_matrix",
    "camera_covariance",
    "latest_camera_covariance",
    "DAMPING_MODES",
]

DAMPING_MODES = ("additive", "marquardt")
_MIN_DIAG = 1e-12


@dataclass
class _ChunkGroup:
    """Chunks touching the same number ``L`` of cameras: one batched GEMM."""

    L: int  # cameras per chunk (local slots)
    n: int  # chunks in the group
    row0: int  # first line of the group in the padded layout
    cams: np.ndarray  # (n, L) camera of each local slot (increasing)
    target: np.ndarray  # (n * L * L,) flat camera-pair index in a (Cf + 1)^2 grid


@dataclass
class _ChunkStructure:
    """Point chunks of one sparsity pattern (see :func:`_chunk_structure`)."""

    chunk: int  # points per chunk
    lines: int  # lines (of 6 values) of the padded layout
    groups: list[_ChunkGroup]
    row: np.ndarray  # (3N,) line of each block's Z^T lines in the padded layout
    span: int = 0  # largest (last - first) free camera of one point: S's block half-bandwidth
    reach: np.ndarray | None = None  # (Cf,) lowest free camera sharing a point with each camera
    buffer: tuple | None = None  # (padded layout A, chunk sums G per group), compiled path


#: use the banded Cholesky when ``6 Cf >= BANDED_RATIO * (upper bandwidth + 1)`` (below, the
#: dense LAPACK factorisation is as fast)
BANDED_RATIO = 6

_BAND_CACHE: OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()


def _upper_band(S: np.ndarray, u: int) -> np.ndarray:
    """LAPACK upper band storage ``ab (u + 1, n)``, ``ab[u + i - j, j] = S[i, j]`` (``i <= j``)."""
    n = S.shape[0]
    hit = _BAND_CACHE.get((n, u))
    if hit is None:
        j = np.broadcast_to(np.arange(n), (u + 1, n))
        i = j - u + np.arange(u + 1)[:, None]
        keep = i >= 0
        hit = (np.flatnonzero(keep), (i * n + j)[keep])
        _BAND_CACHE[(n, u)] = hit
        if len(_BAND_CACHE) > _CACHE_SIZE:
            _BAND_CACHE.popitem(last=False)
    dst, src = hit
    ab = np.zeros((u + 1, n))
    ab.reshape(-1)[dst] = S.reshape(-1)[src]
    return ab


_STRUCT_CACHE: OrderedDict[tuple, _ChunkStructure] = OrderedDict()
_LAST_STRUCT: list = []  # [(sizes, W_cameras, W_points, structure)] of the latest call
_CACHE_SIZE = 8
#: points per chunk of the reduced-system product (see the module docstring)
CHUNK_POINTS = 32


def _set_last_struct(
    sizes: tuple, W_cameras: np.ndarray, W_points: np.ndarray, st: _ChunkStructure
) -> None:
    """Remember the latest structure; the previous one drops its work buffers (several MB each
    on large windows; only the structure in use needs them)."""
    if _LAST_STRUCT and _LAST_STRUCT[0][3] is not st:
        _LAST_STRUCT[0][3].buffer = None
    _LAST_STRUCT[:] = [(sizes, W_cameras.copy(), W_points.copy(), st)]


def _chunk_structure(
    W_cameras: np.ndarray, W_points: np.ndarray, Cf: int, Pf: int, chunk: int = CHUNK_POINTS
) -> _ChunkStructure:
    """Group the points in chunks of ``chunk`` points sorted by earliest, then latest camera,
    and the chunks in groups by the number of cameras they touch.

    In a keyframe window the cameras of a point are a short run of successive keyframes, so a
    chunk of points with nearby first and last cameras touches few cameras and its contribution
    ``A^T A`` is a small dense GEMM with little padding. Chunks with the same ``L`` share one
    batched GEMM, with far less padding than chunks of same-length tracks (which span the
    whole window; the figures are in ``docs/lessons.md``). Any other pattern stays
    correct (``L`` just grows; the chunks shrink when the padding gets large).
    """
    last = _LAST_STRUCT[0] if _LAST_STRUCT else None
    if (
        last is not None
        and last[0] == (Cf, Pf, chunk)
        and np.array_equal(last[1], W_cameras)
        and np.array_equal(last[2], W_points)
    ):  # same pattern as the previous call (every LM iteration): no hashing of the key
        return last[3]
    key = (Cf, Pf, chunk, W_cameras.tobytes(), W_points.tobytes())
    hit = _STRUCT_CACHE.get(key)
    if hit is not None:
        _STRUCT_CACHE.move_to_end(key)
        _set_last_struct((Cf, Pf, chunk), W_cameras, W_points, hit)
        return hit
    minc = np.full(Pf, Cf, dtype=np.int64)
    np.minimum.at(minc, W_points, W_cameras)
    maxc = np.full(Pf, -1, dtype=np.int64)
    np.maximum.at(maxc, W_points, W_cameras)
    porder = np.lexsort((np.arange(Pf), maxc, minc))
    rank = np.empty(Pf, dtype=np.int64)
    rank[porder] = np.arange(Pf)
    N = W_points.size
    while True:
        # a pattern without locality makes L large: shrink the chunks until the padded layout
        # holds at most ~8x the blocks (chunk = 1 is one GEMM per point)
        p_chunk, p_pos = rank // chunk, rank % chunk
        n_chunks = max(int(-(-Pf // chunk)), 1)
        e_chunk = p_chunk[W_points]
        pair = e_chunk * Cf + W_cameras
        uniq, inv = np.unique(pair, return_inverse=True)
        u_chunk, u_cam = uniq // Cf, uniq % Cf
        first = np.searchsorted(u_chunk, np.arange(n_chunks))
        u_local = np.arange(uniq.size) - first[u_chunk]
        Lc = np.maximum(np.bincount(u_chunk, minlength=n_chunks), 1)  # cameras per chunk
        if chunk == 1 or chunk * int(Lc.sum()) <= 8 * max(N, 1):
            break
        chunk = max(chunk // 2, 1)
    cams = np.full((n_chunks, int(Lc.max())), Cf, dtype=np.int64)
    cams[u_chunk, u_local] = u_cam
    # chunks ordered by L, each taking 3 chunk L lines: line (pos 3 + j) L + local of chunk c
    corder = np.argsort(Lc, kind="stable")
    size = 3 * chunk * Lc[corder]
    base = np.empty(n_chunks, dtype=np.int64)
    base[corder] = np.cumsum(size) - size
    e_local, e_pos = u_local[inv], p_pos[W_points]
    row = (
        base[e_chunk][:, None]
        + ((e_pos[:, None] * 3 + np.arange(3)) * Lc[e_chunk][:, None])
        + e_local[:, None]
    ).reshape(-1)
    groups = []
    for L in np.unique(Lc):
        idx = corder[Lc[corder] == L]
        g_cams = np.ascontiguousarray(cams[idx, :L])
        target = (g_cams[:, :, None] * (Cf + 1) + g_cams[:, None, :]).reshape(-1)
        groups.append(_ChunkGroup(int(L), idx.size, int(base[idx[0]]), g_cams, target))
    seen = maxc >= 0
    span = int((maxc[seen] - minc[seen]).max()) if np.any(seen) else 0
    reach = np.arange(Cf, dtype=np.int64)
    np.minimum.at(reach, W_cameras, minc[W_points])
    s = _ChunkStructure(chunk, int(size.sum()), groups, row, span, reach)
    _STRUCT_CACHE[key] = s
    if len(_STRUCT_CACHE) > _CACHE_SIZE:
        _STRUCT_CACHE.popitem(last=False)
    _set_last_struct((Cf, Pf, chunk), W_cameras, W_points, s)
    return s


@_njit
def _z_kernel(W, W_points, Linv, row, A):  # pragma: no cover - compiled
    """``Z_e^T = Linv[p_e] W[e]^T`` (``Linv`` lower triangular), line ``j`` written to
    ``A[row[3 e + j]]`` (the padded chunk layout)."""
    for e in range(W.shape[0]):
        p = W_points[e]
        for j in range(3):
            o = row[3 * e + j]
            for a in range(6):
                z = 0.0
                for i in range(j + 1):
                    z += Linv[p, j, i] * W[e, a, i]
                A[o, a] = z


@_njit
def _scatter_chunks_kernel(G, cams, S):  # pragma: no cover - compiled
    """``S[block(c_i, c_j)] -= G[chunk, block(i, j)]`` for every chunk and local camera pair.

    ``G (n_chunks, 6L, 6L)`` chunk sums, ``cams (n_chunks, L)`` (``Cf`` = padding, placed after
    the real slots, which are in increasing camera order), ``S (6Cf, 6Cf)``. Only ``i <= j`` is
    read; the ``(j, i)`` block is written as the transpose.
    """
    Cf = S.shape[0] // 6
    for ch in range(G.shape[0]):
        for i in range(cams.shape[1]):
            ci = cams[ch, i]
            if ci >= Cf:
                break
            for j in range(i, cams.shape[1]):
                cj = cams[ch, j]
                if cj >= Cf:
                    break
                for a in range(6):
                    for b in range(6):
                        g = G[ch, 6 * i + a, 6 * j + b]
                        S[6 * ci + a, 6 * cj + b] -= g
                        if i != j:
                            S[6 * cj + b, 6 * ci + a] -= g


@_njit
def _vinv_kernel(Linv, v, out):  # pragma: no cover - compiled
    """``out[p] = Linv[p]^T Linv[p] v[p] = V_p^-1 v[p]`` (``Linv`` lower triangular)."""
    for p in range(v.shape[0]):
        y0 = Linv[p, 0, 0] * v[p, 0]
        y1 = Linv[p, 1, 0] * v[p, 0] + Linv[p, 1, 1] * v[p, 1]
        y2 = Linv[p, 2, 0] * v[p, 0] + Linv[p, 2, 1] * v[p, 1] + Linv[p, 2, 2] * v[p, 2]
        out[p, 0] = Linv[p, 0, 0] * y0 + Linv[p, 1, 0] * y1 + Linv[p, 2, 0] * y2
        out[p, 1] = Linv[p, 1, 1] * y1 + Linv[p, 2, 1] * y2
        out[p, 2] = Linv[p, 2, 2] * y2


@_njit
def _rhs_kernel(W, W_cameras, W_points, x, b):  # pragma: no cover - compiled
    """``b[c_e] -= W[e] x[p_e]`` for every block ``e`` (``b_c - W V^-1 b_p``, ``x = V^-1 b_p``)."""
    for e in range(W.shape[0]):
        c = W_cameras[e]
        p = W_points[e]
        for a in range(6):
            b[c, a] -= W[e, a, 0] * x[p, 0] + W[e, a, 1] * x[p, 1] + W[e, a, 2] * x[p, 2]


@_njit
def _back_kernel(W, W_cameras, W_points, dc, t):  # pragma: no cover - compiled
    """``t[p_e] -= W[e]^T dc[c_e]`` for every block ``e`` (``b_p - W^T dc``, eq. 1.30)."""
    for e in range(W.shape[0]):
        c = W_cameras[e]
        p = W_points[e]
        for j in range(3):
            z = 0.0
            for a in range(6):
                z += W[e, a, j] * dc[c, a]
            t[p, j] -= z


@_njit
def _chol_inv3_kernel(V, Li, pd):  # pragma: no cover - compiled
    """Compiled :func:`_chol_inv3` (same thresholds); ``Li`` and ``pd`` are written."""
    for p in range(V.shape[0]):
        scale = 1e-300
        for i in range(3):
            for j in range(3):
                v = abs(V[p, i, j])
                if v > scale:
                    scale = v
        tiny = 1e-13 * scale
        a, b, c = V[p, 0, 0], V[p, 0, 1], V[p, 0, 2]
        d, e, f = V[p, 1, 1], V[p, 1, 2], V[p, 2, 2]
        ok = a > tiny
        l00 = np.sqrt(a) if ok else 1.0
        l10, l20 = b / l00, c / l00
        q11 = d - l10 * l10
        ok = ok and q11 > tiny
        l11 = np.sqrt(q11) if ok else 1.0
        l21 = (e - l20 * l10) / l11
        q22 = f - l20 * l20 - l21 * l21
        ok = ok and q22 > tiny and np.isfinite(q22)
        pd[p] = ok
        for i in range(3):
            for j in range(3):
                Li[p, i, j] = 0.0
        if ok:
            l22 = np.sqrt(q22)
            m00, m11, m22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
            m10 = -l10 * m00 * m11
            Li[p, 0, 0] = m00
            Li[p, 1, 0] = m10
            Li[p, 1, 1] = m11
            Li[p, 2, 0] = -(l20 * m00 + l21 * m10) * m22
            Li[p, 2, 1] = -l21 * m11 * m22
            Li[p, 2, 2] = m22


def _chol_inv3(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``L^-1`` of ``V = L L^T`` for symmetric ``(P, 3, 3)`` blocks (closed form), and a mask of
    the positive-definite blocks (``L^-1`` is 0 for the others)."""
    if numba_enabled():
        Li = np.empty((V.shape[0], 3, 3))
        pd = np.empty(V.shape[0], dtype=bool)
        _chol_inv3_kernel(np.ascontiguousarray(V, dtype=np.float64), Li, pd)
        return Li, pd
    a, b, c = V[:, 0, 0], V[:, 0, 1], V[:, 0, 2]
    d, e, f = V[:, 1, 1], V[:, 1, 2], V[:, 2, 2]
    scale = np.maximum(np.abs(V).reshape(V.shape[0], -1).max(axis=1), 1e-300)
    tiny = 1e-13 * scale
    pd = a > tiny
    l00 = np.sqrt(np.where(pd, a, 1.0))
    l10, l20 = b / l00, c / l00
    q11 = d - l10 * l10
    pd &= q11 > tiny
    l11 = np.sqrt(np.where(pd, q11, 1.0))
    l21 = (e - l20 * l10) / l11
    q22 = f - l20 * l20 - l21 * l21
    pd &= (q22 > tiny) & np.isfinite(q22)
    l22 = np.sqrt(np.where(pd, q22, 1.0))
    Li = np.zeros_like(V)
    m00, m11, m22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
    m10 = -l10 * m00 * m11
    Li[:, 0, 0] = m00
    Li[:, 1, 0] = m10
    Li[:, 1, 1] = m11
    Li[:, 2, 0] = -(l20 * m00 + l21 * m10) * m22
    Li[:, 2, 1] = -l21 * m11 * m22
    Li[:, 2, 2] = m22
    Li[~pd] = 0.0
    return Li, pd


def _inv_sym3(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form inverse of symmetric ``(P, 3, 3)`` blocks and a positive-definiteness mask."""
    a, b, c = V[:, 0, 0], V[:, 0, 1], V[:, 0, 2]
    d, e, f = V[:, 1, 1], V[:, 1, 2], V[:, 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    Cc = b * e - c * d
    det = a * A + b * B + c * Cc
    m2 = a * d - b * b
    pd = (a > 0) & (m2 > 0) & (det > 0) & np.isfinite(det)
    scale = np.abs(V).reshape(V.shape[0], -1).max(axis=1)
    pd &= det > 1e-14 * scale**3
    inv_det = np.where(pd, 1.0 / np.where(pd, det, 1.0), 0.0)
    out = np.empty_like(V)
    out[:, 0, 0] = A
    out[:, 0, 1] = out[:, 1, 0] = B
    out[:, 0, 2] = out[:, 2, 0] = Cc
    out[:, 1, 1] = a * f - c * c
    out[:, 1, 2] = out[:, 2, 1] = b * c - a * e
    out[:, 2, 2] = m2
    out *= inv_det[:, None, None]
    return out, pd


def _damp(blocks: np.ndarray, damping: float, mode: str) -> np.ndarray:
    if damping == 0.0:
        return blocks
    n = blocks.shape[-1]
    idx = np.arange(n)
    out = blocks.copy()
    if mode == "additive":
        out[:, idx, idx] += damping
    else:
        out[:, idx, idx] += damping * np.maximum(blocks[:, idx, idx], _MIN_DIAG)
    return out


#: chain split (:class:`_ChainSplit`): the chain's largest block half-bandwidth and the most
#: chain cameras the rest may couple to
SPLIT_BAND = 2


def _chain_split_point(reach: np.ndarray, band: int = SPLIT_BAND) -> tuple[int, int]:
    """Where a block-banded chain of cameras ends in ``S`` (see :class:`_ChainSplit`).

    Args:
        reach: ``(Cf,)`` lowest camera coupled to each camera (``reach[j] <= j``).
        band: largest block half-bandwidth of the chain, and most of its last cameras that the
            rest may couple to.

    Returns:
        ``(m, r)``: the chain is cameras ``0 .. m - 1`` and the rest couples only to its last
        ``r`` cameras; ``(0, 0)`` when no chain of at least a third of the cameras (and 3)
        exists, where splitting would not pay for its extra solves.
    """
    Cf = reach.size
    prof = np.arange(Cf) - reach
    # chain_ok[m]: cameras 0 .. m - 1 have half-bandwidth <= band; tail[m] = min reach[m:]
    chain_ok = np.concatenate([[True], np.maximum.accumulate(prof) <= band])
    tail = np.concatenate([np.minimum.accumulate(reach[::-1])[::-1], [Cf]])
    m_all = np.arange(Cf + 1)
    good = chain_ok & (tail >= m_all - band) & (m_all < Cf)
    m = int(np.flatnonzero(good).max(initial=0))
    if m < max(3, Cf // 3):
        return 0, 0
    return m, int(max(m - tail[m], 0))


def _factor_layout(reach: np.ndarray, pairs: np.ndarray) -> tuple[int, int, int]:
    """``(span, m, r)`` of ``S``: its block half-bandwidth and :func:`_chain_split_point`, from
    each camera's lowest point-sharing camera ``reach (Cf,)`` and the camera pairs ``(Q, 2)``
    (``i < j``). Cached by pattern: every solver step of a window asks again."""
    return _factor_layout_cached(
        np.ascontiguousarray(reach, dtype=np.int64).tobytes(),
        np.ascontiguousarray(pairs, dtype=np.int64).tobytes(),
    )


@functools.lru_cache(maxsize=_CACHE_SIZE)
def _factor_layout_cached(reach_bytes: bytes, pairs_bytes: bytes) -> tuple[int, int, int]:
    reach = np.frombuffer(reach_bytes, dtype=np.int64).copy()
    pairs = np.frombuffer(pairs_bytes, dtype=np.int64).reshape(-1, 2)
    if pairs.shape[0]:
        np.minimum.at(reach, pairs[:, 1], pairs[:, 0])
    span = int(np.max(np.arange(reach.size) - reach))
    return (span, *_chain_split_point(reach))


class _ChainSplit:
    """Cholesky of ``S`` when its first ``m`` cameras form a block-banded chain (the pose-graph
    window of a hybrid, fig. 3.3: each camera coupled to the next by its link) that the other
    cameras touch only through its last ``r`` cameras::

        S = [[A, B], [B^T, D]],   B nonzero in A's last 6r rows only,
        D' = D - B_r^T (A^-1)_rr B_r,       A banded (LAPACK ``pbtrf``), D' dense

    so the dense factorisation shrinks from ``6 Cf`` to ``6 (Cf - m)`` (a pose-graph window of
    20 of 40 cameras: 8x fewer flops) and ``(A^-1)_rr`` costs ``6r`` banded solves. Solve:
    ``x_D = D'^-1 (b_D - B_r^T (A^-1 b_A)_r)``, ``x_A = A^-1 (b_A - E_r B_r x_D)``.
    """

    def __init__(self, S: np.ndarray, m: int, r: int) -> None:
        self.n_A = 6 * m
        self.n_r = 6 * r
        prof = 6 * SPLIT_BAND + 5
        self.cho_A = (
            scipy.linalg.cholesky_banded(
                _upper_band(np.ascontiguousarray(S[: self.n_A, : self.n_A]), prof),
                lower=False,
                check_finite=False,
            ),
            False,
        )
        self.r0 = self.n_A - self.n_r  # first row of A that D couples to
        self.B = np.ascontiguousarray(S[self.r0 : self.n_A, self.n_A :])
        E = np.zeros((self.n_A, self.n_r))
        E[self.r0 :] = np.eye(self.n_r)
        Y = scipy.linalg.cho_solve_banded(self.cho_A, E, check_finite=False)[self.r0 :]
        D = S[self.n_A :, self.n_A :] - self.B.T @ (Y @ self.B)
        self.cho_D = scipy.linalg.cho_factor(D, lower=False, check_finite=False)
        self.finite = bool(np.all(np.isfinite(self.cho_A[0])) and np.all(np.isfinite(D)))

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``S^-1 b`` for ``b (6Cf,)`` or ``(6Cf, k)``."""
        bA, bD = b[: self.n_A], b[self.n_A :]
        yA = scipy.linalg.cho_solve_banded(self.cho_A, bA, check_finite=False)
        xD = scipy.linalg.cho_solve(self.cho_D, bD - self.B.T @ yA[self.r0 :], check_finite=False)
        bA = bA.copy()
        bA[self.r0 :] -= self.B @ xD
        xA = scipy.linalg.cho_solve_banded(self.cho_A, bA, check_finite=False)
        return np.concatenate([xA, xD])


class SchurFactorization:
    """Factorised reduced camera system of one (damped) normal-equations matrix.

    Args:
        neq: the block normal equations (only ``U``, ``pairs``, ``U_pairs``, ``W*``, ``V`` used).
        damping: ``lambda >= 0``.
        mode: ``"additive"`` or ``"marquardt"`` (module docstring).

    Raises:
        SlamError: if a point block or the reduced system is not positive definite (e.g. a
            free point seen by too few cameras without damping, or an unfixed gauge).
    """

    def __init__(self, neq: NormalEquations, damping: float = 0.0, mode: str = "additive") -> None:
        if mode not in DAMPING_MODES:
            raise SlamError(f"mode: expected one of {DAMPING_MODES}, got {mode!r}")
        if not np.isfinite(damping) or damping < 0:
            raise SlamError(f"damping: expected a finite number >= 0, got {damping}")
        self.neq = neq
        self.damping = float(damping)
        self.mode = mode
        Cf, Pf = neq.num_free_cameras, neq.num_free_points
        self.Cf, self.Pf = Cf, Pf
        U = _damp(neq.U, self.damping, mode)
        V = _damp(neq.V, self.damping, mode)
        self._compiled = numba_enabled() and Pf > 0  # fixed for the factorisation's lifetime
        N = neq.W.shape[0]
        if N and (
            neq.W_cameras.shape != (N,)
            or neq.W_points.shape != (N,)
            or min(neq.W_cameras.min(), neq.W_points.min()) < 0
            or neq.W_cameras.max() >= Cf
            or neq.W_points.max() >= Pf
        ):  # the compiled kernels index without bounds checks
            raise SlamError("W_cameras/W_points: expected (N,) free indices within (Cf, Pf)")
        if Pf:
            self._Linv, pd = _chol_inv3(V)
            if not np.all(pd):
                bad = int(np.flatnonzero(~pd)[0])
                raise SlamError(
                    f"point block {bad} of V is not positive definite (point seen by too few "
                    "cameras, or zero parallax); add damping or fix/remove the point"
                )
            # Z_e^T = L_p^-1 W_e^T (N, 3, 6): W V^-1 W^T = sum_p (sum_e Z_e)(sum_e Z_e)^T; the
            # compiled path writes it straight into the padded layout in _reduced_compiled and
            # its solve works with W and V^-1 (no Z kept)
            self._ZT = (
                None if self._compiled else self._Linv[neq.W_points] @ np.swapaxes(neq.W, 1, 2)
            )
        else:
            self._Linv = np.zeros((0, 3, 3))
            self._ZT = np.zeros((0, 3, 6))
        self._span = 0  # block half-bandwidth of S, set by _reduced
        self._reach = np.arange(Cf, dtype=np.int64)  # likewise (lowest coupled camera)
        self.S = self._reduced(U)
        self._banded = False
        self._split: _ChainSplit | None = None
        if Cf:
            span, m, r = _factor_layout(self._reach, neq.pairs)
            u = 6 * span + 5  # scalar upper bandwidth
            try:
                if 6 * Cf >= BANDED_RATIO * (u + 1):
                    # a keyframe window makes S block-banded: banded Cholesky is O(n u^2)
                    ab = _upper_band(self.S, u)
                    self._cho = (
                        scipy.linalg.cholesky_banded(ab, lower=False, check_finite=False),
                        False,
                    )
                    self._banded = True
                else:
                    if m:
                        self._split = _ChainSplit(self.S, m, r)
                        self._cho = self._split.cho_D
                    else:
                        self._cho = scipy.linalg.cho_factor(self.S, lower=False, check_finite=False)
            except np.linalg.LinAlgError as exc:
                raise SlamError(
                    "reduced camera system is not positive definite: is the gauge fixed "
                    "(enough fixed cameras) and does every free camera see points?"
                ) from exc
            if not np.all(np.isfinite(self._cho[0])) or (
                self._split is not None and not self._split.finite
            ):
                raise SlamError("reduced camera system: non-finite Cholesky factor")
        else:
            self._cho = None

    @property
    def V_inv(self) -> np.ndarray:
        """``(Pf, 3, 3)`` inverses of the damped point blocks."""
        return np.swapaxes(self._Linv, 1, 2) @ self._Linv

    def _reduced(self, U: np.ndarray) -> np.ndarray:
        if self._compiled:
            return self._reduced_compiled(U)
        neq, Cf = self.neq, self.Cf
        S4 = np.zeros((Cf, Cf, 6, 6))
        ar = np.arange(Cf)
        S4[ar, ar] = U
        if neq.pairs.shape[0]:
            S4[neq.pairs[:, 0], neq.pairs[:, 1]] += neq.U_pairs
            S4[neq.pairs[:, 1], neq.pairs[:, 0]] += np.swapaxes(neq.U_pairs, 1, 2)
        if self._ZT.shape[0]:
            st = _chunk_structure(neq.W_cameras, neq.W_points, Cf, self.Pf)
            self._span, self._reach = st.span, st.reach
            # layout (chunk, point slot, j, local camera, i): each row j of Z_e^T is 6 contiguous
            # values; per chunk a (3 chunk, 6L) matrix A with A^T A = the chunk's camera sums
            A = np.zeros((st.lines, 6))
            A[st.row] = self._ZT.reshape(-1, 6)
            blocks, targets = [], []
            for g in st.groups:
                Ag = A[g.row0 : g.row0 + g.n * 3 * st.chunk * g.L]
                Ag = Ag.reshape(g.n, 3 * st.chunk, 6 * g.L)
                G = np.swapaxes(Ag, 1, 2) @ Ag  # (n, 6L, 6L)
                G = G.reshape(g.n, g.L, 6, g.L, 6).transpose(0, 1, 3, 2, 4)
                blocks.append(G.reshape(-1, 6, 6))
                targets.append(g.target)
            Sx = _segment_sum(np.concatenate(targets), np.concatenate(blocks), (Cf + 1) ** 2)
            S4 -= Sx.reshape(Cf + 1, Cf + 1, 6, 6)[:Cf, :Cf]
        return S4.transpose(0, 2, 1, 3).reshape(6 * Cf, 6 * Cf)

    def _reduced_compiled(self, U: np.ndarray) -> np.ndarray:
        """:meth:`_reduced` with compiled kernels: ``Z^T`` written straight into the padded chunk
        layout (kept with the cached structure, whose padding stays zero), one batched GEMM per
        chunk group, and the chunk sums scattered into ``S`` without a segment sum."""
        neq, Cf = self.neq, self.Cf
        S = np.zeros((6 * Cf, 6 * Cf))
        S4 = S.reshape(Cf, 6, Cf, 6)  # view: S4[i, :, j, :] is block (i, j)
        ar = np.arange(Cf)
        S4[ar, :, ar, :] = U
        if neq.pairs.shape[0]:
            S4[neq.pairs[:, 0], :, neq.pairs[:, 1], :] += neq.U_pairs
            S4[neq.pairs[:, 1], :, neq.pairs[:, 0], :] += np.swapaxes(neq.U_pairs, 1, 2)
        if neq.W.shape[0] == 0:
            return S
        st = _chunk_structure(neq.W_cameras, neq.W_points, Cf, self.Pf)
        self._span, self._reach = st.span, st.reach
        # borrow the structure's buffers (every call writes the same entries of A, the rest stays
        # 0; G is overwritten): fresh multi-MB arrays per iteration cost page faults
        (A, Gs), st.buffer = st.buffer or (None, None), None
        if A is None:
            A = np.zeros((st.lines, 6))
            Gs = [np.empty((g.n, 6 * g.L, 6 * g.L)) for g in st.groups]
        try:
            _z_kernel(
                np.ascontiguousarray(neq.W, dtype=np.float64),
                np.ascontiguousarray(neq.W_points, dtype=np.int64),
                self._Linv,
                st.row,
                A,
            )
            for g, G in zip(st.groups, Gs):
                Ag = A[g.row0 : g.row0 + g.n * 3 * st.chunk * g.L]
                Ag = Ag.reshape(g.n, 3 * st.chunk, 6 * g.L)
                np.matmul(np.swapaxes(Ag, 1, 2), Ag, out=G)  # (n, 6L, 6L)
                _scatter_chunks_kernel(G, g.cams, S)
        finally:
            st.buffer = (A, Gs)
        return S

    def solve(self, rhs_c: np.ndarray, rhs_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Solve ``H_damped [dc; dp] = [rhs_c; rhs_p]``.

        Args:
            rhs_c: ``(Cf, 6)``.
            rhs_p: ``(Pf, 3)``.

        Returns:
            ``dc (Cf, 6)``, ``dp (Pf, 3)``.
        """
        neq = self.neq
        rhs_c = np.asarray(rhs_c, dtype=np.float64)
        rhs_p = np.asarray(rhs_p, dtype=np.float64)
        if rhs_c.shape != (self.Cf, 6):
            raise SlamError(f"rhs_c: expected shape ({self.Cf}, 6), got {rhs_c.shape}")
        if rhs_p.shape != (self.Pf, 3):
            raise SlamError(f"rhs_p: expected shape ({self.Pf}, 3), got {rhs_p.shape}")
        if self._compiled:  # dc = S^-1 (b_c - W V^-1 b_p), dp = V^-1 (b_p - W^T dc)
            W = np.ascontiguousarray(neq.W, dtype=np.float64)
            Wc = np.ascontiguousarray(neq.W_cameras, dtype=np.int64)
            Wp = np.ascontiguousarray(neq.W_points, dtype=np.int64)
            rhs_p = np.ascontiguousarray(rhs_p)
            x = np.empty((self.Pf, 3))
            _vinv_kernel(self._Linv, rhs_p, x)
            b = rhs_c.copy()
            _rhs_kernel(W, Wc, Wp, x, b)
            if self._cho is not None:
                dc = self._cho_solve(b.reshape(-1)).reshape(self.Cf, 6)
            else:
                dc = np.zeros((0, 6))
            t = rhs_p.copy()
            _back_kernel(W, Wc, Wp, dc, t)
            _vinv_kernel(self._Linv, t, x)
            return dc, x
        ZT = self._ZT
        y = (self._Linv @ rhs_p[:, :, None])[:, :, 0]  # L^-1 b_p
        b = rhs_c.copy()
        if ZT.shape[0]:  # b_c - W V^-1 b_p = b_c - sum_e Z_e L^-1 b_p
            b -= _segment_sum(neq.W_cameras, (y[neq.W_points][:, None, :] @ ZT)[:, 0, :], self.Cf)
        if self._cho is not None:
            dc = self._cho_solve(b.reshape(-1)).reshape(self.Cf, 6)
        else:
            dc = np.zeros((0, 6))
        if ZT.shape[0]:  # dp = L^-T (L^-1 b_p - sum_e Z_e^T dc)
            y = y - _segment_sum(
                neq.W_points, (ZT @ dc[neq.W_cameras][:, :, None])[:, :, 0], self.Pf
            )
        dp = (np.swapaxes(self._Linv, 1, 2) @ y[:, :, None])[:, :, 0]
        return dc, dp

    def camera_covariance_full(self) -> np.ndarray:
        """``S^-1`` ``(6Cf, 6Cf)`` (eq. 1.32 when undamped)."""
        if self._cho is None:
            return np.zeros((0, 0))
        return self._cho_solve(np.eye(6 * self.Cf))

    def _cho_solve(self, b: np.ndarray) -> np.ndarray:
        """``S^-1 b`` for ``b (6Cf,)`` or ``(6Cf, k)`` with the (dense, banded or split) factor."""
        if self._split is not None:
            return self._split.solve(b)
        if self._banded:
            return scipy.linalg.cho_solve_banded(self._cho, b, check_finite=False)
        return scipy.linalg.cho_solve(self._cho, b, check_finite=False)


def schur_solve(
    neq: NormalEquations,
    rhs_c: np.ndarray,
    rhs_p: np.ndarray,
    damping: float = 0.0,
    mode: str = "additive",
) -> tuple[np.ndarray, np.ndarray]:
    """One-shot solve of ``H_damped [dc; dp] = [rhs_c; rhs_p]``.

    Args:
        neq: block normal equations.
        rhs_c: ``(Cf, 6)`` any right-hand side (e.g. ``-neq.g_c``).
        rhs_p: ``(Pf, 3)``.
        damping: ``lambda >= 0``.
        mode: ``"additive"`` or ``"marquardt"``.

    Returns:
        ``dc (Cf, 6)``, ``dp (Pf, 3)``. Use :class:`SchurFactorization` to reuse the factor.
    """
    return SchurFactorization(neq, damping, mode).solve(rhs_c, rhs_p)


def reduced_camera_matrix(
    neq: NormalEquations, damping: float = 0.0, mode: str = "additive"
) -> np.ndarray:
    """``S = A - W V^-1 W^T`` ``(6Cf, 6Cf)`` (eq. 1.29)."""
    return SchurFactorization(neq, damping, mode).S


def camera_covariance(neq: NormalEquations) -> np.ndarray:
    """Diagonal blocks of ``C_a = (U - W V^-1 W^T)^-1`` (eq. 1.32).

    The normal equations are those of ``0.5 * cost`` with whitened residuals, so ``C_a`` is the
    covariance of the camera increments ``[dw, dT]`` (first-order, unit-variance residuals).

    Args:
        neq: undamped normal equations at the optimum.

    Returns:
        ``(Cf, 6, 6)``.
    """
    fac = SchurFactorization(neq, 0.0)
    full = fac.camera_covariance_full()
    Cf = fac.Cf
    blocks = full.reshape(Cf, 6, Cf, 6)
    ar = np.arange(Cf)
    return blocks[ar, :, ar, :]


def latest_camera_covariance(neq: NormalEquations) -> np.ndarray:
    """``(6, 6)`` covariance block of the last free camera (the most recent keyframe)."""
    if neq.num_free_cameras == 0:
        raise SlamError("latest_camera_covariance: no free camera")
    return camera_covariance(neq)[-1]
