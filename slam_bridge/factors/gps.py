"""GPS constraint on the horizontal position of cameras (thesis eq. 3.1, appendix B.3.1).

``C_gps = sum_i w_i ||P_gps T_i - x_gps,i||^2`` (eq. B.7) where ``T_i = t_wc[i]`` is the optical
centre of camera ``i`` in the world (x east, y north, z up, docs/architecture.md) and ``P_gps`` keeps ``(x,
y)``: the GPS altitude of low-cost receivers is ignored. (The thesis's ``B = diag(1, 0, 1)`` of
eq. B.10 selects the same horizontal plane in its y-up frame.) Chapter 3 constrains only the most
recent camera; the factor accepts any subset of cameras.

Residual of fix ``i``: ``r_i = sqrt(w_i) (T_i[:2] - x_gps,i)``, shape ``(2,)``; its Jacobian with
respect to the camera increment ``[dw, dT]`` is ``[0_(2x3), sqrt(w_i) P]`` (eq. B.11), so the
Gauss-Newton block ``2 J^T J`` (eq. B.12) touches only the translation diagonal block of that
camera: no dense term (appendix B.4).

Missing fixes (GPS dropouts): a fix given as NaN is *skipped* (its residual row is dropped and a
debug message logged) when ``skip_missing=True`` (default), or raises :class:`GPSFixError`
otherwise. Infinite fixes and NaN/negative weights always raise.
"""

from __future__ import annotations

import logging

import numpy as np

from geoseg.errors import check_shape
from slam_bridge.ba.robust import RobustKernel
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.factors.single_camera import SingleCameraFactor, check_weights

logger = logging.getLogger(__name__)

__all__ = ["GPSFixError", "GPSFactor", "gps_residuals", "clean_gps_fixes"]


class GPSFixError(SlamError):
    """A GPS fix that cannot be used: missing (NaN) when not allowed, infinite, or a bad weight."""


def clean_gps_fixes(
    cameras: np.ndarray,
    xy_gps: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    skip_missing: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate GPS fixes and drop the missing ones.

    Args:
        cameras: ``(M,)`` integer camera index of each fix.
        xy_gps: ``(M, 2)`` horizontal GPS positions in the world frame (metres); a row with a NaN
            is a missing fix.
        weights: ``(M,)`` non-negative weights ``w_i`` (default 1).
        skip_missing: drop missing fixes (True) or raise (False).

    Returns:
        ``(cameras (M',), xy_gps (M', 2), weights (M',))`` with the missing fixes removed.

    Raises:
        GPSFixError: infinite fixes, bad weights, or missing fixes with ``skip_missing=False``.
    """
    cameras = np.asarray(cameras, dtype=np.int64).reshape(-1)
    xy_gps = np.asarray(xy_gps, dtype=np.float64)
    if xy_gps.ndim == 1:
        xy_gps = xy_gps[None, :]
    check_shape("xy_gps", xy_gps, (cameras.shape[0], 2))
    weights = check_weights(weights, cameras.shape[0], "GPS", error=GPSFixError)
    if np.any(np.isinf(xy_gps)):
        raise GPSFixError("xy_gps: contains infinite values")
    missing = np.isnan(xy_gps).any(axis=1)
    if np.any(missing):
        if not skip_missing:
            raise GPSFixError(
                f"xy_gps: {int(missing.sum())} missing (NaN) GPS fix(es) for camera(s) "
                f"{cameras[missing].tolist()}; pass skip_missing=True to drop them"
            )
        logger.debug("skipping %d missing GPS fix(es)", int(missing.sum()))
    keep = ~missing
    return cameras[keep], xy_gps[keep], weights[keep]


def gps_residuals(
    t_wc: np.ndarray, xy_gps: np.ndarray, sqrt_weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Whitened horizontal GPS residuals and their Jacobians (eqs. B.7, B.11).

    Args:
        t_wc: ``(M, 3)`` optical centres of the constrained cameras (one row per fix).
        xy_gps: ``(M, 2)`` GPS fixes (finite).
        sqrt_weights: ``(M,)`` square roots of the fix weights.

    Returns:
        ``(r, J)``: ``r (M, 2)`` residuals ``sqrt(w) (T[:2] - x_gps)``; ``J (M, 2, 6)`` their
        derivatives with respect to the camera increment ``[dw, dT]``.
    """
    r = sqrt_weights[:, None] * (t_wc[:, :2] - xy_gps)
    J = np.zeros((t_wc.shape[0], 2, 6))
    J[:, 0, 3] = sqrt_weights
    J[:, 1, 4] = sqrt_weights
    return r, J


class GPSFactor(SingleCameraFactor):
    """GPS fixes on the horizontal positions of some cameras (eq. B.7), one row per fix.

    Args:
        cameras: ``(M,)`` state camera index of each fix (e.g. ``[C - 1]`` for the most recent
            camera, as in chapter 3: see :meth:`most_recent`).
        xy_gps: ``(M, 2)`` horizontal fixes in the world frame (metres); NaN rows = missing.
        weights: ``(M,)`` per-fix weights ``w_i`` (default 1; ``1 / sigma_gps^2`` for a
            statistical reading).
        skip_missing: drop missing (NaN) fixes (default) or raise :class:`GPSFixError`.
        kernel: robust kernel (default least squares, as eq. B.7).
        name: label of the family in cost reports.

    Raises:
        GPSFixError: see :func:`clean_gps_fixes`.
    """

    def __init__(
        self,
        cameras: np.ndarray,
        xy_gps: np.ndarray,
        weights: np.ndarray | None = None,
        *,
        skip_missing: bool = True,
        kernel: str | RobustKernel | None = None,
        name: str = "gps",
    ) -> None:
        cameras, self.xy_gps, w = clean_gps_fixes(
            cameras, xy_gps, weights, skip_missing=skip_missing
        )
        super().__init__(
            cameras, w, kernel=kernel, name=name, weight_label="GPS", error=GPSFixError
        )

    @classmethod
    def most_recent(
        cls, state: BAState, xy_gps: np.ndarray, weight: float = 1.0, **kwargs
    ) -> GPSFactor:
        """The chapter-3 constraint (eq. 3.1): one fix on the most recent free camera.

        Args:
            state: the problem; its last free camera (highest index) is constrained.
            xy_gps: ``(2,)`` the fix.
            weight: its weight.
            **kwargs: forwarded to the constructor.

        Raises:
            GPSFixError: no free camera.
        """
        free = state.free_cameras
        if free.size == 0:
            raise GPSFixError("GPSFactor.most_recent: the state has no free camera")
        xy = np.asarray(xy_gps, dtype=np.float64).reshape(1, 2)
        return cls(np.array([free[-1]]), xy, np.array([weight]), **kwargs)

    def _residuals(self, t_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows ``(M, 2)``: ``r_i = sqrt(w_i) (T_i[:2] - x_gps,i)`` (:func:`gps_residuals`)."""
        return gps_residuals(t_wc, self.xy_gps, self.sqrt_weights)
