"""Odometry constraint: camera positions tied to a dead-reckoned position (appendix B.3.2).

The thesis (appendix B.3.2) describes the odometry constraint as "essentially the same as GPS":
the speed vector returned by the vehicle's odometer is integrated into a *new position in the
world frame*, and the camera position is constrained to it. We follow that reading: an absolute,
dead-reckoned position ``x_odo,i`` (see :func:`dead_reckon`, anchored at a trusted position such
as the fixed keyframe ``z_0`` before the window) and the unary residual::

    r_i = sqrt(w_i) (S T_i - x_odo,i)

with ``S`` selecting the horizontal ``(x, y)`` (default, like GPS) or all of ``(x, y, z)``. Its
Jacobian with respect to ``[dw, dT]`` is ``[0, sqrt(w_i) S]``: translation diagonal blocks
only, no dense term (appendix B.4).
"""

from __future__ import annotations

import logging

import numpy as np

from geoseg.errors import GeosegError, check_finite, check_shape
from slam_bridge.ba.robust import RobustKernel
from slam_bridge.factors.single_camera import SingleCameraFactor

logger = logging.getLogger(__name__)

__all__ = ["OdometryFactor", "dead_reckon", "odometry_residuals"]


def dead_reckon(
    t_start_w: np.ndarray,
    velocities_w: np.ndarray,
    dt: np.ndarray,
    *,
    heading_rad: np.ndarray | None = None,
) -> np.ndarray:
    """Integrate the odometer's speed vector into world positions (forward Euler).

    Args:
        t_start_w: ``(3,)`` (or ``(2,)``) starting position in the world frame.
        velocities_w: ``(M, 3)`` (or ``(M, 2)``) world-frame velocity between successive
            positions, metres per second; or ``(M,)`` scalar speeds when ``heading_rad`` is given.
        dt: ``(M,)`` time steps, seconds.
        heading_rad: ``(M,)`` optional headings (radians, counter-clockwise from x east) used with
            scalar speeds: velocity = speed * (cos, sin, 0).

    Returns:
        ``(M, D)`` positions after each step (the start itself is not included).

    Raises:
        GeosegError: non-finite inputs or mismatched shapes.
    """
    t_start_w = np.asarray(t_start_w, dtype=np.float64).reshape(-1)
    dt = np.asarray(dt, dtype=np.float64).reshape(-1)
    velocities_w = np.asarray(velocities_w, dtype=np.float64)
    if heading_rad is not None:
        heading_rad = np.asarray(heading_rad, dtype=np.float64).reshape(-1)
        speed = velocities_w.reshape(-1)
        check_shape("heading_rad", heading_rad, (speed.shape[0],))
        velocities_w = np.zeros((speed.shape[0], t_start_w.shape[0]))
        velocities_w[:, 0] = speed * np.cos(heading_rad)
        velocities_w[:, 1] = speed * np.sin(heading_rad)
    check_shape("velocities_w", velocities_w, (dt.shape[0], t_start_w.shape[0]))
    for name, arr in (("t_start_w", t_start_w), ("velocities_w", velocities_w), ("dt", dt)):
        check_finite(name, arr)
    if np.any(dt < 0):
        raise GeosegError("dt: expected non-negative time steps")
    return t_start_w[None, :] + np.cumsum(velocities_w * dt[:, None], axis=0)


def odometry_residuals(
    t_wc: np.ndarray, x_odo_w: np.ndarray, sqrt_weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Whitened odometry position residuals and their Jacobians.

    Args:
        t_wc: ``(M, 3)`` optical centres of the constrained cameras.
        x_odo_w: ``(M, D)`` dead-reckoned targets, ``D = 2`` (horizontal) or ``3``.
        sqrt_weights: ``(M,)`` square roots of the weights.

    Returns:
        ``(r, J)``: ``r (M, D)``; ``J (M, D, 6)`` with respect to ``[dw, dT]``.
    """
    D = x_odo_w.shape[1]
    r = sqrt_weights[:, None] * (t_wc[:, :D] - x_odo_w)
    J = np.zeros((t_wc.shape[0], D, 6))
    for k in range(D):
        J[:, k, 3 + k] = sqrt_weights
    return r, J


class OdometryFactor(SingleCameraFactor):
    """Camera positions tied to dead-reckoned odometry positions, one row per constrained camera.

    Args:
        cameras: ``(M,)`` state camera indices.
        x_odo_w: ``(M, 2)`` horizontal or ``(M, 3)`` full dead-reckoned positions
            (:func:`dead_reckon`).
        weights: ``(M,)`` non-negative weights (default 1).
        kernel: robust kernel (default least squares).
        name: family label.

    Raises:
        GeosegError: non-finite targets or bad weights.
    """

    def __init__(
        self,
        cameras: np.ndarray,
        x_odo_w: np.ndarray,
        weights: np.ndarray | None = None,
        *,
        kernel: str | RobustKernel | None = None,
        name: str = "odometry",
    ) -> None:
        cameras = np.asarray(cameras, dtype=np.int64).reshape(-1)
        M = cameras.size
        self.x_odo_w = np.asarray(x_odo_w, dtype=np.float64)
        if (
            self.x_odo_w.ndim != 2
            or self.x_odo_w.shape[0] != M
            or self.x_odo_w.shape[1]
            not in (
                2,
                3,
            )
        ):
            raise GeosegError(
                f"x_odo_w: expected shape ({M}, 2) or ({M}, 3), got {self.x_odo_w.shape}"
            )
        check_finite("x_odo_w", self.x_odo_w)
        super().__init__(cameras, weights, kernel=kernel, name=name, weight_label="odometry")

    def _residuals(self, t_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows ``(M, D)``: ``r_i = sqrt(w_i) (S T_i - x_odo,i)`` (:func:`odometry_residuals`)."""
        return odometry_residuals(t_wc, self.x_odo_w, self.sqrt_weights)
