"""DPC: direct pose constraints of the hybrid window (thesis §3.5.0.1, eqs. 3.2, 3.14-3.16).

For two successive keyframes ``i`` and ``j = i + 1`` of the pose-graph window (camera-to-world
``R_i = R_wc[i]``, ``T_i = t_wc[i]``), the relative pose of ``j`` in ``i`` is (eq. 3.2)::

    S(R_i, T_i, R_j, T_j) = (R_i^T R_j, R_i^T (T_j - T_i))

``S_hat`` is the same quantity before fusion (after the minimisation of zeta, eq. 3.14), and::

    q_i = log_SE3(S_hat^-1 S(R_i, T_i, R_j, T_j))^vee      (eq. 3.15)
    xi  = q_i^T D q_i,   D = diag(A, B)                    (eq. 3.16)

Twists are rotation first (``[w, v]``, :mod:`slam_bridge.geometry.lie`), so ``A`` weighs the
rotation and ``B`` the translation part (identity by default, as in the thesis). The whitened
residual is ``r = L^T q`` with ``D = L L^T`` (Cholesky), so that ``||r||^2 = xi``.

Analytic Jacobian (the thesis uses finite differences, §3.6.1; this one is exact). With the
core's increments ``R <- exp(hat(dw)) R``, ``T <- T + dT`` the relative pose moves by a right
perturbation ``S <- S exp(delta)`` with, to first order::

    camera j:  delta = [R_j^T dw_j,  R_j^T dT_j]
    camera i:  delta = [-R_j^T dw_i,  R_j^T [T_j - T_i]_x dw_i - R_j^T dT_i]

and ``S_hat^-1 S`` moves by the same right perturbation, so ``dq = J_r^-1(q) delta`` with the
SE(3) right Jacobian (:func:`slam_bridge.geometry.lie.se3_right_jacobian_inv`).
"""

from __future__ import annotations

import logging

import numpy as np

from geoseg.errors import GeosegError, check_finite
from slam_bridge.ba.compiled import _njit, numba_enabled
from slam_bridge.ba.factor import FactorBlock
from slam_bridge.ba.normal_equations import pair_normal_equations
from slam_bridge.ba.robust import RobustKernel, get_kernel
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.geometry import lie

logger = logging.getLogger(__name__)

__all__ = [
    "DPCFactor",
    "relative_pose",
    "dpc_residuals",
    "dpc_whitener",
    "relative_pose_information",
]


def relative_pose(
    R_wc_i: np.ndarray, t_wc_i: np.ndarray, R_wc_j: np.ndarray, t_wc_j: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``S(R_i, T_i, R_j, T_j)`` of eq. 3.2: the pose of camera ``j`` in camera ``i``.

    Args:
        R_wc_i: ``(M, 3, 3)``.
        t_wc_i: ``(M, 3)``.
        R_wc_j: ``(M, 3, 3)``.
        t_wc_j: ``(M, 3)``.

    Returns:
        ``R_ij (M, 3, 3) = R_i^T R_j`` and ``t_ij (M, 3) = R_i^T (T_j - T_i)``.
    """
    R_it = np.swapaxes(R_wc_i, -1, -2)
    return R_it @ R_wc_j, np.einsum("...ab,...b->...a", R_it, t_wc_j - t_wc_i)


def dpc_whitener(D: np.ndarray | None) -> np.ndarray:
    """``L^T`` with ``D = L L^T``; identity for ``D = None``.

    Args:
        D: ``(6, 6)`` symmetric positive-definite weight ``diag(A, B)`` (or any SPD matrix),
            ``(6,)`` its diagonal, or ``(Q, 6, 6)`` one SPD weight per pair (e.g. the
            information of each relative pose, :func:`relative_pose_information`).

    Returns:
        ``(6, 6)`` or, for a per-pair ``D``, ``(Q, 6, 6)``.

    Raises:
        GeosegError: D is not symmetric positive definite.
    """
    if D is None:
        return np.eye(6)
    D = np.asarray(D, dtype=np.float64)
    if D.shape == (6,):
        D = np.diag(D)
    if (
        D.ndim not in (2, 3)
        or D.shape[-2:] != (6, 6)
        or not np.all(np.isfinite(D))
        or not np.allclose(D, np.swapaxes(D, -1, -2))
    ):
        raise GeosegError(
            f"D: expected a finite symmetric (6, 6) or (Q, 6, 6) matrix, got shape {D.shape}"
        )
    try:
        L = np.linalg.cholesky(D)
    except np.linalg.LinAlgError as exc:
        raise GeosegError("D: expected a positive-definite weight matrix") from exc
    return np.swapaxes(L, -1, -2).copy()


def relative_pose_information(
    R_wc_i: np.ndarray,
    t_wc_i: np.ndarray,
    R_wc_j: np.ndarray,
    t_wc_j: np.ndarray,
    cov_joint: np.ndarray,
    *,
    min_sigma: tuple[float, float] = (1e-6, 1e-5),
) -> np.ndarray:
    """Information ``Sigma_q^-1`` of the relative pose ``S`` (eq. 3.2) of camera pairs.

    The thesis's perspective (§5.2: learn the DPC weight from the uncertainty): to first order
    the twist ``q`` of eq. 3.15 at ``S_hat = S`` moves by ``J_i d_i + J_j d_j`` when the cameras
    move by ``d_i, d_j`` (``[dw, dT]``, :func:`dpc_residuals`), so a joint covariance of the two
    cameras (e.g. the k-BA's marginal, ``S^-1`` of its reduced camera system, eq. 1.32) gives
    ``Sigma_q = [J_i J_j] Sigma_ij [J_i J_j]^T``. Weighing ``q`` by its inverse makes ``xi``
    (eq. 3.16) the chi-square the k-BA's points would charge for bending the link.

    Args:
        R_wc_i: ``(Q, 3, 3)`` older camera of each pair.
        t_wc_i: ``(Q, 3)``.
        R_wc_j: ``(Q, 3, 3)`` newer camera.
        t_wc_j: ``(Q, 3)``.
        cov_joint: ``(Q, 12, 12)`` covariance of ``[d_i, d_j]`` (zero rows/columns for a fixed
            camera).
        min_sigma: ``(rad, m)`` floors of the standard deviations along the eigenvectors of
            ``Sigma_q`` (a numerically stiff link is capped, never infinite).

    Returns:
        ``(Q, 6, 6)`` SPD weights ``D`` (rotation block first).
    """
    Q = R_wc_i.shape[0]
    cov_joint = np.asarray(cov_joint, dtype=np.float64)
    if cov_joint.shape != (Q, 12, 12) or not np.all(np.isfinite(cov_joint)):
        raise GeosegError(
            f"cov_joint: expected a finite ({Q}, 12, 12) array, got {cov_joint.shape}"
        )
    R_ij, t_ij = relative_pose(R_wc_i, t_wc_i, R_wc_j, t_wc_j)
    _, J_i, J_j = dpc_residuals(R_wc_i, t_wc_i, R_wc_j, t_wc_j, R_ij, t_ij)
    J = np.concatenate([J_i, J_j], axis=2)  # (Q, 6, 12), q = 0 so J_r^-1 = I
    cov = J @ cov_joint @ np.swapaxes(J, 1, 2)
    # whiten by the floors so that the eigen-floor is one number for both blocks
    f = np.repeat(np.asarray(min_sigma, dtype=np.float64), 3)
    cov_n = 0.5 * (cov + np.swapaxes(cov, 1, 2)) / np.outer(f, f)
    lam, V = np.linalg.eigh(cov_n)
    lam = np.maximum(lam, 1.0)
    info_n = (V / lam[:, None, :]) @ np.swapaxes(V, 1, 2)
    info = info_n / np.outer(f, f)
    return 0.5 * (info + np.swapaxes(info, 1, 2))


def dpc_residuals(
    R_wc_i: np.ndarray,
    t_wc_i: np.ndarray,
    R_wc_j: np.ndarray,
    t_wc_j: np.ndarray,
    R_hat_ij: np.ndarray,
    t_hat_ij: np.ndarray,
    whitener: np.ndarray | None = None,
    *,
    with_jacobians: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Whitened DPC residuals ``L^T q`` (eq. 3.15) and their analytic Jacobians.

    Args:
        R_wc_i: ``(M, 3, 3)`` rotation of the older camera of each pair.
        t_wc_i: ``(M, 3)`` its optical centre.
        R_wc_j: ``(M, 3, 3)`` rotation of the newer camera.
        t_wc_j: ``(M, 3)`` its optical centre.
        R_hat_ij: ``(M, 3, 3)`` relative rotation before fusion (``S_hat``, eq. 3.14).
        t_hat_ij: ``(M, 3)`` relative translation before fusion.
        whitener: ``(6, 6)`` or ``(M, 6, 6)`` ``L^T`` from :func:`dpc_whitener` (identity if
            None).
        with_jacobians: also return the Jacobians.

    Returns:
        ``(r, J_i, J_j)``: ``r (M, 6)``; ``J_i``, ``J_j`` ``(M, 6, 6)`` derivatives with respect
        to ``[dw, dT]`` of cameras ``i`` and ``j`` (None when ``with_jacobians`` is False).
    """
    Wt = np.eye(6) if whitener is None else whitener
    poses = (R_wc_i, t_wc_i, R_wc_j, t_wc_j)
    if numba_enabled():  # one compiled pass; _dpc_residuals_numpy is its reference
        M = R_wc_i.shape[0]
        R_hi, t_hi = (np.ascontiguousarray(a) for a in lie.se3_inverse(R_hat_ij, t_hat_ij))
        Wb = np.ascontiguousarray(np.broadcast_to(Wt, (M, 6, 6)), dtype=np.float64)
        args = [np.ascontiguousarray(a, dtype=np.float64) for a in poses]
        r, J_i, J_j = _dpc_kernel(*args, R_hi, t_hi, Wb, with_jacobians)
        return (r, J_i, J_j) if with_jacobians else (r, None, None)
    return _dpc_residuals_numpy(poses, R_hat_ij, t_hat_ij, Wt, with_jacobians)


def _dpc_residuals_numpy(
    poses: tuple[np.ndarray, ...],
    R_hat_ij: np.ndarray,
    t_hat_ij: np.ndarray,
    Wt: np.ndarray,
    with_jacobians: bool,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`dpc_residuals` with :mod:`slam_bridge.geometry.lie`; ``poses = (R_wc_i, t_wc_i,
    R_wc_j, t_wc_j)``, ``Wt`` ``(6, 6)`` or ``(M, 6, 6)``."""
    R_wc_i, t_wc_i, R_wc_j, t_wc_j = poses
    R_ij, t_ij = relative_pose(R_wc_i, t_wc_i, R_wc_j, t_wc_j)
    R_hi, t_hi = lie.se3_inverse(R_hat_ij, t_hat_ij)
    R_e, t_e = lie.se3_compose(R_hi, t_hi, R_ij, t_ij)
    q = lie.se3_log(R_e, t_e)  # (M, 6)
    r = q @ Wt.T if Wt.ndim == 2 else np.einsum("mab,mb->ma", Wt, q)
    if not with_jacobians:
        return r, None, None
    M = q.shape[0]
    Jri = lie.se3_right_jacobian_inv(q)  # (M, 6, 6)
    R_jt = np.swapaxes(R_wc_j, -1, -2)
    d_j = np.zeros((M, 6, 6))
    d_j[:, :3, :3] = R_jt
    d_j[:, 3:, 3:] = R_jt
    d_i = np.zeros((M, 6, 6))
    d_i[:, :3, :3] = -R_jt
    d_i[:, 3:, :3] = R_jt @ lie.so3_hat(t_wc_j - t_wc_i)
    d_i[:, 3:, 3:] = -R_jt
    WJ = (Wt[None] if Wt.ndim == 2 else Wt) @ Jri
    return r, WJ @ d_i, WJ @ d_j


# ------------------------------------------------------------------ compiled residuals (numba)
# The same formulas as slam_bridge.geometry.lie (series below lie._SMALL), per pair in one loop: at
# the pose graph's size (~30 pairs) the NumPy version is ~40 small array calls (~0.3 ms).
_SMALL2 = lie._SMALL * lie._SMALL


@_njit
def _series(t2, c0, c1, c2, c3, c4):
    return c0 + t2 * (c1 + t2 * (c2 + t2 * (c3 + t2 * c4)))


@_njit
def _so3_log1(R):
    """Rotation vector of one matrix (:func:`slam_bridge.geometry.lie.so3_log`)."""
    s = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = min(1.0, max(-1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    th = np.arctan2(np.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2]), c)
    t2 = th * th
    if c > 0.0:
        if t2 < _SMALL2:
            k = _series(t2, 1.0, 1.0 / 6, 7.0 / 360, 31.0 / 15120, 127.0 / 604800)
        else:
            k = th / np.sin(th)
        return k * s
    M = 0.5 * (R + R.T)
    for a in range(3):
        M[a, a] -= c
    k = 0
    for a in range(1, 3):
        if M[a, a] > M[k, k]:
            k = a
    axis = M[:, k] / np.sqrt(M[0, k] ** 2 + M[1, k] ** 2 + M[2, k] ** 2)
    sign = -1.0 if axis[0] * s[0] + axis[1] * s[1] + axis[2] * s[2] < 0.0 else 1.0
    return sign * th * axis


@_njit
def _coefs(t2):
    """``C, D, E, F`` of :mod:`slam_bridge.geometry.lie` at ``theta^2``."""
    if t2 < _SMALL2:
        C = _series(t2, 1.0 / 6, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800)
        D = _series(t2, 1.0 / 12, 1.0 / 720, 1.0 / 30240, 1.0 / 1209600, 1.0 / 47900160)
        E = _series(t2, 1.0 / 24, -1.0 / 720, 1.0 / 40320, -1.0 / 3628800, 1.0 / 479001600)
        F = _series(t2, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800, -1.0 / 6227020800)
        return C, D, E, F
    t = np.sqrt(t2)
    sn, cs = np.sin(t), np.cos(t)
    C = (t - sn) / t**3
    D = (1.0 - t * sn / (2.0 * (1.0 - cs))) / t2
    E = (t2 / 2.0 + cs - 1.0) / t2**2
    F = (t - sn - t**3 / 6.0) / t**5
    return C, D, E, F


@_njit
def _mm_into(A, B, out):
    """``out = A @ B`` for tiny matrices, in place (``out`` distinct from ``A`` and ``B``)."""
    for a in range(A.shape[0]):
        for b in range(B.shape[1]):
            x = 0.0
            for c in range(A.shape[1]):
                x += A[a, c] * B[c, b]
            out[a, b] = x


@_njit
def _hat3_into(w0, w1, w2, W):
    W[0, 0], W[0, 1], W[0, 2] = 0.0, -w2, w1
    W[1, 0], W[1, 1], W[1, 2] = w2, 0.0, -w0
    W[2, 0], W[2, 1], W[2, 2] = -w1, w0, 0.0


@_njit
def _dpc_kernel(R_i, t_i, R_j, t_j, R_hi, t_hi, Wt, with_jacobians):
    """Whitened residuals ``(M, 6)`` and Jacobians ``(M, 6, 6)`` x 2 of :func:`dpc_residuals`
    (``R_hi, t_hi`` = ``S_hat^-1``, ``Wt`` ``(M, 6, 6)``). The temporaries are allocated once:
    per-pair allocations cost more than the arithmetic."""
    M = R_i.shape[0]
    r = np.zeros((M, 6))
    J_i = np.zeros((M, 6, 6)) if with_jacobians else np.zeros((0, 6, 6))
    J_j = np.zeros((M, 6, 6)) if with_jacobians else np.zeros((0, 6, 6))
    T1, T2, R_e = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    W, W2, Wn, Vn = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Ji, WV, VW, WVW = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Q, A1, A2 = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    q, d, te = np.empty(6), np.empty(3), np.empty(3)
    Jri, WJ, d_i, d_j = np.zeros((6, 6)), np.empty((6, 6)), np.zeros((6, 6)), np.zeros((6, 6))
    for m in range(M):
        # R_e = S_hat^-1 R_ij, t_e = R_hi R_i^T (t_j - t_i) + t_hi
        for a in range(3):
            for b in range(3):
                T1[a, b] = (
                    R_i[m, 0, a] * R_j[m, 0, b]
                    + R_i[m, 1, a] * R_j[m, 1, b]
                    + (R_i[m, 2, a] * R_j[m, 2, b])
                )
        _mm_into(R_hi[m], T1, R_e)
        for a in range(3):
            d[a] = t_j[m, a] - t_i[m, a]
        for a in range(3):
            te[a] = R_i[m, 0, a] * d[0] + R_i[m, 1, a] * d[1] + R_i[m, 2, a] * d[2]
        for a in range(3):
            q[3 + a] = R_hi[m, a, 0] * te[0] + R_hi[m, a, 1] * te[1] + R_hi[m, a, 2] * te[2]
            q[3 + a] += t_hi[m, a]
        w = _so3_log1(R_e)
        t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
        C, D, E, F = _coefs(t2)
        _hat3_into(w[0], w[1], w[2], W)
        _mm_into(W, W, W2)
        # v = (I - W / 2 + D W^2) t_e
        for a in range(3):
            te[a] = q[3 + a]
        for a in range(3):
            v = te[a]
            for b in range(3):
                v += (-0.5 * W[a, b] + D * W2[a, b]) * te[b]
            q[3 + a] = v
        for a in range(3):
            q[a] = w[a]
        for a in range(6):
            x = 0.0
            for b in range(6):
                x += Wt[m, a, b] * q[b]
            r[m, a] = x
        if not with_jacobians:
            continue
        # J_r^-1(q) = J_l^-1(-q): [[Ji, 0], [-Ji Q Ji, Ji]] at (-w, -v)
        _hat3_into(-w[0], -w[1], -w[2], Wn)
        _hat3_into(-q[3], -q[4], -q[5], Vn)
        for a in range(3):
            for b in range(3):
                Ji[a, b] = -0.5 * Wn[a, b] + D * W2[a, b]
            Ji[a, a] += 1.0
        _mm_into(Wn, Vn, WV)
        _mm_into(Vn, Wn, VW)
        _mm_into(WV, Wn, WVW)
        _mm_into(Wn, WV, A1)
        _mm_into(VW, Wn, A2)
        _mm_into(WVW, Wn, T1)
        _mm_into(Wn, WVW, T2)
        for a in range(3):
            for b in range(3):
                Q[a, b] = (
                    0.5 * Vn[a, b]
                    + C * (WV[a, b] + VW[a, b] + WVW[a, b])
                    + E * (A1[a, b] + A2[a, b] - 3.0 * WVW[a, b])
                    + 0.5 * (E + 3.0 * F) * (T1[a, b] + T2[a, b])
                )
        _mm_into(Ji, Q, T1)
        _mm_into(T1, Ji, T2)
        for a in range(3):
            for b in range(3):
                Jri[a, b] = Ji[a, b]
                Jri[3 + a, 3 + b] = Ji[a, b]
                Jri[3 + a, b] = -T2[a, b]
        _mm_into(Wt[m], Jri, WJ)
        # d_j = diag(R_j^T, R_j^T); d_i = [[-R_j^T, 0], [R_j^T [t_j - t_i]_x, -R_j^T]]
        _hat3_into(d[0], d[1], d[2], T1)
        for a in range(3):
            for b in range(3):
                rt = R_j[m, b, a]
                d_j[a, b] = rt
                d_j[3 + a, 3 + b] = rt
                d_i[a, b] = -rt
                d_i[3 + a, 3 + b] = -rt
                d_i[3 + a, b] = (
                    R_j[m, 0, a] * T1[0, b] + R_j[m, 1, a] * T1[1, b] + (R_j[m, 2, a] * T1[2, b])
                )
        _mm_into(WJ, d_i, J_i[m])
        _mm_into(WJ, d_j, J_j[m])
    return r, J_i, J_j


class DPCFactor:
    """Direct pose constraints between successive pose-graph cameras (eq. 3.16), one row each.

    Args:
        pairs: ``(Q, 2)`` state camera indices ``(i, j)`` of successive keyframes (``j`` newer).
        R_hat_ij: ``(Q, 3, 3)`` relative rotations before fusion (``S_hat``, eq. 3.14).
        t_hat_ij: ``(Q, 3)`` relative translations before fusion.
        D: ``(6, 6)`` or ``(6,)`` weight ``diag(A, B)`` (rotation block first), or ``(Q, 6, 6)``
            one weight per pair; identity if None.
        kernel: robust kernel (default least squares, as eq. 3.16).
        name: family label.

    Use :meth:`from_state` to take ``S_hat`` from the current (pre-fusion) state.
    """

    def __init__(
        self,
        pairs: np.ndarray,
        R_hat_ij: np.ndarray,
        t_hat_ij: np.ndarray,
        D: np.ndarray | None = None,
        *,
        kernel: str | RobustKernel | None = None,
        name: str = "pose_graph_dpc",
    ) -> None:
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        Q = self.pairs.shape[0]
        self.R_hat_ij = np.asarray(R_hat_ij, dtype=np.float64).reshape(Q, 3, 3)
        self.t_hat_ij = np.asarray(t_hat_ij, dtype=np.float64).reshape(Q, 3)
        check_finite("R_hat_ij", self.R_hat_ij)
        check_finite("t_hat_ij", self.t_hat_ij)
        self.whitener = dpc_whitener(D)
        if self.whitener.ndim == 3 and self.whitener.shape[0] != Q:
            raise GeosegError(f"D: expected one (6, 6) weight per pair ({Q}), got {np.shape(D)}")
        self.kernel = get_kernel(kernel)
        self.name = name
        self._compiled_args: tuple[np.ndarray, ...] | None = None  # S_hat^-1, whitener (Q, 6, 6)

    @classmethod
    def from_state(
        cls, state: BAState, pairs: np.ndarray, D: np.ndarray | None = None, **kwargs
    ) -> DPCFactor:
        """Build the factor with ``S_hat`` = the relative poses of ``state`` (eq. 3.14).

        Args:
            state: the state after the minimisation of zeta (before fusion).
            pairs: ``(Q, 2)`` state camera indices ``(i, i + 1)``.
            D: weight, see the constructor.
            **kwargs: forwarded to the constructor.
        """
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        R_h, t_h = relative_pose(
            state.R_wc[pairs[:, 0]],
            state.t_wc[pairs[:, 0]],
            state.R_wc[pairs[:, 1]],
            state.t_wc[pairs[:, 1]],
        )
        return cls(pairs, R_h, t_h, D, **kwargs)

    @property
    def num_residuals(self) -> int:
        """Six per pose-graph pair."""
        return 6 * self.pairs.shape[0]

    def _gather(self, state: BAState) -> tuple[np.ndarray, ...]:
        C = state.num_cameras
        if self.pairs.size and (self.pairs.max() >= C or self.pairs.min() < 0):
            raise SlamError(f"{self.name}: camera index out of range for {C} cameras")
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        return state.R_wc[i], state.t_wc[i], state.R_wc[j], state.t_wc[j]

    def _rows(
        self, state: BAState, jac: bool
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """:func:`dpc_residuals` at ``state``; with numba, the compiled pass with ``S_hat^-1``
        and the per-pair whitener prepared once per factor."""
        if not numba_enabled():
            return dpc_residuals(
                *self._gather(state),
                self.R_hat_ij,
                self.t_hat_ij,
                self.whitener,
                with_jacobians=jac,
            )
        if self._compiled_args is None:
            Q = self.pairs.shape[0]
            R_hi, t_hi = lie.se3_inverse(self.R_hat_ij, self.t_hat_ij)
            Wb = np.broadcast_to(self.whitener, (Q, 6, 6))
            self._compiled_args = tuple(
                np.ascontiguousarray(a, dtype=np.float64) for a in (R_hi, t_hi, Wb)
            )
        poses = [np.ascontiguousarray(a) for a in self._gather(state)]
        r, J_i, J_j = _dpc_kernel(*poses, *self._compiled_args, jac)
        return (r, J_i, J_j) if jac else (r, None, None)

    def evaluate(self, state: BAState) -> FactorBlock:
        """Rows ``(Q, 6)``, ``a = 2``."""
        r, J_i, J_j = self._rows(state, True)
        return FactorBlock(
            residuals=r,
            cameras=self.pairs,
            J_cameras=np.stack([J_i, J_j], axis=1),
            kernel=self.kernel,
            name=self.name,
        )

    def _normal_equations(
        self, state: BAState, cmap: np.ndarray, pmap: np.ndarray, Cf: int, Pf: int
    ) -> tuple | None:
        """Compiled shortcut of :func:`slam_bridge.ba.normal_equations.assemble` for this family
        (numba only): one batched product per pair instead of the generic path's per-slot segment
        sums.

        Returns:
            :func:`slam_bridge.ba.normal_equations.pair_normal_equations`'s blocks, those
            :meth:`evaluate` leads the generic path to (up to rounding), or None when a subclass
            overrides :meth:`evaluate`.
        """
        if type(self).evaluate is not DPCFactor.evaluate:
            return None
        r, J_i, J_j = self._rows(state, True)
        s = np.einsum("mk,mk->m", r, r)
        w = self.kernel.weight(s)
        J = np.concatenate([J_i, J_j], axis=2)  # (Q, 6, 12)
        JtW = np.swapaxes(J, 1, 2) * w[:, None, None]
        H = JtW @ J
        g = (JtW @ r[:, :, None])[:, :, 0]
        cost = float(np.sum(self.kernel.rho(s)))
        return pair_normal_equations(cost, 0, H, g, self.pairs, cmap, Cf, Pf)

    def cost_and_invalid(self, state: BAState) -> tuple[float, int]:
        """The cost and 0 (a DPC row is always defined)."""
        return self.cost(state), 0

    def cost(self, state: BAState) -> float:
        """``sum_i rho(q_i^T D q_i)``."""
        r, _, _ = self._rows(state, False)
        return float(np.sum(self.kernel.rho(np.einsum("mk,mk->m", r, r))))
