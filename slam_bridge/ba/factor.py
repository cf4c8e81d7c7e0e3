"""The factor protocol: what a residual family hands to the normal-equations assembler.

A **factor family** (reprojection, GPS, DEM, odometry, building, pose-graph DPC/MPC, ...) is any
object with ``evaluate(state) -> FactorBlock`` (all its whitened residuals and analytic
Jacobians, vectorised) and ``cost(state) -> float`` (see :class:`Factor`); optionally
``num_residuals`` and ``cost_and_invalid(state) -> (float, int)``. A :class:`FactorBlock` holds
``M`` residual rows of ``k`` values, each involving a fixed number of cameras (indices into all
cameras, Jacobians for the increment of :meth:`slam_bridge.ba.state.BAState.retract`) and at most
one point. The assembler drops fixed cameras and points, skips invalid rows (counted in
``n_invalid``) and applies the block's robust kernel (IRLS). The full contract:
``docs/solvers.md`` ("The factor protocol").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from slam_bridge.ba.robust import RobustKernel, TrivialKernel, get_kernel
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = ["FactorBlock", "Factor"]


@dataclass
class FactorBlock:
    """Whitened residuals of one factor family with their Jacobians.

    Attributes:
        residuals: ``(M, k)`` whitened residual rows.
        cameras: ``(M, a)`` int, indices into the state's cameras (``a`` may be 0).
        J_cameras: ``(M, a, k, 6)`` Jacobians wrt each row's cameras' ``[dw, dT]`` increments.
        points: ``(M,)`` int indices into the state's points, or ``None`` (no point involved).
        J_points: ``(M, k, 3)`` Jacobians wrt the point increments, or ``None``.
        kernel: robust kernel applied by the assembler (name or object; default trivial).
        valid: ``(M,)`` bool, rows that count; ``None`` means all rows.
        name: label used in logs and per-family cost reports.
    """

    residuals: np.ndarray
    cameras: np.ndarray
    J_cameras: np.ndarray
    points: np.ndarray | None = None
    J_points: np.ndarray | None = None
    kernel: RobustKernel | str | None = field(default_factory=TrivialKernel)
    valid: np.ndarray | None = None
    name: str = "factor"

    def __post_init__(self) -> None:
        self.kernel = get_kernel(self.kernel)
        r = np.asarray(self.residuals, dtype=np.float64)
        if r.ndim != 2:
            raise SlamError(f"{self.name}.residuals: expected (M, k), got {r.shape}")
        M, k = r.shape
        self.residuals = r
        cams = np.asarray(self.cameras, dtype=np.int64)
        if cams.ndim == 1:
            cams = cams[:, None]
        if cams.ndim != 2 or cams.shape[0] != M:
            raise SlamError(f"{self.name}.cameras: expected ({M}, a), got {cams.shape}")
        self.cameras = cams
        a = cams.shape[1]
        Jc = np.asarray(self.J_cameras, dtype=np.float64)
        if Jc.shape != (M, a, k, 6):
            raise SlamError(f"{self.name}.J_cameras: expected {(M, a, k, 6)}, got {Jc.shape}")
        self.J_cameras = Jc
        if (self.points is None) != (self.J_points is None):
            raise SlamError(f"{self.name}: points and J_points must both be given or both None")
        if self.points is not None:
            self.points = np.asarray(self.points, dtype=np.int64).reshape(-1)
            if self.points.shape != (M,):
                raise SlamError(f"{self.name}.points: expected ({M},), got {self.points.shape}")
            self.J_points = np.asarray(self.J_points, dtype=np.float64)
            if self.J_points.shape != (M, k, 3):
                raise SlamError(
                    f"{self.name}.J_points: expected {(M, k, 3)}, got {self.J_points.shape}"
                )
        if self.valid is not None:
            self.valid = np.asarray(self.valid, dtype=bool).reshape(-1)
            if self.valid.shape != (M,):
                raise SlamError(f"{self.name}.valid: expected ({M},), got {self.valid.shape}")

    @property
    def num_rows(self) -> int:
        """``M``."""
        return self.residuals.shape[0]

    @property
    def n_invalid(self) -> int:
        """Number of rows flagged invalid."""
        return 0 if self.valid is None else int(self.num_rows - np.count_nonzero(self.valid))

    def squared_norms(self) -> np.ndarray:
        """``(M,)`` ``s_m = ||r_m||^2`` (0 for invalid rows)."""
        s = np.einsum("mk,mk->m", self.residuals, self.residuals)
        return s if self.valid is None else np.where(self.valid, s, 0.0)

    def cost(self) -> float:
        """``sum_m rho(s_m)`` over valid rows."""
        s = self.squared_norms()
        rho = self.kernel.rho(s)
        if self.valid is not None:
            rho = np.where(self.valid, rho, 0.0)
        return float(np.sum(rho))


@runtime_checkable
class Factor(Protocol):
    """A residual family. See the module docstring for the exact contract."""

    def evaluate(self, state: BAState) -> FactorBlock:
        """Residual rows and Jacobians at ``state``."""
        ...

    def cost(self, state: BAState) -> float:
        """``sum_m rho(||r_m||^2)`` at ``state`` (no Jacobians needed)."""
        ...
