"""Heading change between two cameras, as wheel odometry or a gyro measures it.

A vehicle turns about its vertical axis; a camera mounted on it with its y axis down (car or
tram camera) turns about its own ``-y`` by the same angle, whatever way it looks. Row per pair
``(i, j)``: ``r = (e_y . log(R_i^T R_j) + dpsi) / sigma`` with ``dpsi`` the measured heading
change (counter-clockwise seen from above, a turn about ``-y``). With the left update
``R <- exp(dw) R``, ``R_i^T R_j`` turns on its left by ``R_i^T (dw_j - dw_i)``, so
``d log(R_i^T R_j) = J_l^{-1}(log(R_i^T R_j)) R_i^T (dw_j - dw_i)``. Only the off-diagonal blocks of two cameras are
filled (no dense term, appendix B).
"""

from __future__ import annotations

import numpy as np

from slam_bridge.ba.factor import FactorBlock
from slam_bridge.errors import SlamError
from slam_bridge.geometry.lie import so3_left_jacobian_inv, so3_log

__all__ = ["YawChangeFactor"]


class YawChangeFactor:
    """Heading change between camera pairs (module docstring).

    Args:
        pairs: ``(Q, 2)`` state camera indices ``(i, j)``.
        dpsi: ``(Q,)`` measured heading changes from ``i`` to ``j``, radians (counter-clockwise).
        sigma: radians, scalar or ``(Q,)``.
        kernel: robust kernel of the rows (default least squares).
    """

    def __init__(self, pairs: np.ndarray, dpsi: np.ndarray, sigma, *, kernel=None) -> None:
        from slam_bridge.ba.robust import get_kernel

        self.kernel = get_kernel(kernel)
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        self.dpsi = np.asarray(dpsi, dtype=np.float64).reshape(-1)
        if self.dpsi.shape != (self.pairs.shape[0],) or not np.isfinite(self.dpsi).all():
            raise SlamError("dpsi: expected one finite heading change per pair")
        sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), self.dpsi.shape)
        if not np.all(sigma > 0):
            raise SlamError(f"sigma: expected > 0, got {sigma}")
        self.sigma = sigma.copy()
        self.name = "yaw_change"

    @property
    def num_residuals(self) -> int:
        """One per pair."""
        return self.pairs.shape[0]

    def _r(self, state) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Ri = state.R_wc[self.pairs[:, 0]]
        rel = np.einsum("qji,qjk->qik", Ri, state.R_wc[self.pairs[:, 1]])  # R_i^T R_j
        w = so3_log(rel).reshape(-1, 3)  # batched: this runs at every LM iteration
        return (w[:, 1] + self.dpsi) / self.sigma, Ri, w

    def evaluate(self, state) -> FactorBlock:
        """Rows ``(Q, 1)`` over the pairs, ``J (Q, 2, 1, 6)``."""
        r, Ri, w = self._r(state)
        rows = so3_left_jacobian_inv(w)[:, 1, :]
        g = np.einsum("qa,qba->qb", rows, Ri) / self.sigma[:, None]  # e_y^T J_l^-1 R_i^T
        J = np.zeros((r.size, 2, 1, 6))
        J[:, 0, 0, :3] = -g
        J[:, 1, 0, :3] = g
        return FactorBlock(r[:, None], self.pairs, J, kernel=self.kernel, name=self.name)

    def cost(self, state) -> float:
        """``sum rho(r^2)``."""
        return float(np.sum(self.kernel.rho(self._r(state)[0] ** 2)))

    def cost_and_invalid(self, state) -> tuple[float, int]:
        """``(cost, 0)``."""
        return self.cost(state), 0
