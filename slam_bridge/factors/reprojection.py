"""Reprojection residuals (thesis eq. 1.24), the k-BA's vision term.

Row ``m`` observes point ``points[m]`` in camera ``cameras[m]`` at pixel ``uv[m]``::

    r_m = (pi(K R_wc^T (X_w - t_wc)) - uv_m) / sigma            (k = 2, a = 1)

Rows whose point is not in front of the camera (``z_c <= eps``) are flagged invalid (zero
residual and Jacobian, counted in ``FactorBlock.n_invalid``), never divided by.
"""

from __future__ import annotations

import logging

import numpy as np

from geoseg.errors import check_finite, check_positive
from slam_bridge.camera import DEFAULT_EPS, _check_K, project, project_with_jacobians
from slam_bridge.errors import SlamError
from slam_bridge.factors.base import FactorBlock
from slam_bridge.problem import BAState
from slam_bridge.solvers.robust import RobustKernel, get_kernel

logger = logging.getLogger(__name__)

__all__ = ["ReprojectionFactor"]


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

    def _check_state(self, state: BAState) -> None:
        if self.cameras.size and (
            self.cameras.max() >= state.num_cameras or self.cameras.min() < 0
        ):
            raise SlamError(
                f"{self.name}: camera index out of range for {state.num_cameras} cameras"
            )
        if self.points.size and (self.points.max() >= state.num_points or self.points.min() < 0):
            raise SlamError(f"{self.name}: point index out of range for {state.num_points} points")

    def residuals(self, state: BAState) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals ``(M, 2)`` (0 where invalid) and the valid mask ``(M,)``."""
        self._check_state(state)
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
