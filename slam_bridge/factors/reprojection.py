"""Reprojection residuals (thesis eq. 1.24), the k-BA's vision term.

Row ``m`` observes point ``points[m]`` in camera ``cameras[m]`` at pixel ``uv[m]``::

    r_m = (pi(K R_wc^T (X_w - t_wc)) - uv_m) / sigma            (k = 2, a = 1)

Rows whose point is not in front of the camera (``z_c <= eps``) are flagged invalid (zero
residual and Jacobian, counted in ``FactorBlock.n_invalid``), never divided by. With ``numba``
(:data:`slam_bridge.ba.compiled.USE_NUMBA`) residuals and Jacobians come from one compiled pass that
gathers cameras and points by index (same formulas as :mod:`slam_bridge.geometry.camera`).
"""

from __future__ import annotations

import logging

import numpy as np

from geoseg.errors import check_finite, check_positive
from slam_bridge.ba.compiled import _njit, numba_enabled
from slam_bridge.ba.factor import FactorBlock
from slam_bridge.ba.normal_equations import _mirror_kernel
from slam_bridge.ba.robust import RobustKernel, get_kernel
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.geometry.camera import DEFAULT_EPS, _check_K, project, project_with_jacobians

logger = logging.getLogger(__name__)

__all__ = ["ReprojectionFactor"]


@_njit
def _reproj_kernel(
    K, R, t, X, cams, pts, uv_obs, inv_s, eps, r, ok, Jc, Jp, jac
):  # pragma: no cover
    """Compiled residuals (and, if ``jac``, Jacobians) of every row, gathering the cameras and
    points by index (the formulas of :func:`slam_bridge.geometry.camera.project_with_jacobians`).

    ``K (1 or C, 3, 3)`` (one shared or one per state camera), ``R (C, 3, 3)``, ``t (C, 3)``,
    ``X (P, 3)``, ``cams``/``pts (M,)``, ``uv_obs (M, 2)``; writes ``r (M, 2)``, ``ok (M,)`` and
    ``Jc (M, 2, 6)``, ``Jp (M, 2, 3)`` (zero where not in front).
    """
    per_cam = K.shape[0] > 1
    for m in range(cams.shape[0]):
        c = cams[m]
        p = pts[m]
        kk = c if per_cam else 0
        d0 = X[p, 0] - t[c, 0]
        d1 = X[p, 1] - t[c, 1]
        d2 = X[p, 2] - t[c, 2]
        xc = R[c, 0, 0] * d0 + R[c, 1, 0] * d1 + R[c, 2, 0] * d2
        yc = R[c, 0, 1] * d0 + R[c, 1, 1] * d1 + R[c, 2, 1] * d2
        zc = R[c, 0, 2] * d0 + R[c, 1, 2] * d1 + R[c, 2, 2] * d2
        if not zc > eps:  # not in front (or NaN): never divide
            ok[m] = False
            r[m, 0] = 0.0
            r[m, 1] = 0.0
            if jac:
                for q in range(2):
                    for a in range(6):
                        Jc[m, q, a] = 0.0
                    for a in range(3):
                        Jp[m, q, a] = 0.0
            continue
        ok[m] = True
        fx, sk, cx = K[kk, 0, 0], K[kk, 0, 1], K[kk, 0, 2]
        fy, cy = K[kk, 1, 1], K[kk, 1, 2]
        iz = 1.0 / zc
        x = xc * iz
        y = yc * iz
        r[m, 0] = (fx * x + sk * y + cx - uv_obs[m, 0]) * inv_s
        r[m, 1] = (fy * y + cy - uv_obs[m, 1]) * inv_s
        if jac:
            # J_pt = [[fx, s, -(fx x + s y)], [0, fy, -fy y]] / z R^T; J_cam = [J_pt hat(d), -J_pt]
            a0 = fx * iz * inv_s
            a1 = sk * iz * inv_s
            a2 = -(fx * x + sk * y) * iz * inv_s
            b1 = fy * iz * inv_s
            b2 = -fy * y * iz * inv_s
            for i in range(3):
                Jp[m, 0, i] = R[c, i, 0] * a0 + R[c, i, 1] * a1 + R[c, i, 2] * a2
                Jp[m, 1, i] = R[c, i, 1] * b1 + R[c, i, 2] * b2
            for q in range(2):
                e0, e1, e2 = Jp[m, q, 0], Jp[m, q, 1], Jp[m, q, 2]
                Jc[m, q, 0] = e1 * d2 - e2 * d1
                Jc[m, q, 1] = e2 * d0 - e0 * d2
                Jc[m, q, 2] = e0 * d1 - e1 * d0
                Jc[m, q, 3] = -e0
                Jc[m, q, 4] = -e1
                Jc[m, q, 5] = -e2


@_njit
def _reproj_normal_kernel(
    K, R, t, X, cams, pts, inv_s, eps, r, w, ci, pj, U, g_c, V, g_p, W, Wc, Wp
):  # pragma: no cover
    """Compiled reprojection Jacobians accumulated straight into the normal equations.

    Same inputs as :func:`_reproj_kernel` plus the residuals ``r (M, 2)`` of that kernel, the
    robust weights ``w (M,)`` (0 where invalid) and the free indices ``ci``/``pj (M,)``; the
    Jacobians of each row are recomputed in registers (never stored) and added as in
    :func:`slam_bridge.ba.normal_equations._one_cam_one_point_kernel` (written out again: a shared
    helper is 3x slower). ``U``/``V`` must start at zero. Returns the number of ``W`` blocks.
    """
    per_cam = K.shape[0] > 1
    n = 0
    for m in range(cams.shape[0]):
        c = ci[m]
        p = pj[m]
        if c < 0 and p < 0:
            continue
        sc = cams[m]
        sp = pts[m]
        kk = sc if per_cam else 0
        d0 = X[sp, 0] - t[sc, 0]
        d1 = X[sp, 1] - t[sc, 1]
        d2 = X[sp, 2] - t[sc, 2]
        zc = R[sc, 0, 2] * d0 + R[sc, 1, 2] * d1 + R[sc, 2, 2] * d2
        # the row's Jacobians live in registers (tuples): scratch arrays would alias U, V, W
        if zc > eps:
            yc = R[sc, 0, 1] * d0 + R[sc, 1, 1] * d1 + R[sc, 2, 1] * d2
            fx, sk = K[kk, 0, 0], K[kk, 0, 1]
            fy = K[kk, 1, 1]
            iz = 1.0 / zc
            xc = R[sc, 0, 0] * d0 + R[sc, 1, 0] * d1 + R[sc, 2, 0] * d2
            x = xc * iz
            y = yc * iz
            a0 = fx * iz * inv_s
            a1 = sk * iz * inv_s
            a2 = -(fx * x + sk * y) * iz * inv_s
            b1 = fy * iz * inv_s
            b2 = -fy * y * iz * inv_s
            p00 = R[sc, 0, 0] * a0 + R[sc, 0, 1] * a1 + R[sc, 0, 2] * a2
            p01 = R[sc, 1, 0] * a0 + R[sc, 1, 1] * a1 + R[sc, 1, 2] * a2
            p02 = R[sc, 2, 0] * a0 + R[sc, 2, 1] * a1 + R[sc, 2, 2] * a2
            p10 = R[sc, 0, 1] * b1 + R[sc, 0, 2] * b2
            p11 = R[sc, 1, 1] * b1 + R[sc, 1, 2] * b2
            p12 = R[sc, 2, 1] * b1 + R[sc, 2, 2] * b2
        else:
            p00 = p01 = p02 = p10 = p11 = p12 = 0.0
            d0 = d1 = d2 = 0.0
        jp0 = (p00, p01, p02)
        jp1 = (p10, p11, p12)
        jc0 = (p01 * d2 - p02 * d1, p02 * d0 - p00 * d2, p00 * d1 - p01 * d0, -p00, -p01, -p02)
        jc1 = (p11 * d2 - p12 * d1, p12 * d0 - p10 * d2, p10 * d1 - p11 * d0, -p10, -p11, -p12)
        wm = w[m]
        r0 = r[m, 0]
        r1 = r[m, 1]
        if c >= 0:
            for a in range(6):
                ja0 = jc0[a] * wm
                ja1 = jc1[a] * wm
                g_c[c, a] += ja0 * r0 + ja1 * r1
                for b in range(a, 6):
                    U[c, a, b] += ja0 * jc0[b] + ja1 * jc1[b]
        if p >= 0:
            for a in range(3):
                ja0 = jp0[a] * wm
                ja1 = jp1[a] * wm
                g_p[p, a] += ja0 * r0 + ja1 * r1
                for b in range(a, 3):
                    V[p, a, b] += ja0 * jp0[b] + ja1 * jp1[b]
            if c >= 0:
                for a in range(6):
                    ja0 = jc0[a] * wm
                    ja1 = jc1[a] * wm
                    for b in range(3):
                        W[n, a, b] = ja0 * jp0[b] + ja1 * jp1[b]
                Wc[n] = c
                Wp[n] = p
                n += 1
    _mirror_kernel(U, V)
    return n


class ReprojectionFactor:
    """All reprojection observations of a problem, vectorised.

    Args:
        K: ``(3, 3)`` shared calibration or ``(C, 3, 3)`` one per state camera (fixed).
        cameras: ``(M,)`` int state camera index of each observation.
        points: ``(M,)`` int state point index of each observation.
        uv: ``(M, 2)`` observed pixels (finite).
        sigma: pixel standard deviation (residuals are divided by it).
        kernel: robust kernel name or object (``None`` = least squares).
        kernel_scale: kernel threshold in whitened units (``delta``/``sigma`` of the kernel).
        eps: minimal depth for a valid observation.
        name: label for per-family costs.
    """

    def __init__(
        self,
        K: np.ndarray,
        cameras: np.ndarray,
        points: np.ndarray,
        uv: np.ndarray,
        sigma: float = 1.0,
        kernel: str | RobustKernel | None = None,
        kernel_scale: float | None = None,
        eps: float = DEFAULT_EPS,
        name: str = "reprojection",
    ) -> None:
        self.K = _check_K(K)
        self.cameras = np.asarray(cameras, dtype=np.int64).reshape(-1)
        self.points = np.asarray(points, dtype=np.int64).reshape(-1)
        self.uv = np.asarray(uv, dtype=np.float64)
        M = self.cameras.size
        if self.points.shape != (M,):
            raise SlamError(f"points: expected shape ({M},), got {self.points.shape}")
        if self.uv.shape != (M, 2):
            raise SlamError(f"uv: expected shape ({M}, 2), got {self.uv.shape}")
        check_finite("uv", self.uv)
        check_positive("sigma", sigma)
        self.sigma = float(sigma)
        self.kernel = get_kernel(kernel, kernel_scale)
        self.eps = float(eps)
        self.name = name

    def _K_rows(self) -> np.ndarray:
        return self.K if self.K.ndim == 2 else self.K[self.cameras]

    @property
    def num_residuals(self) -> int:
        """Scalar residuals: two per observation."""
        return 2 * self.cameras.size

    def _check_state(self, state: BAState) -> None:
        if self.cameras.size and (
            self.cameras.max() >= state.num_cameras or self.cameras.min() < 0
        ):
            raise SlamError(
                f"{self.name}: camera index out of range for {state.num_cameras} cameras"
            )
        if self.points.size and (self.points.max() >= state.num_points or self.points.min() < 0):
            raise SlamError(f"{self.name}: point index out of range for {state.num_points} points")
        if self.K.ndim == 3 and self.cameras.size and self.cameras.max() >= self.K.shape[0]:
            raise SlamError(f"{self.name}: {self.K.shape[0]} calibrations for a camera index >= it")

    def _compiled(self, state: BAState, jac: bool) -> tuple[np.ndarray, ...]:
        """``r (M, 2)``, ``ok (M,)``, ``Jc (M, 2, 6)``, ``Jp (M, 2, 3)`` by the compiled kernel
        (Jacobians left empty unless ``jac``)."""
        M = self.cameras.size
        r, ok = np.empty((M, 2)), np.empty(M, dtype=bool)
        Jc = np.empty((M, 2, 6) if jac else (0, 2, 6))
        Jp = np.empty((M, 2, 3) if jac else (0, 2, 3))
        _reproj_kernel(
            self.K.reshape(-1, 3, 3),
            np.ascontiguousarray(state.R_wc),
            np.ascontiguousarray(state.t_wc),
            np.ascontiguousarray(state.X_w),
            self.cameras,
            self.points,
            self.uv,
            1.0 / self.sigma,
            self.eps,
            r,
            ok,
            Jc,
            Jp,
            jac,
        )
        return r, ok, Jc, Jp

    def _normal_equations(
        self, state: BAState, cmap: np.ndarray, pmap: np.ndarray, Cf: int, Pf: int
    ) -> tuple | None:
        """Compiled shortcut of :func:`slam_bridge.ba.normal_equations.assemble` for this family
        (used only when numba is enabled): its normal-equation blocks without materialising the
        Jacobians.

        Args:
            state: the current state.
            cmap: ``(C,)`` free index of each camera (``-1`` = fixed).
            pmap: ``(P,)`` free index of each point.
            Cf: free cameras.
            Pf: free points.

        Returns:
            ``(cost, n_invalid, U (Cf, 6, 6), g_c (Cf, 6), V (Pf, 3, 3), g_p (Pf, 3), W (N, 6, 3),
            W_cameras (N,), W_points (N,))`` exactly as the generic path would assemble them
            from :meth:`evaluate` (up to rounding), or None when a subclass overrides
            :meth:`evaluate` (the generic path must then see its rows).
        """
        if type(self).evaluate is not ReprojectionFactor.evaluate:
            return None
        self._check_state(state)
        r, ok, _, _ = self._compiled(state, False)
        s = np.where(ok, np.einsum("mk,mk->m", r, r), 0.0)
        rho = np.where(ok, self.kernel.rho(s), 0.0)
        w = np.where(ok, self.kernel.weight(s), 0.0)
        ci, pj = cmap[self.cameras], pmap[self.points]
        U, g_c = np.zeros((Cf, 6, 6)), np.zeros((Cf, 6))
        V, g_p = np.zeros((Pf, 3, 3)), np.zeros((Pf, 3))
        N = int(np.count_nonzero((ci >= 0) & (pj >= 0)))
        W = np.empty((N, 6, 3))
        Wc = np.empty(N, dtype=np.int64)
        Wp = np.empty(N, dtype=np.int64)
        _reproj_normal_kernel(
            self.K.reshape(-1, 3, 3),
            np.ascontiguousarray(state.R_wc),
            np.ascontiguousarray(state.t_wc),
            np.ascontiguousarray(state.X_w),
            self.cameras,
            self.points,
            1.0 / self.sigma,
            self.eps,
            r,
            np.ascontiguousarray(w, dtype=np.float64),
            ci,
            pj,
            U,
            g_c,
            V,
            g_p,
            W,
            Wc,
            Wp,
        )
        n_invalid = int(ok.size - np.count_nonzero(ok))
        return float(np.sum(rho)), n_invalid, U, g_c, V, g_p, W, Wc, Wp

    def residuals(self, state: BAState) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals ``(M, 2)`` (0 where invalid) and the valid mask ``(M,)``."""
        self._check_state(state)
        if numba_enabled():
            return self._compiled(state, False)[:2]
        uv, _, ok = project(
            self._K_rows(),
            state.R_wc[self.cameras],
            state.t_wc[self.cameras],
            state.X_w[self.points],
            self.eps,
        )
        r = np.where(ok[:, None], (uv - self.uv) / self.sigma, 0.0)
        return r, ok

    def evaluate(self, state: BAState) -> FactorBlock:
        """All rows with their Jacobians (``a = 1``, ``k = 2``)."""
        self._check_state(state)
        if numba_enabled():
            r, ok, Jc, Jp = self._compiled(state, True)
            return FactorBlock(
                residuals=r,
                cameras=self.cameras[:, None],
                J_cameras=Jc[:, None],
                points=self.points,
                J_points=Jp,
                kernel=self.kernel,
                valid=ok,
                name=self.name,
            )
        uv, _, ok, Jc, Jp = project_with_jacobians(
            self._K_rows(),
            state.R_wc[self.cameras],
            state.t_wc[self.cameras],
            state.X_w[self.points],
            self.eps,
        )
        inv_s = 1.0 / self.sigma
        r = np.where(ok[:, None], (uv - self.uv) * inv_s, 0.0)
        if self.sigma != 1.0:
            Jc = Jc * inv_s
            Jp = Jp * inv_s
        return FactorBlock(
            residuals=r,
            cameras=self.cameras[:, None],
            J_cameras=Jc[:, None],
            points=self.points,
            J_points=Jp,
            kernel=self.kernel,
            valid=ok,
            name=self.name,
        )

    def cost(self, state: BAState) -> float:
        """``sum rho(||r||^2)`` over valid rows."""
        return self.cost_and_invalid(state)[0]

    def cost_and_invalid(self, state: BAState) -> tuple[float, int]:
        """``sum rho(||r||^2)`` over valid rows and the number of invalid rows."""
        r, ok = self.residuals(state)
        s = np.einsum("mk,mk->m", r, r)
        return float(np.sum(np.where(ok, self.kernel.rho(s), 0.0))), int(
            ok.size - np.count_nonzero(ok)
        )
