"""Shared machinery of the unary position factors (GPS, odometry, DEM: appendix B.3).

Each of these families constrains the optical centre ``T_i = t_wc[cameras[i]]`` of one camera
per residual row (``a = 1`` in :class:`~slam_bridge.ba.factor.FactorBlock`), whitened by a
per-row weight ``w_i``. They differ only in the residual function ``h``; a subclass of
:class:`SingleCameraFactor` provides it as :meth:`SingleCameraFactor._residuals` and inherits
the camera-index check, :meth:`~SingleCameraFactor.evaluate` and
:meth:`~SingleCameraFactor.cost`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from geoseg.errors import GeosegError, check_shape
from slam_bridge.ba.factor import FactorBlock
from slam_bridge.ba.normal_equations import camera_only_blocks
from slam_bridge.ba.robust import RobustKernel, get_kernel
from slam_bridge.errors import SlamError

if TYPE_CHECKING:
    from slam_bridge.ba.state import BAState

__all__ = ["SingleCameraFactor", "check_weights"]


def check_weights(
    weights: np.ndarray | None,
    M: int,
    label: str,
    *,
    error: type[GeosegError] = GeosegError,
) -> np.ndarray:
    """Validate per-row factor weights.

    Args:
        weights: ``(M,)`` (any shape with ``M`` elements) non-negative weights, or ``None``
            (all 1).
        M: number of rows.
        label: family name used in the error message (``"GPS"``, ``"odometry"``, ...).
        error: exception class raised for non-finite or negative weights.

    Returns:
        ``(M,)`` float64 weights.

    Raises:
        GeosegError: wrong number of weights (from :func:`~geoseg.errors.check_shape`).
        error: a non-finite or negative weight.
    """
    w = np.ones(M) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    check_shape("weights", w, (M,))
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise error(f"weights: expected finite non-negative {label} weights")
    return w


class SingleCameraFactor:
    """Base of the factor families whose every row involves exactly one camera and no point.

    Subclasses call ``super().__init__`` once their own data are validated and implement
    :meth:`_residuals`.

    Args:
        cameras: ``(M,)`` state camera index of each row.
        weights: ``(M,)`` non-negative row weights, or ``None`` (all 1); see
            :func:`check_weights`.
        kernel: robust kernel (default least squares).
        name: family label in cost reports and error messages.
        weight_label: family name in the weight error message.
        error: exception class for bad weights.

    Attributes:
        cameras: ``(M,)`` int64 camera indices.
        sqrt_weights: ``(M,)`` square roots of the weights.
        kernel: the robust kernel object.
        name: the family label.
    """

    def __init__(
        self,
        cameras: np.ndarray,
        weights: np.ndarray | None,
        *,
        kernel: str | RobustKernel | None,
        name: str,
        weight_label: str,
        error: type[GeosegError] = GeosegError,
    ) -> None:
        self.cameras = np.asarray(cameras, dtype=np.int64).reshape(-1)
        w = check_weights(weights, self.cameras.size, weight_label, error=error)
        self.sqrt_weights = np.sqrt(w)
        self.kernel = get_kernel(kernel)
        self.name = name

    def _residuals(self, t_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals and Jacobians of all rows.

        Args:
            t_wc: ``(M, 3)`` optical centres of the constrained cameras, row ``i`` for
                ``cameras[i]``.

        Returns:
            ``(r, J)``: ``r (M, k)``; ``J (M, k, 6)`` with respect to ``[dw, dT]``.
        """
        raise NotImplementedError

    def _check(self, state: BAState) -> None:
        if self.cameras.size and (
            self.cameras.max() >= state.num_cameras or self.cameras.min() < 0
        ):
            raise SlamError(f"{self.name}: camera index out of range for {state.num_cameras}")

    def evaluate(self, state: BAState) -> FactorBlock:
        """Rows ``(M, k)``, ``a = 1``."""
        self._check(state)
        r, J = self._residuals(state.t_wc[self.cameras])
        return FactorBlock(
            residuals=r,
            cameras=self.cameras[:, None],
            J_cameras=J[:, None],
            kernel=self.kernel,
            name=self.name,
        )

    def _normal_equations(
        self, state: BAState, cmap: np.ndarray, pmap: np.ndarray, Cf: int, Pf: int
    ) -> tuple | None:
        """Shortcut of :func:`slam_bridge.ba.normal_equations.assemble` for this family (used with
        numba): its few rows' camera blocks by one batched product, without the generic path's
        segment sums (a GPS fix is one row per fusion iteration).

        Returns:
            :func:`slam_bridge.ba.normal_equations.camera_only_blocks`, or None when a subclass
            overrides :meth:`evaluate`.
        """
        if type(self).evaluate is not SingleCameraFactor.evaluate:
            return None
        self._check(state)
        r, J = self._residuals(state.t_wc[self.cameras])  # (M, k), (M, k, 6)
        s = np.einsum("mk,mk->m", r, r)
        JtW = np.swapaxes(J, 1, 2) * self.kernel.weight(s)[:, None, None]
        ci = cmap[self.cameras]
        free = ci >= 0
        U, g_c = np.zeros((Cf, 6, 6)), np.zeros((Cf, 6))
        np.add.at(U, ci[free], (JtW @ J)[free])
        np.add.at(g_c, ci[free], (JtW @ r[:, :, None])[free, :, 0])
        return camera_only_blocks(float(np.sum(self.kernel.rho(s))), 0, U, g_c, Pf)

    def cost(self, state: BAState) -> float:
        """``sum_i rho(||r_i||^2)`` over all rows."""
        self._check(state)
        r, _ = self._residuals(state.t_wc[self.cameras])
        return float(np.sum(self.kernel.rho(np.einsum("mk,mk->m", r, r))))
