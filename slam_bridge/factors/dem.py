"""Terrain-elevation constraint: camera altitude = road altitude + camera height (appendix B.3.2).

For camera ``i`` with optical centre ``T_i = t_wc[i]`` (z up), the residual is::

    r_i = sqrt(w_i) (T_i,z - h(T_i,xy) - h_cam)

where ``h`` is the road altitude given by the digital elevation model under the camera and
``h_cam`` the height of the camera above the road. Its Jacobian with respect to ``[dw, dT]`` is
``sqrt(w_i) [0, 0, 0, -dh/dx, -dh/dy, 1]``: one translation diagonal block per camera, no dense
term (appendix B.4).

The DEM is any object with the :class:`TerrainModel` protocol (``altitude_at(xy (N, 2)) -> (N,)``
and ``gradient_at(xy (N, 2)) -> (N, 2)``). :class:`DemSegments` implements it for the thesis's
road DEM: 2D segments with an altitude at each end; the altitude under a point is linearly
interpolated along the *nearest* segment (the point projected onto it, clamped to its ends). The
gradient is the slope along that segment (zero beyond its ends); where the nearest segment
changes the altitude may jump, which the Gauss-Newton steps tolerate because the camera moves by
centimetres between iterations.
"""

from __future__ import annotations

import logging
from typing import Protocol

import numpy as np

from geoseg.errors import GeosegError, check_finite, check_shape
from slam_bridge.ba.robust import RobustKernel
from slam_bridge.factors.single_camera import SingleCameraFactor

logger = logging.getLogger(__name__)

__all__ = ["DEMFactor", "DemSegments", "TerrainModel", "dem_residuals"]


class TerrainModel(Protocol):
    """What the elevation constraint needs from a DEM."""

    def altitude_at(self, xy: np.ndarray) -> np.ndarray:
        """Road altitude ``(N,)`` under the horizontal positions ``xy (N, 2)``."""
        ...

    def gradient_at(self, xy: np.ndarray) -> np.ndarray:
        """Horizontal gradient ``(N, 2)`` of :meth:`altitude_at` at ``xy (N, 2)``."""
        ...


class DemSegments:
    """A road DEM made of 2D segments with an altitude at each end.

    Args:
        xy_start: ``(S, 2)`` first end of each segment (world x, y, metres).
        xy_end: ``(S, 2)`` second end of each segment.
        z_start: ``(S,)`` altitude at ``xy_start``.
        z_end: ``(S,)`` altitude at ``xy_end``.

    Raises:
        GeosegError: no segment, mismatched shapes, non-finite values.
    """

    def __init__(
        self, xy_start: np.ndarray, xy_end: np.ndarray, z_start: np.ndarray, z_end: np.ndarray
    ) -> None:
        self.xy_start = np.asarray(xy_start, dtype=np.float64)
        self.xy_end = np.asarray(xy_end, dtype=np.float64)
        self.z_start = np.asarray(z_start, dtype=np.float64).reshape(-1)
        self.z_end = np.asarray(z_end, dtype=np.float64).reshape(-1)
        S = self.z_start.shape[0]
        if S == 0:
            raise GeosegError("DemSegments: expected at least one segment, got 0")
        check_shape("xy_start", self.xy_start, (S, 2))
        check_shape("xy_end", self.xy_end, (S, 2))
        check_shape("z_end", self.z_end, (S,))
        for name in ("xy_start", "xy_end", "z_start", "z_end"):
            check_finite(name, getattr(self, name))
        self._d = self.xy_end - self.xy_start  # (S, 2)
        self._len2 = np.maximum(np.einsum("sa,sa->s", self._d, self._d), 1e-24)

    @classmethod
    def from_model(cls, model: object) -> DemSegments:
        """Adapt any DEM object with ``p0``, ``p1`` ``(S, 2)`` and ``z0``, ``z1`` ``(S,)``
        attributes (e.g. :class:`geoseg.synth.dem.DemModel`, whose ``altitude_at`` agrees with
        :meth:`altitude_at`)."""
        try:
            return cls(model.p0, model.p1, model.z0, model.z1)  # type: ignore[attr-defined]
        except AttributeError as exc:
            raise GeosegError(
                f"model: expected p0, p1, z0, z1 segment arrays, got {type(model).__name__}"
            ) from exc

    def _nearest(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest segment ``(N,)``, raw parameter ``s (N,)`` and clamped parameter ``(N,)``."""
        rel = xy[:, None, :] - self.xy_start[None, :, :]  # (N, S, 2)
        s = np.einsum("nsa,sa->ns", rel, self._d) / self._len2[None, :]
        sc = np.clip(s, 0.0, 1.0)
        foot = self.xy_start[None] + sc[..., None] * self._d[None]
        dist2 = np.sum((xy[:, None, :] - foot) ** 2, axis=-1)
        k = np.argmin(dist2, axis=1)
        rows = np.arange(xy.shape[0])
        return k, s[rows, k], sc[rows, k]

    def distance_at(self, xy: np.ndarray) -> np.ndarray:
        """Horizontal distance ``(N,)`` from ``xy (N, 2)`` to the nearest segment."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        k, _, sc = self._nearest(xy)
        foot = self.xy_start[k] + sc[:, None] * self._d[k]
        return np.linalg.norm(xy - foot, axis=1)

    def altitude_at(self, xy: np.ndarray) -> np.ndarray:
        """Road altitude ``(N,)`` under ``xy (N, 2)``."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        k, _, sc = self._nearest(xy)
        return self.z_start[k] + sc * (self.z_end[k] - self.z_start[k])

    def gradient_at(self, xy: np.ndarray) -> np.ndarray:
        """Gradient ``(N, 2)`` of :meth:`altitude_at` (slope along the nearest segment)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        k, s, _ = self._nearest(xy)
        inside = (s > 0.0) & (s < 1.0)
        dz = (self.z_end[k] - self.z_start[k]) / self._len2[k]
        return np.where(inside[:, None], dz[:, None] * self._d[k], 0.0)


def dem_residuals(
    t_wc: np.ndarray,
    terrain: TerrainModel,
    camera_height: np.ndarray,
    sqrt_weights: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Whitened elevation residuals and their Jacobians.

    Args:
        t_wc: ``(M, 3)`` optical centres of the constrained cameras.
        terrain: the DEM (:class:`TerrainModel`).
        camera_height: ``(M,)`` camera height above the road, metres.
        sqrt_weights: ``(M,)`` square roots of the weights.

    Returns:
        ``(r, J)``: ``r (M, 1)``; ``J (M, 1, 6)`` with respect to ``[dw, dT]``.

    Raises:
        GeosegError: the DEM returned non-finite altitudes or gradients.
    """
    xy = t_wc[:, :2]
    h = np.asarray(terrain.altitude_at(xy), dtype=np.float64).reshape(-1)
    grad = np.asarray(terrain.gradient_at(xy), dtype=np.float64).reshape(-1, 2)
    if not (np.all(np.isfinite(h)) and np.all(np.isfinite(grad))):
        raise GeosegError("terrain: the DEM returned non-finite altitudes or gradients")
    r = (sqrt_weights * (t_wc[:, 2] - h - camera_height))[:, None]
    J = np.zeros((t_wc.shape[0], 1, 6))
    J[:, 0, 3] = -sqrt_weights * grad[:, 0]
    J[:, 0, 4] = -sqrt_weights * grad[:, 1]
    J[:, 0, 5] = sqrt_weights
    return r, J


class DEMFactor(SingleCameraFactor):
    """Terrain-elevation constraint on some cameras, one scalar row per camera.

    Args:
        cameras: ``(M,)`` state camera indices.
        terrain: the DEM (:class:`TerrainModel`, e.g. :class:`DemSegments`).
        camera_height: camera height above the road (metres), scalar or ``(M,)``.
        weights: ``(M,)`` non-negative weights (default 1).
        kernel: robust kernel (default least squares).
        name: family label.
    """

    def __init__(
        self,
        cameras: np.ndarray,
        terrain: TerrainModel,
        camera_height: float | np.ndarray,
        weights: np.ndarray | None = None,
        *,
        kernel: str | RobustKernel | None = None,
        name: str = "dem",
    ) -> None:
        cameras = np.asarray(cameras, dtype=np.int64).reshape(-1)
        M = cameras.size
        if not (hasattr(terrain, "altitude_at") and hasattr(terrain, "gradient_at")):
            raise GeosegError("terrain: expected an object with altitude_at and gradient_at")
        self.terrain = terrain
        self.camera_height = np.broadcast_to(
            np.asarray(camera_height, dtype=np.float64), (M,)
        ).copy()
        check_finite("camera_height", self.camera_height)
        super().__init__(cameras, weights, kernel=kernel, name=name, weight_label="DEM")

    def _residuals(self, t_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows ``(M, 1)``: ``sqrt(w_i) (T_i,z - h(T_i,xy) - h_cam)`` (:func:`dem_residuals`)."""
        return dem_residuals(t_wc, self.terrain, self.camera_height, self.sqrt_weights)
