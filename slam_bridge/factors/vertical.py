"""The world's vertical as a camera measured it: a constraint on the camera's tilt.

A camera that measured world down as the unit vector ``d`` in its own frame (e.g. the vertical
vanishing point, :mod:`slam_bridge.frontend.vertical_lines`) with covariance ``Sigma`` along an
orthonormal basis ``B (2, 3)`` of the plane orthogonal to ``d`` gives, with ``g = (0, 0, -1)``
the world's down:

``r = S B (R_wc^T g)``,   ``S = Sigma^(-1/2)``   (2 rows; zero when ``R_wc^T g = d``).

With the increment ``R_wc <- exp(hat(dw)) R_wc``, ``R_wc^T g <- R_wc^T (g + hat(g) dw)``, so
``dr / d[dw] = S B R_wc^T hat(g)`` and ``dr / d[dT] = 0``: one camera's rotation block, no dense
term (appendix B). Heading (rotation about ``g``) is not constrained.
"""

from __future__ import annotations

import numpy as np

from geoseg.errors import check_finite, check_shape
from slam_bridge.ba.factor import FactorBlock
from slam_bridge.ba.robust import RobustKernel, get_kernel
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.geometry.lie import so3_hat

__all__ = ["VerticalFactor"]

_DOWN_W = np.array([0.0, 0.0, -1.0])


class VerticalFactor:
    """Measured verticals on some cameras, two rows each (module docstring).

    Args:
        cameras: ``(M,)`` state camera indices.
        basis: ``(M, 2, 3)`` orthonormal rows orthogonal to each measured down direction.
        covariance: ``(M, 2, 2)`` symmetric positive definite, rad^2, along ``basis``.
        kernel: robust kernel (a measurement from the wrong segments is an outlier).
        name: family label.

    Raises:
        SlamError: shapes that disagree, non-finite values, a covariance that is not positive
            definite.
    """

    def __init__(
        self,
        cameras: np.ndarray,
        basis: np.ndarray,
        covariance: np.ndarray,
        *,
        kernel: str | RobustKernel | None = "huber",
        name: str = "vertical",
    ) -> None:
        self.cameras = np.asarray(cameras, dtype=np.int64).reshape(-1)
        M = self.cameras.size
        self.basis = np.asarray(basis, dtype=np.float64)
        covariance = np.asarray(covariance, dtype=np.float64)
        check_shape("basis", self.basis, (M, 2, 3))
        check_shape("covariance", covariance, (M, 2, 2))
        check_finite("basis", self.basis)
        check_finite("covariance", covariance)
        try:
            L = np.linalg.cholesky(0.5 * (covariance + np.swapaxes(covariance, 1, 2)))
        except np.linalg.LinAlgError:
            raise SlamError("covariance: expected positive definite 2x2 blocks") from None
        self.sqrt_info = np.linalg.inv(L)  # S with S Sigma S^T = I
        self.kernel = get_kernel(kernel)
        self.name = name

    @property
    def num_residuals(self) -> int:
        """Scalar residuals (two per camera)."""
        return 2 * self.cameras.size

    def _rows(self, state: BAState, jacobians: bool) -> tuple[np.ndarray, np.ndarray | None]:
        if self.cameras.size and (
            self.cameras.max() >= state.num_cameras or self.cameras.min() < 0
        ):
            raise SlamError(f"{self.name}: camera index out of range for {state.num_cameras}")
        R = state.R_wc[self.cameras]  # (M, 3, 3)
        SB = self.sqrt_info @ self.basis  # (M, 2, 3)
        down_c = np.einsum("mji,j->mi", R, _DOWN_W)  # R^T g
        r = np.einsum("mkj,mj->mk", SB, down_c)
        if not jacobians:
            return r, None
        J = np.zeros((self.cameras.size, 2, 6))
        J[:, :, :3] = SB @ np.swapaxes(R, 1, 2) @ so3_hat(_DOWN_W)
        return r, J

    def evaluate(self, state: BAState) -> FactorBlock:
        """Rows ``(M, 2)``, one camera each."""
        r, J = self._rows(state, jacobians=True)
        return FactorBlock(
            residuals=r,
            cameras=self.cameras[:, None],
            J_cameras=J[:, None],
            kernel=self.kernel,
            name=self.name,
        )

    def cost(self, state: BAState) -> float:
        """``sum_m rho(||r_m||^2)``."""
        r, _ = self._rows(state, jacobians=False)
        return float(np.sum(self.kernel.rho(np.einsum("mk,mk->m", r, r))))
