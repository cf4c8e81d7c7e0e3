"""The reduced camera system (thesis eqs. 1.28-1.32), solved by dense Cholesky.

For the block system (see :mod:`slam_bridge.problem`)::

    [[A, W], [W^T, V]] [dc; dp] = [b_c; b_p],   A = U (+ U_offdiag) (+ damping)

the points are eliminated (eq. 1.29)::

    S dc = b_c - W V^-1 b_p,   S = A - W V^-1 W^T            (6 Cf x 6 Cf, dense)
    dp  = V^-1 (b_p - W^T dc)                                 (eq. 1.30)

With ``V_p = L_p L_p^T`` (closed-form 3x3 Cholesky) and ``Z_e = W_e L_p^-T`` for every
camera-point block ``e`` of point ``p``, ``W V^-1 W^T = sum_p sum_{e, e' in p} Z_e Z_e'^T``; the
right-hand side and the back-substitution only need ``Z`` and ``L^-1`` as well.

The sum is computed by point *chunks* (a supernodal trick): points are sorted by their earliest
camera and cut in chunks of ``CHUNK_POINTS``; in a keyframe window a chunk touches only ``L``
cameras (its span plus the track length, ~9-10 here), so its blocks ``Z_e^T`` are laid out
densely in a ``(3 chunk, 6L)`` matrix ``A`` and one batched GEMM ``A^T A`` gives all the chunk's
camera-pair sums; the ``(L, L)`` block grids are added into ``S`` with one sparse segment sum.
The layout depends only on the sparsity pattern and is cached. There is no Python loop per
point or per observation; any other pattern stays correct (``L`` just grows). ``S`` is
factorised with ``scipy.linalg.cho_factor``; :class:`SchurFactorization` keeps the factor so
that several right-hand sides can be solved with one factorisation (the barrier solver needs
two per step, eqs. B.14-B.17).

**Damping** (used by Levenberg-Marquardt), ``lambda >= 0``:

* ``"additive"``: ``H + lambda I`` (Levenberg);
* ``"marquardt"``: ``H + lambda diag(H)`` (Marquardt; the diagonal is clipped below at
  ``1e-12`` so that unobserved directions still get damped).

The camera covariance (eq. 1.32) is ``C_a = S^-1`` of the undamped system; :func:`camera_covariance`
returns its diagonal blocks.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from slam_bridge.errors import SlamError
from slam_bridge.problem import NormalEquations, _segment_sum

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
class _ChunkStructure:
    """Point chunks of one sparsity pattern (see :func:`_chunk_structure`)."""

    chunk: int  # points per chunk
    n_chunks: int
    L: int  # most cameras touched by one chunk
    e_chunk: np.ndarray  # (N,) chunk of each camera-point block
    e_local: np.ndarray  # (N,) rank of the block's camera within its chunk's camera set
    e_pos: np.ndarray  # (N,) position of the block's point within its chunk
    cams: np.ndarray  # (n_chunks, L) camera of each local slot (Cf = padding)
    row: np.ndarray  # (3N,) rows of each block's Z^T lines in the padded layout
    target: np.ndarray  # (n_chunks * L * L,) flat camera-pair index in a (Cf + 1)^2 grid


_STRUCT_CACHE: OrderedDict[tuple, _ChunkStructure] = OrderedDict()
_CACHE_SIZE = 8
#: points per chunk of the reduced-system product (see the module docstring)
CHUNK_POINTS = 64


def _chunk_structure(
    W_cameras: np.ndarray, W_points: np.ndarray, Cf: int, Pf: int, chunk: int = CHUNK_POINTS
) -> _ChunkStructure:
    """Group the points in chunks of ``chunk`` points sorted by their earliest camera.

    In a keyframe window the cameras of a point are a short run of successive keyframes, so the
    cameras touched by a chunk are few (``L`` ~ chunk span + track length) and the chunk's
    contribution ``A^T A`` is a small dense GEMM. Any other pattern stays correct
    (``L`` just grows).
    """
    key = (Cf, Pf, chunk, W_cameras.tobytes(), W_points.tobytes())
    hit = _STRUCT_CACHE.get(key)
    if hit is not None:
        _STRUCT_CACHE.move_to_end(key)
        return hit
    minc = np.full(Pf, Cf, dtype=np.int64)
    np.minimum.at(minc, W_points, W_cameras)
    porder = np.lexsort((np.arange(Pf), minc))
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
        L = int(u_local.max()) + 1 if uniq.size else 1
        if chunk == 1 or n_chunks * chunk * L <= 8 * max(N, 1):
            break
        chunk = max(chunk // 2, 1)
    cams = np.full((n_chunks, L), Cf, dtype=np.int64)
    cams[u_chunk, u_local] = u_cam
    e_local, e_pos = u_local[inv], p_pos[W_points]
    # row of line j of Z_e^T in the (n_chunks * chunk * 3 * L, 6) layout, (N * 3,)
    row = (((e_chunk * chunk + e_pos)[:, None] * 3 + np.arange(3)) * L + e_local[:, None]).reshape(
        -1
    )
    target = (cams[:, :, None] * (Cf + 1) + cams[:, None, :]).reshape(-1)
    s = _ChunkStructure(chunk, n_chunks, L, e_chunk, e_local, e_pos, cams, row, target)
    _STRUCT_CACHE[key] = s
    if len(_STRUCT_CACHE) > _CACHE_SIZE:
        _STRUCT_CACHE.popitem(last=False)
    return s


def _chol_inv3(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``L^-1`` of ``V = L L^T`` for symmetric ``(P, 3, 3)`` blocks (closed form), and a mask of
    the positive-definite blocks (``L^-1`` is 0 for the others)."""
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
        if Pf:
            self._Linv, pd = _chol_inv3(V)
            if not np.all(pd):
                bad = int(np.flatnonzero(~pd)[0])
                raise SlamError(
                    f"point block {bad} of V is not positive definite (point seen by too few "
                    "cameras, or zero parallax); add damping or fix/remove the point"
                )
            # Z_e^T = L_p^-1 W_e^T (N, 3, 6): W V^-1 W^T = sum_p (sum_e Z_e)(sum_e Z_e)^T
            self._ZT = self._Linv[neq.W_points] @ np.swapaxes(neq.W, 1, 2)
        else:
            self._Linv = np.zeros((0, 3, 3))
            self._ZT = np.zeros((0, 3, 6))
        self.S = self._reduced(U)
        if Cf:
            try:
                self._cho = scipy.linalg.cho_factor(self.S, lower=False, check_finite=False)
            except np.linalg.LinAlgError as exc:
                raise SlamError(
                    "reduced camera system is not positive definite: is the gauge fixed "
                    "(enough fixed cameras) and does every free camera see points?"
                ) from exc
            if not np.all(np.isfinite(self._cho[0])):
                raise SlamError("reduced camera system: non-finite Cholesky factor")
        else:
            self._cho = None

    @property
    def V_inv(self) -> np.ndarray:
        """``(Pf, 3, 3)`` inverses of the damped point blocks."""
        return np.swapaxes(self._Linv, 1, 2) @ self._Linv

    def _reduced(self, U: np.ndarray) -> np.ndarray:
        neq, Cf = self.neq, self.Cf
        S4 = np.zeros((Cf, Cf, 6, 6))
        ar = np.arange(Cf)
        S4[ar, ar] = U
        if neq.pairs.shape[0]:
            S4[neq.pairs[:, 0], neq.pairs[:, 1]] += neq.U_pairs
            S4[neq.pairs[:, 1], neq.pairs[:, 0]] += np.swapaxes(neq.U_pairs, 1, 2)
        if self._ZT.shape[0]:
            st = _chunk_structure(neq.W_cameras, neq.W_points, Cf, self.Pf)
            # layout (chunk, point slot, j, local camera, i): each row j of Z_e^T is 6 contiguous
            # values; per chunk a (3 chunk, 6L) matrix A with A^T A = the chunk's camera sums
            A = np.zeros((st.n_chunks * st.chunk * 3 * st.L, 6))
            A[st.row] = self._ZT.reshape(-1, 6)
            A = A.reshape(st.n_chunks, 3 * st.chunk, 6 * st.L)
            G = np.swapaxes(A, 1, 2) @ A  # (n_chunks, 6L, 6L)
            G = G.reshape(st.n_chunks, st.L, 6, st.L, 6).transpose(0, 1, 3, 2, 4)
            Sx = _segment_sum(st.target, G.reshape(-1, 6, 6), (Cf + 1) ** 2)
            S4 -= Sx.reshape(Cf + 1, Cf + 1, 6, 6)[:Cf, :Cf]
        return S4.transpose(0, 2, 1, 3).reshape(6 * Cf, 6 * Cf)

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
        ZT = self._ZT
        y = (self._Linv @ rhs_p[:, :, None])[:, :, 0]  # L^-1 b_p
        b = rhs_c.copy()
        if ZT.shape[0]:  # b_c - W V^-1 b_p = b_c - sum_e Z_e L^-1 b_p
            b -= _segment_sum(neq.W_cameras, (y[neq.W_points][:, None, :] @ ZT)[:, 0, :], self.Cf)
        if self._cho is not None:
            dc = scipy.linalg.cho_solve(self._cho, b.reshape(-1), check_finite=False).reshape(
                self.Cf, 6
            )
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
        return scipy.linalg.cho_solve(self._cho, np.eye(6 * self.Cf), check_finite=False)


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
