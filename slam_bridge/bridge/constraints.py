"""Building constraints for the fusion: associated map points on their facade planes.

:class:`BuildingConstraints` is a constraint provider of :func:`slam_bridge.slam.fusion.fuse`
(the protocol :class:`~slam_bridge.slam.fusion.ConstraintProvider`): for the keyframe being
fused, every point of its window that the current :class:`~slam_bridge.bridge.association.
Association` gives a facade becomes one row of a :class:`~slam_bridge.factors.building.
BuildingFactor`, ``W_q rho(d_q^2)`` with ``d_q`` the point's distance to the facade's plane
(eq. 4.2, Geman-McClure of scale ``sigma_m``). A point-only row adds to the point's diagonal
block: no dense term beside the barrier's rank one (appendix B.4).

The association is replaced whenever a newer one is ready (:meth:`BuildingConstraints.update`,
an atomic swap of one reference: a worker thread may call it while the loop fuses); the fusion
uses the one current when it asks.
"""

from __future__ import annotations

import logging

import numpy as np

from geoseg.errors import check_positive
from slam_bridge.ba.factor import Factor
from slam_bridge.bridge.association import Association
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError
from slam_bridge.factors.building import BuildingFactor
from slam_bridge.slam.map import Map

logger = logging.getLogger(__name__)

__all__ = ["BuildingConstraints"]


class BuildingConstraints:
    """Facade-plane constraints on the associated points of the fused window.

    Args:
        facades: the building model the associations refer to.
        sigma_m: Geman-McClure scale, metres (a point farther from its plane than a few
            ``sigma_m`` pulls little: a wrong association or a model error).
        weight: multiplies every point's association weight.
        window_weight: the building rows of one fused window weigh together at most this much
            (their weights are scaled down to it; None: no cap). Hundreds of points on a model
            with errors would otherwise outvote the window's single GPS fix and pull the
            trajectory onto the model's errors.
        association: the first association (None: none yet).
    """

    name = "building"
    world_frame = True

    def __init__(
        self,
        facades: Facades,
        *,
        sigma_m: float = 0.5,
        weight: float = 1.0,
        window_weight: float | None = None,
        association: Association | None = None,
    ) -> None:
        check_positive("sigma_m", sigma_m)
        check_positive("weight", weight)
        if window_weight is not None:
            check_positive("window_weight", window_weight)
        self.window_weight = window_weight
        self.facades = facades
        self.sigma_m = float(sigma_m)
        self.weight = float(weight)
        self.association: Association | None = None
        if association is not None:
            self.update(association)

    def update(self, association: Association) -> None:
        """Make ``association`` the current one.

        Raises:
            SlamError: it refers to facades this model does not have, or has negative or
                non-finite weights.
        """
        f = np.asarray(association.facade)
        w = np.asarray(association.weight, dtype=np.float64)
        if f.shape != w.shape or f.ndim != 1:
            raise SlamError(f"association: facade {f.shape} and weight {w.shape} differ")
        if f.size and (f.max() >= len(self.facades) or f.min() < -1):
            raise SlamError(
                f"association: facade ids must lie in [-1, {len(self.facades)}), got "
                f"{int(f.min())}..{int(f.max())}"
            )
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise SlamError("association: weights must be finite and >= 0")
        self.association = association

    def window_points(self, problem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The window's points associated with a facade.

        Returns:
            ``(rows (P,), facade ids (P,), weights (P,))``: their rows in ``problem``'s points,
            their facades and association weights (all empty without an association).
        """
        a = self.association
        if a is None:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        ids = np.asarray(problem.point_ids)
        known = ids < a.facade.size  # points newer than the association have none yet
        facade = np.full(ids.size, -1, np.int64)
        facade[known] = a.facade[ids[known]]
        weight = np.zeros(ids.size)
        weight[known] = a.weight[ids[known]]
        rows = np.flatnonzero((facade >= 0) & (weight > 0))
        return rows, facade[rows], weight[rows]

    def factors(self, slam_map: Map, problem, k: int) -> list[Factor]:
        """One :class:`BuildingFactor` over the window's associated points (none when no point
        of the window is associated)."""
        rows, f, weight = self.window_points(problem)
        if rows.size == 0:
            return []
        w = self.weight * weight
        if self.window_weight is not None and w.sum() > self.window_weight:
            w *= self.window_weight / w.sum()
        logger.debug("keyframe %d: %d points on facades", k, rows.size)
        return [
            BuildingFactor(rows, self.facades.normal[f], self.facades.d[f], w, sigma=self.sigma_m)
        ]
