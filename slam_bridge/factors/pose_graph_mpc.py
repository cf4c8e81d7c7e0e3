"""MPC: multi-view (epipolar) pose-graph constraints of the hybrid window (thesis §3.5.0.2).

For two successive keyframes ``i`` and ``j = i + 1`` of the pose-graph window and their 2D
correspondences ``(x_k, x'_k)``, the residual ``psi_k`` is the signed distance in pixels from
``x_k`` to the epipolar line ``F x'_k`` (eqs. 3.17-3.18, C.3); the pair's term is
``xi = sum_k psi_k^2``. The Jacobians are analytic (appendix C, rederived in world-frame form:
every block a cross product, vectorised over correspondences); with ``numba``
(:data:`slam_bridge.ba.compiled.USE_NUMBA`) one compiled pass computes the same formulas and
hands the assembler its normal-equation blocks (:meth:`MPCFactor._normal_equations`), of which
:func:`epipolar_residuals` is the NumPy reference. The residual is invariant to the scale of the
baseline; coincident optical centres raise :class:`MPCDegenerateError`, a correspondence on the
epipole makes its row invalid. The derivation: ``docs/solvers.md`` ("MPC").
"""

from __future__ import annotations

import logging

import numpy as np

from geoseg.errors import check_finite, check_positive
from slam_bridge.ba.compiled import _njit, numba_enabled
from slam_bridge.ba.factor import FactorBlock
from slam_bridge.ba.normal_equations import pair_normal_equations
from slam_bridge.ba.robust import RobustKernel, TrivialKernel, get_kernel
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = ["MPCDegenerateError", "MPCFactor", "epipolar_residuals"]


class MPCDegenerateError(SlamError):
    """The epipolar residual is undefined: the two optical centres coincide (``F = 0``)."""


def _matvec(A: np.ndarray, x: np.ndarray, *, transpose: bool = False) -> np.ndarray:
    """``A x`` (or ``A^T x``) for ``A (M, 3, 3)`` or ``(3, 3)`` and ``x (M, 3)``."""
    if A.ndim == 2:
        return x @ A if transpose else x @ A.T
    # three multiply-adds per row: faster than a batched matmul of 3x3 blocks
    if transpose:
        return A[:, 0, :] * x[:, 0:1] + A[:, 1, :] * x[:, 1:2] + A[:, 2, :] * x[:, 2:3]
    return A[:, :, 0] * x[:, 0:1] + A[:, :, 1] * x[:, 1:2] + A[:, :, 2] * x[:, 2:3]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise ``a x b`` of ``(M, 3)`` arrays (``np.cross`` without its axis handling, which
    cost more than the arithmetic at these sizes)."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=1)


def epipolar_residuals(
    R_wc_i: np.ndarray,
    t_wc_i: np.ndarray,
    R_wc_j: np.ndarray,
    t_wc_j: np.ndarray,
    Kinv_i: np.ndarray,
    Kinv_j: np.ndarray,
    uv_i: np.ndarray,
    uv_j: np.ndarray,
    *,
    with_jacobians: bool = True,
    min_baseline: float = 1e-9,
    min_line_norm: float = 1e-12,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Normalised epipolar distances (eq. 3.18) and their analytic Jacobians (appendix C).

    Every argument is given per correspondence (gather camera arrays with the pair index first).

    Args:
        R_wc_i: ``(M, 3, 3)`` rotation of the older camera ``i`` (camera-to-world).
        t_wc_i: ``(M, 3)`` optical centre of camera ``i`` in the world.
        R_wc_j: ``(M, 3, 3)`` rotation of the newer camera ``j = i + 1``.
        t_wc_j: ``(M, 3)`` optical centre of camera ``j``.
        Kinv_i: ``(M, 3, 3)`` inverse intrinsics ``K_i^-1`` of camera ``i`` (``(3, 3)``
            broadcasts).
        Kinv_j: ``(M, 3, 3)`` inverse intrinsics of camera ``j`` (``(3, 3)`` broadcasts).
        uv_i: ``(M, 2)`` pixel ``x_k`` in image ``i``.
        uv_j: ``(M, 2)`` corresponding pixel ``x'_k`` in image ``j``.
        with_jacobians: also return the Jacobians.
        min_baseline: below this ``||T_j - T_i||`` (metres) the pair is degenerate.
        min_line_norm: below this ``||P F x'||`` relative to ``||F x'||`` the point is at the
            epipole and its row is flagged invalid.

    Returns:
        ``(psi, valid, J_i, J_j)``: ``psi (M,)`` signed distances in pixels (0 where invalid);
        ``valid (M,)`` bool, False for points on the epipole; ``J_i (M, 6)`` and ``J_j (M, 6)``
        the derivatives with respect to the increments ``[dw, dT]`` of cameras ``i`` and ``j``
        (``None`` when ``with_jacobians`` is False; zero rows where invalid).

    Raises:
        MPCDegenerateError: coincident optical centres.
    """
    M = uv_i.shape[0]
    delta_w = t_wc_j - t_wc_i  # (M, 3)
    base = np.linalg.norm(delta_w, axis=-1)
    if M and np.any(base < min_baseline):
        bad = int(np.argmin(base))
        raise MPCDegenerateError(
            f"epipolar residual undefined: cameras of correspondence {bad} share one optical "
            f"centre (baseline {base[bad]:.3g} m < {min_baseline:g} m)"
        )
    ones = np.ones((M, 1))
    x_i = np.concatenate([uv_i, ones], axis=1)  # (M, 3) homogeneous pixels
    x_j = np.concatenate([uv_j, ones], axis=1)
    b_j = _matvec(Kinv_j, x_j)  # normalised ray of x' in camera j
    n_w = _matvec(R_wc_j, b_j)  # that ray in world axes
    ell_w = _cross(delta_w, n_w)  # (M, 3)
    ell = _matvec(R_wc_i, ell_w, transpose=True)  # R_i^T ell_w: line in normalised coords of i
    l_px = _matvec(Kinv_i, ell, transpose=True)  # K_i^-T ell = F x'
    u = np.sum(x_i * l_px, axis=1)
    v = np.hypot(l_px[:, 0], l_px[:, 1])
    scale = np.linalg.norm(l_px, axis=-1)
    valid = v > min_line_norm * np.maximum(scale, 1e-300)
    v = np.where(valid, v, 1.0)
    psi = np.where(valid, u / v, 0.0)
    if not with_jacobians:
        return psi, valid, None, None

    # d psi / d l_px (M, 3) = x^T / v - u (P l)^T / v^3, then chain through K_i^-T and R_i^T:
    # g_w = R_i K_i^-1 dpsi_dl is the world-frame row vector with d psi = g_w . d ell_w.
    Pl = l_px.copy()
    Pl[:, 2] = 0.0
    dpsi_dl = x_i / v[:, None] - (u / v**3)[:, None] * Pl
    g_w = _matvec(R_wc_i, _matvec(Kinv_i, dpsi_dl))
    # g^T [a]_x = (g x a)^T, so every block is a cross product:
    J_i = np.empty((M, 6))
    J_j = np.empty((M, 6))
    J_i[:, :3] = _cross(g_w, ell_w)  # g^T [ell_w]_x
    J_i[:, 3:] = _cross(g_w, n_w)  # g^T [n]_x
    J_j[:, :3] = -_cross(_cross(g_w, delta_w), n_w)  # -g^T [Delta]_x [n]_x
    J_j[:, 3:] = -J_i[:, 3:]
    J_i[~valid] = 0.0
    J_j[~valid] = 0.0
    return psi, valid, J_i, J_j


# ------------------------------------------------------------------ compiled residuals (numba)
# The formulas of epipolar_residuals, one correspondence per loop turn: at the pose graph's size
# (~2000 correspondences) the NumPy version is ~60 array passes and the per-pair compression
# an eigendecomposition per pair (~1.5 ms per assembly, measured in the ch. 3 fusion).


@_njit
def _epipolar_kernel(
    Kinv,
    R,
    t,
    cams_i,
    cams_j,
    uv_i,
    uv_j,
    offset,
    inv_s,
    min_baseline,
    min_line_norm,
    r,
    ok,
    J,
    jac,
):  # pragma: no cover - compiled
    """Whitened rows ``r (M,)`` = ``(psi - offset) / sigma``, ``ok (M,)`` and, if ``jac``,
    ``J (M, 12)`` = ``[J_i | J_j] / sigma`` (zero where invalid), gathering cameras by index.

    ``Kinv (1 or C, 3, 3)``, ``R (C, 3, 3)``, ``t (C, 3)``. Returns the first correspondence
    whose two optical centres coincide (the caller raises), else -1.
    """
    per_cam = Kinv.shape[0] > 1
    for m in range(cams_i.shape[0]):
        ci = cams_i[m]
        cj = cams_j[m]
        ki = ci if per_cam else 0
        kj = cj if per_cam else 0
        d0 = t[cj, 0] - t[ci, 0]
        d1 = t[cj, 1] - t[ci, 1]
        d2 = t[cj, 2] - t[ci, 2]
        if not np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) >= min_baseline:
            return m
        xi0 = uv_i[m, 0]
        xi1 = uv_i[m, 1]
        xj0 = uv_j[m, 0]
        xj1 = uv_j[m, 1]
        # b_j = K_j^-1 x', n = R_j b_j (the ray of x' in world axes)
        b0 = Kinv[kj, 0, 0] * xj0 + Kinv[kj, 0, 1] * xj1 + Kinv[kj, 0, 2]
        b1 = Kinv[kj, 1, 0] * xj0 + Kinv[kj, 1, 1] * xj1 + Kinv[kj, 1, 2]
        b2 = Kinv[kj, 2, 0] * xj0 + Kinv[kj, 2, 1] * xj1 + Kinv[kj, 2, 2]
        n0 = R[cj, 0, 0] * b0 + R[cj, 0, 1] * b1 + R[cj, 0, 2] * b2
        n1 = R[cj, 1, 0] * b0 + R[cj, 1, 1] * b1 + R[cj, 1, 2] * b2
        n2 = R[cj, 2, 0] * b0 + R[cj, 2, 1] * b1 + R[cj, 2, 2] * b2
        # ell_w = Delta x n, ell = R_i^T ell_w, l = K_i^-T ell
        w0 = d1 * n2 - d2 * n1
        w1 = d2 * n0 - d0 * n2
        w2 = d0 * n1 - d1 * n0
        e0 = R[ci, 0, 0] * w0 + R[ci, 1, 0] * w1 + R[ci, 2, 0] * w2
        e1 = R[ci, 0, 1] * w0 + R[ci, 1, 1] * w1 + R[ci, 2, 1] * w2
        e2 = R[ci, 0, 2] * w0 + R[ci, 1, 2] * w1 + R[ci, 2, 2] * w2
        l0 = Kinv[ki, 0, 0] * e0 + Kinv[ki, 1, 0] * e1 + Kinv[ki, 2, 0] * e2
        l1 = Kinv[ki, 0, 1] * e0 + Kinv[ki, 1, 1] * e1 + Kinv[ki, 2, 1] * e2
        l2 = Kinv[ki, 0, 2] * e0 + Kinv[ki, 1, 2] * e1 + Kinv[ki, 2, 2] * e2
        u = xi0 * l0 + xi1 * l1 + l2
        v = np.sqrt(l0 * l0 + l1 * l1)
        scale = max(np.sqrt(l0 * l0 + l1 * l1 + l2 * l2), 1e-300)
        if not v > min_line_norm * scale:  # x' on the epipole: the row does not count
            ok[m] = False
            r[m] = 0.0
            if jac:
                for a in range(12):
                    J[m, a] = 0.0
            continue
        ok[m] = True
        r[m] = (u / v - offset[m]) * inv_s
        if not jac:
            continue
        # dpsi/dl = x^T / v - u (P l)^T / v^3; g_w = R_i K_i^-1 dpsi/dl
        c3 = u / (v * v * v)
        q0 = xi0 / v - c3 * l0
        q1 = xi1 / v - c3 * l1
        q2 = 1.0 / v
        h0 = Kinv[ki, 0, 0] * q0 + Kinv[ki, 0, 1] * q1 + Kinv[ki, 0, 2] * q2
        h1 = Kinv[ki, 1, 0] * q0 + Kinv[ki, 1, 1] * q1 + Kinv[ki, 1, 2] * q2
        h2 = Kinv[ki, 2, 0] * q0 + Kinv[ki, 2, 1] * q1 + Kinv[ki, 2, 2] * q2
        g0 = (R[ci, 0, 0] * h0 + R[ci, 0, 1] * h1 + R[ci, 0, 2] * h2) * inv_s
        g1 = (R[ci, 1, 0] * h0 + R[ci, 1, 1] * h1 + R[ci, 1, 2] * h2) * inv_s
        g2 = (R[ci, 2, 0] * h0 + R[ci, 2, 1] * h1 + R[ci, 2, 2] * h2) * inv_s
        # J_i = [g x ell_w, g x n], J_j = [-(g x Delta) x n, -(g x n)]
        J[m, 0] = g1 * w2 - g2 * w1
        J[m, 1] = g2 * w0 - g0 * w2
        J[m, 2] = g0 * w1 - g1 * w0
        gn0 = g1 * n2 - g2 * n1
        gn1 = g2 * n0 - g0 * n2
        gn2 = g0 * n1 - g1 * n0
        J[m, 3] = gn0
        J[m, 4] = gn1
        J[m, 5] = gn2
        gd0 = g1 * d2 - g2 * d1
        gd1 = g2 * d0 - g0 * d2
        gd2 = g0 * d1 - g1 * d0
        J[m, 6] = -(gd1 * n2 - gd2 * n1)
        J[m, 7] = -(gd2 * n0 - gd0 * n2)
        J[m, 8] = -(gd0 * n1 - gd1 * n0)
        J[m, 9] = -gn0
        J[m, 10] = -gn1
        J[m, 11] = -gn2
    return -1


@_njit
def _pair_sums_kernel(J, r, w, pair_of, H, g):  # pragma: no cover - compiled
    """``H[q] += sum w J^T J`` (``(Q, 12, 12)``, both triangles) and ``g[q] += sum w J^T r``
    over the rows ``m`` of pair ``q = pair_of[m]`` (``J (M, 12)``, ``r (M,)``)."""
    for m in range(J.shape[0]):
        wm = w[m]
        if wm == 0.0:
            continue
        q = pair_of[m]
        for a in range(12):
            wa = wm * J[m, a]
            g[q, a] += wa * r[m]
            for b in range(a, 12):
                H[q, a, b] += wa * J[m, b]
    for q in range(H.shape[0]):
        for a in range(12):
            for b in range(a + 1, 12):
                H[q, b, a] = H[q, a, b]


class MPCFactor:
    """Epipolar pose-graph terms between successive pose-graph cameras (eq. 3.18), one row per
    2D correspondence.

    Args:
        K: ``(3, 3)`` shared calibration or ``(C, 3, 3)`` one per state camera.
        cameras_i: ``(M,)`` state index of the older camera ``z_i`` of each correspondence.
        cameras_j: ``(M,)`` state index of the newer camera ``z_{i+1}``.
        uv_i: ``(M, 2)`` pixel in image ``i``.
        uv_j: ``(M, 2)`` pixel in image ``j``.
        sigma: pixel standard deviation (residuals divided by it; 1 keeps the thesis's pixels).
        kernel: robust kernel (default least squares, as eq. 3.18).
        compress: with the least-squares kernel, hand the assembler one exact 13-dimensional
            row per camera pair instead of one row per correspondence (same cost, same normal
            equations, far fewer rows; see :meth:`_compressed`).
        offset: ``(M,)`` pixels subtracted from each epipolar distance (default none: eq. 3.18
            as written). :meth:`relative_to` sets it to the distances at a reference state, so
            that ``xi`` measures how much the pose graph moved away from that estimate (§3.5:
            "la fonction mesurant à quel point la pose relative est modifiée par rapport à
            l'estimation initiale"); the Jacobians do not change.
        name: family label.

    Raises:
        GeosegError: NaN/inf pixels, mismatched shapes.
    """

    def __init__(
        self,
        K: np.ndarray,
        cameras_i: np.ndarray,
        cameras_j: np.ndarray,
        uv_i: np.ndarray,
        uv_j: np.ndarray,
        *,
        sigma: float = 1.0,
        kernel: str | RobustKernel | None = None,
        compress: bool = True,
        offset: np.ndarray | None = None,
        name: str = "pose_graph_mpc",
    ) -> None:
        self.K = np.asarray(K, dtype=np.float64)
        if self.K.shape[-2:] != (3, 3) or self.K.ndim not in (2, 3):
            raise SlamError(f"K: expected shape (3, 3) or (C, 3, 3), got {self.K.shape}")
        check_finite("K", self.K)
        try:
            self.Kinv = np.linalg.inv(self.K)  # once, not per correspondence
        except np.linalg.LinAlgError as exc:
            raise SlamError("K: singular calibration matrix") from exc
        self.cameras_i = np.asarray(cameras_i, dtype=np.int64).reshape(-1)
        self.cameras_j = np.asarray(cameras_j, dtype=np.int64).reshape(-1)
        M = self.cameras_i.size
        self.uv_i = np.ascontiguousarray(uv_i, dtype=np.float64)
        self.uv_j = np.ascontiguousarray(uv_j, dtype=np.float64)
        if self.cameras_j.shape != (M,) or self.uv_i.shape != (M, 2) or self.uv_j.shape != (M, 2):
            raise SlamError(
                f"{name}: expected cameras_j ({M},), uv_i ({M}, 2), uv_j ({M}, 2); got "
                f"{self.cameras_j.shape}, {self.uv_i.shape}, {self.uv_j.shape}"
            )
        check_finite("uv_i", self.uv_i)
        check_finite("uv_j", self.uv_j)
        check_positive("sigma", sigma)
        self.sigma = float(sigma)
        self.kernel = get_kernel(kernel)
        self.compress = bool(compress)
        self.name = name
        self.offset = None
        if offset is not None:
            self.offset = np.asarray(offset, dtype=np.float64).reshape(-1)
            if self.offset.shape != (M,):
                raise SlamError(f"{name}: expected offset ({M},), got {self.offset.shape}")
            check_finite("offset", self.offset)
        # the compiled pass's arguments, built once
        self._kinv3 = np.ascontiguousarray(self.Kinv.reshape(-1, 3, 3))
        self._offset0 = np.zeros(M) if self.offset is None else self.offset
        pair_keys = np.stack([self.cameras_i, self.cameras_j], axis=1)
        self._pairs, self._pair_of = np.unique(pair_keys, axis=0, return_inverse=True)
        self._pair_of = self._pair_of.reshape(-1)
        # padded layout (pair, slot) of the rows, for batched per-pair products
        order = np.argsort(self._pair_of, kind="stable")
        counts = np.bincount(self._pair_of, minlength=len(self._pairs))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self._slot = np.empty(M, dtype=np.int64)
        self._slot[order] = np.arange(M) - np.repeat(starts, counts)
        self._max_rows = int(counts.max(initial=0))

    @property
    def num_residuals(self) -> int:
        """One epipolar distance per correspondence (however :meth:`evaluate` packs them)."""
        return self.cameras_i.size

    def _args(self, state: BAState) -> tuple[np.ndarray, ...]:
        C = state.num_cameras
        for cams in (self.cameras_i, self.cameras_j):
            if cams.size and (cams.max() >= C or cams.min() < 0):
                raise SlamError(f"{self.name}: camera index out of range for {C} cameras")
        if self.K.ndim == 2:
            K_i = K_j = self.Kinv
        else:
            K_i, K_j = self.Kinv[self.cameras_i], self.Kinv[self.cameras_j]
        return (
            state.R_wc[self.cameras_i],
            state.t_wc[self.cameras_i],
            state.R_wc[self.cameras_j],
            state.t_wc[self.cameras_j],
            K_i,
            K_j,
            self.uv_i,
            self.uv_j,
        )

    def _rows(self, state: BAState, jac: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Whitened rows ``r (M,)`` = ``(psi - offset) / sigma`` (0 where invalid), ``valid (M,)``
        and, if ``jac``, ``J (M, 12)`` = ``[J_i | J_j] / sigma`` (zero where invalid): the compiled
        pass when numba is enabled, else :func:`epipolar_residuals`."""
        inv_s = 1.0 / self.sigma
        if not numba_enabled():
            psi, valid, J_i, J_j = epipolar_residuals(*self._args(state), with_jacobians=jac)
            if self.offset is not None:
                psi = psi - self.offset
            r = np.where(valid, psi * inv_s, 0.0)
            J = np.concatenate([J_i, J_j], axis=1) * inv_s if jac else None
            return r, valid, J
        C = state.num_cameras
        for cams in (self.cameras_i, self.cameras_j):
            if cams.size and (cams.max() >= C or cams.min() < 0):
                raise SlamError(f"{self.name}: camera index out of range for {C} cameras")
        used = max(self.cameras_i.max(initial=-1), self.cameras_j.max(initial=-1))
        if self.K.ndim == 3 and used >= self.K.shape[0]:
            raise SlamError(f"{self.name}: {self.K.shape[0]} calibrations for a camera index >= it")
        M = self.cameras_i.size
        r, valid = np.empty(M), np.empty(M, dtype=bool)
        J = np.empty((M, 12) if jac else (0, 12))
        bad = _epipolar_kernel(
            self._kinv3,
            np.ascontiguousarray(state.R_wc),
            np.ascontiguousarray(state.t_wc),
            self.cameras_i,
            self.cameras_j,
            self.uv_i,
            self.uv_j,
            self._offset0,
            inv_s,
            1e-9,
            1e-12,
            r,
            valid,
            J,
            jac,
        )
        if bad >= 0:
            raise MPCDegenerateError(
                f"epipolar residual undefined: cameras of correspondence {bad} share one optical "
                "centre (baseline < 1e-09 m)"
            )
        return r, valid, (J if jac else None)

    def evaluate(self, state: BAState) -> FactorBlock:
        """The rows, ``a = 2`` (cameras ``i``, ``j``).

        Without compression: one row ``(1,)`` per correspondence. With compression (default,
        least-squares kernel only) one row ``(13,)`` per camera pair carrying exactly the same
        cost and normal equations (:meth:`_compressed`).
        """
        r, valid, J = self._rows(state, True)
        if self.compress and isinstance(self.kernel, TrivialKernel) and self._pairs.shape[0]:
            return self._compressed(r, J)
        return FactorBlock(
            residuals=r[:, None],
            cameras=np.stack([self.cameras_i, self.cameras_j], axis=1),
            J_cameras=J.reshape(-1, 2, 1, 6),
            kernel=self.kernel,
            valid=valid,
            name=self.name,
        )

    def _normal_equations(
        self, state: BAState, cmap: np.ndarray, pmap: np.ndarray, Cf: int, Pf: int
    ) -> tuple | None:
        """Compiled shortcut of :func:`slam_bridge.ba.normal_equations.assemble` for this family
        (numba only): the per-pair sums ``sum w J^T J`` and ``sum w J^T r`` of one compiled pass,
        scattered into the camera blocks; no compression, no materialised row blocks.

        Returns:
            :func:`slam_bridge.ba.normal_equations.pair_normal_equations`'s blocks, those
            :meth:`evaluate` leads the generic path to (up to rounding), or None when a subclass
            overrides :meth:`evaluate`.
        """
        if type(self).evaluate is not MPCFactor.evaluate:
            return None
        r, valid, J = self._rows(state, True)
        s = r * r
        rho = np.where(valid, self.kernel.rho(s), 0.0)
        w = np.ascontiguousarray(np.where(valid, self.kernel.weight(s), 0.0), dtype=np.float64)
        Q = self._pairs.shape[0]
        H, g = np.zeros((Q, 12, 12)), np.zeros((Q, 12))
        _pair_sums_kernel(J, r, w, self._pair_of, H, g)
        n_invalid = int(valid.size - np.count_nonzero(valid))
        return pair_normal_equations(float(np.sum(rho)), n_invalid, H, g, self._pairs, cmap, Cf, Pf)

    def _compressed(self, r: np.ndarray, J: np.ndarray) -> FactorBlock:
        """One row per camera pair with the same ``sum r^2``, ``J^T J`` and ``J^T r``.

        Per pair ``p``: ``H_p = sum J^T J = V diag(lam) V^T`` (``12 x 12``), ``b_p = sum J^T r``,
        ``c_p = sum r^2``. The row is ``r~ = [lam^-1/2 V^T b_p ; sqrt(c_p - |.|^2)]`` with
        Jacobian ``[diag(lam^1/2) V^T ; 0]`` (eigen-directions with ``lam <= 1e-12 lam_max``
        dropped: ``b_p`` has no component there). Then ``J~^T J~ = H_p``, ``J~^T r~ = b_p`` and
        ``|r~|^2 = c_p``: the assembler sees the same normal equations and cost as with one row
        per correspondence, for ``Q`` rows instead of ``M`` (an exact reformulation for the
        least-squares kernel; the residual rows themselves are not the epipolar distances).
        """
        Q = self._pairs.shape[0]
        Jp = np.zeros((Q, self._max_rows, 12))
        rp = np.zeros((Q, self._max_rows))
        Jp[self._pair_of, self._slot] = J
        rp[self._pair_of, self._slot] = r
        Jpt = np.swapaxes(Jp, 1, 2)
        H = Jpt @ Jp  # (Q, 12, 12)
        b = (Jpt @ rp[:, :, None])[:, :, 0]  # (Q, 12)
        c = np.sum(rp * rp, axis=1)  # (Q,)
        lam, V = np.linalg.eigh(H)
        keep = lam > 1e-12 * np.maximum(lam[:, -1:], 1e-300)
        sq = np.sqrt(np.where(keep, lam, 1.0))
        Vtb = np.einsum("qab,qa->qb", V, b)  # V^T b
        rt = np.where(keep, Vtb / sq, 0.0)  # (Q, 12)
        rest = np.sqrt(np.maximum(c - np.sum(rt * rt, axis=1), 0.0))
        res = np.concatenate([rt, rest[:, None]], axis=1)  # (Q, 13)
        Jt = np.zeros((Q, 13, 12))
        Jt[:, :12, :] = np.where(keep[:, :, None], sq[:, :, None] * np.swapaxes(V, 1, 2), 0.0)
        J_cams = np.stack([Jt[:, :, :6], Jt[:, :, 6:]], axis=1)  # (Q, 2, 13, 6)
        return FactorBlock(
            residuals=res,
            cameras=self._pairs,
            J_cameras=J_cams,
            kernel=self.kernel,
            name=self.name,
        )

    def relative_to(self, state: BAState) -> MPCFactor:
        """This factor with ``offset`` = the epipolar distances at ``state`` (then ``xi = 0``
        and its gradient vanishes there: ``state`` is the pose graph's rest position)."""
        psi, valid, _, _ = epipolar_residuals(*self._args(state), with_jacobians=False)
        return MPCFactor(
            self.K,
            self.cameras_i,
            self.cameras_j,
            self.uv_i,
            self.uv_j,
            sigma=self.sigma,
            kernel=self.kernel,
            compress=self.compress,
            offset=np.where(valid, psi, 0.0),
            name=self.name,
        )

    def cost(self, state: BAState) -> float:
        """``sum_k rho(((psi_k - offset_k) / sigma)^2)`` over valid rows."""
        return self.cost_and_invalid(state)[0]

    def cost_and_invalid(self, state: BAState) -> tuple[float, int]:
        """The cost and the number of invalid rows (points on the epipole), no Jacobians."""
        r, valid, _ = self._rows(state, False)
        rho = np.where(valid, self.kernel.rho(r * r), 0.0)
        return float(np.sum(rho)), int(valid.size - np.count_nonzero(valid))
