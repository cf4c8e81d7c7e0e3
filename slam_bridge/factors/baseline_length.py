"""Baseline length between two cameras: the scale that MPC's epipolar rows cannot see.

The epipolar residual of eq. 3.18 is blind to the length of each baseline, so without a length
term every link of an MPC pose graph, and the scale of the BA window behind it, is free: the
barrier then lets the GPS slide the reconstruction along those directions at no vision cost.
The hybrid window (:mod:`slam_bridge.slam.windows`) adds one row per pose-graph pair, with
``L_hat`` the pair's length when the link entered the pose graph. Not in the thesis.
"""

from __future__ import annotations

import numpy as np

from slam_bridge.ba.factor import FactorBlock
from slam_bridge.errors import SlamError

__all__ = ["BaselineLengthFactor"]


class BaselineLengthFactor:
    """Length of the baseline between two cameras (the scale MPC's epipolar rows cannot see).

    Row per pair ``(i, j)``: ``r = (||T_j - T_i|| - L_hat) / sigma`` (``k = 1``, ``a = 2``), with
    ``dr/dT_j = u^T / sigma``, ``dr/dT_i = -u^T / sigma``, ``u = (T_j - T_i) / ||T_j - T_i||``
    and no rotation dependence. It only fills the off-diagonal blocks of successive cameras,
    like the pose-graph terms (fig. 3.3).

    Args:
        pairs: ``(Q, 2)`` state camera indices.
        lengths: ``(Q,)`` reference lengths ``L_hat`` (metres).
        sigma: metres, scalar or ``(Q,)``.
        kernel: robust kernel of the rows (default least squares).
    """

    def __init__(
        self, pairs: np.ndarray, lengths: np.ndarray, sigma: float, *, kernel=None
    ) -> None:
        from slam_bridge.ba.robust import TrivialKernel, get_kernel

        self.kernel = get_kernel(kernel)
        self._trivial = isinstance(self.kernel, TrivialKernel)
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        self.lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
        if self.lengths.shape != (self.pairs.shape[0],):
            raise SlamError("lengths: expected one per pair")
        if not np.all(np.asarray(sigma) > 0):
            raise SlamError(f"sigma: expected > 0, got {sigma}")
        self.sigma = np.asarray(sigma, dtype=np.float64)
        self.name = "baseline_length"

    @classmethod
    def from_state(cls, state, pairs: np.ndarray, sigma: float) -> BaselineLengthFactor:
        """``L_hat`` = the lengths at ``state`` (the pre-fusion estimate)."""
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        d = state.t_wc[pairs[:, 1]] - state.t_wc[pairs[:, 0]]
        return cls(pairs, np.linalg.norm(d, axis=1), sigma)

    @property
    def num_residuals(self) -> int:
        """One per pair."""
        return self.pairs.shape[0]

    def _r(self, state) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = state.t_wc[self.pairs[:, 1]] - state.t_wc[self.pairs[:, 0]]
        n = np.linalg.norm(d, axis=1)
        return (n - self.lengths) / self.sigma, d, n

    def _rows(self, state) -> tuple[np.ndarray, np.ndarray]:
        """``r (Q,)`` and ``J (Q, 12)`` = ``[d/d(dw_i, dT_i) | d/d(dw_j, dT_j)]``."""
        r, d, n = self._r(state)
        u = d / (np.maximum(n, 1e-12) * self.sigma)[:, None]
        J = np.zeros((r.size, 12))
        J[:, 3:6] = -u
        J[:, 9:12] = u
        return r, J

    def evaluate(self, state):
        """Rows ``(Q, 1)``, ``a = 2``."""
        r, J = self._rows(state)
        return FactorBlock(
            r[:, None], self.pairs, J.reshape(-1, 2, 1, 6), kernel=self.kernel, name=self.name
        )

    def _normal_equations(self, state, cmap: np.ndarray, pmap: np.ndarray, Cf: int, Pf: int):
        """Compiled shortcut of :func:`slam_bridge.ba.normal_equations.assemble` (numba only): the
        per-pair products ``J^T J``, ``J^T r`` of the one-row pairs, scattered by
        :func:`slam_bridge.ba.normal_equations.pair_normal_equations` (the generic path's per-family
        overhead was ~0.2 ms per assembly for ~30 rows)."""
        from slam_bridge.ba.normal_equations import pair_normal_equations

        if type(self).evaluate is not BaselineLengthFactor.evaluate or not self._trivial:
            return None
        r, J = self._rows(state)
        H = J[:, :, None] * J[:, None, :]
        cost = float(np.sum(r * r))
        return pair_normal_equations(cost, 0, H, J * r[:, None], self.pairs, cmap, Cf, Pf)

    def cost(self, state) -> float:
        """``sum rho(r^2)``."""
        return float(np.sum(self.kernel.rho(self._r(state)[0] ** 2)))

    def cost_and_invalid(self, state) -> tuple[float, int]:
        """``(cost, 0)``."""
        return self.cost(state), 0
