"""Building constraint: map points on their facade planes (thesis eqs. 2.4 and 4.2).

For a map point ``q`` (``X_w[q]``) associated with the facade plane ``p_q`` of unit normal
``n_q`` and offset ``c_q`` (the plane is ``{x : n_q . x = c_q}``, world frame), the signed
point-to-plane distance is ``d_q = n_q . X_q - c_q`` and the constraint is::

    C_building = sum_q W_q rho(d_q^2),   rho(s) = sigma^2 s / (sigma^2 + s)   (Geman-McClure)

with ``W_q`` the point's weight (the Dirichlet density of chapter 4, eq. 4.2; 1 for eq. 2.4)
and ``sigma`` the kernel scale in metres. The residual row of ``q`` is the scalar ``d_q``
(``k = 1``) with point Jacobian ``n_q^T`` and no camera (``a = 0``): its Gauss-Newton block sits
in the point diagonal block ``V_q``, so the constraint adds no dense term (appendix B.4).

The per-point weights ride on the robust kernel (:class:`WeightedKernel`,
``rho_W(s)_q = W_q rho(s_q)``) so the core's IRLS assembler applies them unchanged.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from geoseg.errors import GeosegError, check_finite, check_positive, check_shape
from slam_bridge.ba.factor import FactorBlock
from slam_bridge.ba.robust import GemanMcClureKernel, RobustKernel, get_kernel
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = ["BuildingFactor", "WeightedKernel", "point_plane_residuals"]


@dataclass(frozen=True)
class WeightedKernel:
    """A robust kernel scaled per row: ``rho(s)_m = weights[m] * base.rho(s_m)``.

    Attributes:
        base: the underlying kernel.
        weights: ``(M,)`` non-negative per-row weights, aligned with the factor's rows.
    """

    base: RobustKernel
    weights: np.ndarray

    def rho(self, s: np.ndarray) -> np.ndarray:
        """``(M,)`` -> ``(M,)``."""
        return self.weights * self.base.rho(s)

    def weight(self, s: np.ndarray) -> np.ndarray:
        """``(M,)`` -> ``(M,)`` IRLS weights ``W_m rho'(s_m)``."""
        return self.weights * self.base.weight(s)


def point_plane_residuals(
    X_w: np.ndarray, normals_w: np.ndarray, offsets: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed point-to-plane distances and their point Jacobians.

    Args:
        X_w: ``(M, 3)`` points.
        normals_w: ``(M, 3)`` unit plane normals.
        offsets: ``(M,)`` plane offsets ``c`` (plane ``n . x = c``).

    Returns:
        ``(d, J)``: ``d (M,)``, ``J (M, 3) = n``.
    """
    d = np.einsum("ma,ma->m", X_w, normals_w) - offsets
    return d, normals_w.copy()


class BuildingFactor:
    """Point-to-plane distances of building points with Geman-McClure and per-point weights.

    Args:
        points: ``(M,)`` state point index of each associated point.
        normals_w: ``(M, 3)`` normal of its facade plane (normalised here; the offset is rescaled
            accordingly).
        offsets: ``(M,)`` plane offsets ``c`` with the plane ``n . x = c``.
        weights: ``(M,)`` non-negative ``W_q`` (default 1).
        sigma: Geman-McClure scale in metres.
        kernel: override the kernel (default Geman-McClure with ``sigma``).
        name: family label.

    Raises:
        GeosegError: zero or non-finite normals, bad weights, non-positive sigma.
    """

    def __init__(
        self,
        points: np.ndarray,
        normals_w: np.ndarray,
        offsets: np.ndarray,
        weights: np.ndarray | None = None,
        *,
        sigma: float = 1.0,
        kernel: str | RobustKernel | None = None,
        name: str = "building",
    ) -> None:
        self.points = np.asarray(points, dtype=np.int64).reshape(-1)
        M = self.points.size
        n = np.asarray(normals_w, dtype=np.float64)
        c = np.asarray(offsets, dtype=np.float64).reshape(-1)
        check_shape("normals_w", n, (M, 3))
        check_shape("offsets", c, (M,))
        check_finite("normals_w", n)
        check_finite("offsets", c)
        norm = np.linalg.norm(n, axis=1)
        if np.any(norm < 1e-12):
            raise GeosegError("normals_w: contains a zero normal")
        self.normals_w = n / norm[:, None]
        self.offsets = c / norm
        w = np.ones(M) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
        check_shape("weights", w, (M,))
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise GeosegError("weights: expected finite non-negative point weights W_q")
        self.weights = w
        check_positive("sigma", sigma)
        base = GemanMcClureKernel(float(sigma)) if kernel is None else get_kernel(kernel)
        self.kernel = WeightedKernel(base, w)
        self.name = name

    def _check(self, state: BAState) -> None:
        if self.points.size and (self.points.max() >= state.num_points or self.points.min() < 0):
            raise SlamError(f"{self.name}: point index out of range for {state.num_points}")

    def evaluate(self, state: BAState) -> FactorBlock:
        """Rows ``(M, 1)``, ``a = 0``, one point each."""
        self._check(state)
        d, J = point_plane_residuals(state.X_w[self.points], self.normals_w, self.offsets)
        M = d.size
        return FactorBlock(
            residuals=d[:, None],
            cameras=np.zeros((M, 0), dtype=np.int64),
            J_cameras=np.zeros((M, 0, 1, 6)),
            points=self.points,
            J_points=J[:, None, :],
            kernel=self.kernel,
            name=self.name,
        )

    def cost(self, state: BAState) -> float:
        """``sum_q W_q rho(d_q^2)``."""
        self._check(state)
        d, _ = point_plane_residuals(state.X_w[self.points], self.normals_w, self.offsets)
        return float(np.sum(self.kernel.rho(d * d)))
