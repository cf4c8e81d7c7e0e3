"""Pinhole camera: projection, its analytic Jacobians, and the local k-BA window.

Conventions (thesis eqs. 1.3 and 1.24, OpenCV camera frame: x right, y down, z forward):

* camera ``i`` is ``(R_wc, t_wc)`` with ``X_w = R_wc X_c + t_wc`` (``t_wc`` = optical centre);
* projection ``uv = pi(K R_wc^T (X_w - t_wc))``, ``pi(x, y, z) = (x / z, y / z)``;
* a point is *in front* when ``z_c > eps`` (default ``1e-6`` in the camera's length unit);
  points that are not in front are flagged by the ``in_front`` mask and their ``uv`` and
  Jacobians are set to NaN/0 **without** dividing by a tiny or negative depth;
* camera increment ``[dw, dT]``: ``R_wc <- exp(hat(dw)) R_wc``, ``t_wc <- t_wc + dT``, so with
  ``X_c = R_wc^T (X_w - t_wc)``::

      dX_c/ddw = R_wc^T hat(X_w - t_wc),   dX_c/ddT = -R_wc^T,   dX_c/dX_w = R_wc^T
      duv/dX_c = (K[:2, :] - uv e_3^T) / z_c

  (``K`` upper triangular with last row ``(0, 0, 1)``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from geoseg.errors import check_finite, check_shape
from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = [
    "PinholeCamera",
    "project",
    "project_with_jacobians",
    "LocalWindow",
    "local_window",
]

DEFAULT_EPS = 1e-6


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape[-2:] != (3, 3) or K.ndim not in (2, 3):
        raise SlamError(f"K: expected shape (3, 3) or (N, 3, 3), got {K.shape}")
    check_finite("K", K)
    if not np.allclose(K[..., 2, :], [0.0, 0.0, 1.0]) or np.any(K[..., 1, 0] != 0):
        raise SlamError("K: expected an upper-triangular calibration with last row (0, 0, 1)")
    return K


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera with fixed intrinsics.

    Attributes:
        K: ``(3, 3)`` calibration ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (pixels).
        width: image width in pixels (0 if unknown).
        height: image height in pixels (0 if unknown).
    """

    K: np.ndarray
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        K = _check_K(self.K)
        if K.ndim != 2:
            raise SlamError(f"K: expected shape (3, 3), got {K.shape}")
        object.__setattr__(self, "K", K)

    @classmethod
    def from_focal(
        cls, f: float, cx: float, cy: float, width: int = 0, height: int = 0
    ) -> PinholeCamera:
        """Square pixels, no skew."""
        return cls(np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]), width, height)

    def project(
        self, R_wc: np.ndarray, t_wc: np.ndarray, X_w: np.ndarray, eps: float = DEFAULT_EPS
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """See :func:`project`."""
        return project(self.K, R_wc, t_wc, X_w, eps)

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """``(N, 2)`` -> ``(N,)`` bool, inside ``[0, width) x [0, height)`` (NaN -> False)."""
        uv = np.asarray(uv, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return (
                (uv[:, 0] >= 0)
                & (uv[:, 0] < self.width)
                & (uv[:, 1] >= 0)
                & (uv[:, 1] < self.height)
            )


def _camera_coords(
    R_wc: np.ndarray, t_wc: np.ndarray, X_w: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``R (N, 3, 3)``, ``d = X_w - t_wc (N, 3)``, ``X_c = R^T d (N, 3)``."""
    R_wc = np.asarray(R_wc, dtype=np.float64)
    t_wc = np.asarray(t_wc, dtype=np.float64)
    X_w = np.asarray(X_w, dtype=np.float64)
    check_shape("X_w", X_w, (None, 3))
    N = X_w.shape[0]
    if R_wc.shape == (3, 3):
        R_wc = np.broadcast_to(R_wc, (N, 3, 3))
    if t_wc.shape == (3,):
        t_wc = np.broadcast_to(t_wc, (N, 3))
    check_shape("R_wc", R_wc, (N, 3, 3))
    check_shape("t_wc", t_wc, (N, 3))
    d = X_w - t_wc
    # X_c = R^T d, written as a sum of the rows of R (elementwise: faster than tiny matmuls)
    X_c = R_wc[:, 0, :] * d[:, 0:1] + R_wc[:, 1, :] * d[:, 1:2] + R_wc[:, 2, :] * d[:, 2:3]
    return R_wc, d, X_c


def _intrinsics(K: np.ndarray) -> tuple:
    """``fx, s, cx, fy, cy``: scalars for a shared ``(3, 3)`` K, ``(N,)`` arrays otherwise."""
    return K[..., 0, 0], K[..., 0, 1], K[..., 0, 2], K[..., 1, 1], K[..., 1, 2]


def _pixels(
    K: np.ndarray, X_c: np.ndarray, eps: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels ``(N, 2)`` (NaN where not in front), ``z``, ``in_front``, ``1/z`` (0 where not in
    front) and the normalised coordinates ``x, y`` (0 where not in front)."""
    z = X_c[:, 2]
    in_front = z > eps
    inv_z = np.where(in_front, 1.0 / np.where(in_front, z, 1.0), 0.0)
    x = X_c[:, 0] * inv_z
    y = X_c[:, 1] * inv_z
    fx, s, cx, fy, cy = _intrinsics(K)
    uv = np.empty((X_c.shape[0], 2))
    uv[:, 0] = fx * x + s * y + cx
    uv[:, 1] = fy * y + cy
    uv[~in_front] = np.nan
    return uv, z, in_front, inv_z, x, y


def project(
    K: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    eps: float = DEFAULT_EPS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points (eq. 1.24).

    Args:
        K: ``(3, 3)`` or ``(N, 3, 3)`` calibration.
        R_wc: ``(3, 3)`` or ``(N, 3, 3)`` camera-to-world rotations.
        t_wc: ``(3,)`` or ``(N, 3)`` optical centres.
        X_w: ``(N, 3)`` world points.
        eps: minimal depth for a point to count as in front.

    Returns:
        ``uv (N, 2)`` pixels (NaN where not in front), ``z (N,)`` depths in the camera frame,
        ``in_front (N,)`` bool ``z > eps``.
    """
    K = _check_K(K)
    _, _, X_c = _camera_coords(R_wc, t_wc, X_w)
    return _pixels(K, X_c, eps)[:3]


def project_with_jacobians(
    K: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    eps: float = DEFAULT_EPS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Projection and its analytic Jacobians (module docstring for the formulas).

    Args:
        K: ``(3, 3)`` or ``(N, 3, 3)``.
        R_wc: ``(3, 3)`` or ``(N, 3, 3)``.
        t_wc: ``(3,)`` or ``(N, 3)``.
        X_w: ``(N, 3)``.
        eps: minimal depth.

    Returns:
        ``uv (N, 2)``, ``z (N,)``, ``in_front (N,)``, ``J_cam (N, 2, 6)`` wrt ``[dw, dT]``,
        ``J_pt (N, 2, 3)`` wrt ``X_w``; Jacobians are 0 where not in front.
    """
    K = _check_K(K)
    R, d, X_c = _camera_coords(R_wc, t_wc, X_w)
    uv, z, in_front, inv_z, x, y = _pixels(K, X_c, eps)
    fx, s, _, fy, _ = _intrinsics(K)
    N = X_c.shape[0]
    # J_pt = A R^T with A = duv/dX_c = [[fx, s, -(fx x + s y)], [0, fy, -fy y]] / z; the rows of
    # R^T are the columns of R, so each row of J_pt is a combination of R's columns.
    c0, c1, c2 = R[:, :, 0], R[:, :, 1], R[:, :, 2]
    J_pt = np.empty((N, 2, 3))
    J_pt[:, 0] = c0 * (fx * inv_z)[:, None] + c2 * (-(fx * x + s * y) * inv_z)[:, None]
    if np.any(s != 0):
        J_pt[:, 0] += c1 * (s * inv_z)[:, None]
    J_pt[:, 1] = c1 * (fy * inv_z)[:, None] + c2 * (-fy * y * inv_z)[:, None]
    # duv/ddw = J_pt hat(d): row a of J_pt times hat(d) is cross(J_pt[a], d)
    J_cam = np.empty((N, 2, 6))
    a0, a1, a2 = J_pt[:, :, 0], J_pt[:, :, 1], J_pt[:, :, 2]
    d0, d1, d2 = d[:, None, 0], d[:, None, 1], d[:, None, 2]
    J_cam[:, :, 0] = a1 * d2 - a2 * d1
    J_cam[:, :, 1] = a2 * d0 - a0 * d2
    J_cam[:, :, 2] = a0 * d1 - a1 * d0
    np.negative(J_pt, out=J_cam[:, :, 3:])
    return uv, z, in_front, J_cam, J_pt


@dataclass
class LocalWindow:
    """The cameras, points and observations of one local k-BA.

    Attributes:
        free_cameras: ``(l,)`` int, the ``l`` most recent keyframes (optimised).
        fixed_cameras: ``(F,)`` int, older keyframes observing the window's points (held fixed:
            they fix the gauge).
        points: ``(P,)`` int, points observed by at least one free camera.
        observations: ``(M,)`` int, indices of the input observations that belong to the window
            (camera in free or fixed, point in ``points``).
    """

    free_cameras: np.ndarray
    fixed_cameras: np.ndarray
    points: np.ndarray
    observations: np.ndarray


def local_window(
    keyframes: np.ndarray, obs_cameras: np.ndarray, obs_points: np.ndarray, l: int
) -> LocalWindow:
    """Choose the local k-BA window (thesis §1.3.4: the ``l`` latest keyframes free, older
    cameras that see their points fixed).

    Args:
        keyframes: ``(K,)`` camera ids in time order (oldest first).
        obs_cameras: ``(M,)`` camera id of each observation.
        obs_points: ``(M,)`` point id of each observation.
        l: number of free keyframes (``>= 1``).

    Returns:
        A :class:`LocalWindow` (ids, not positions; sorted in time order for cameras).
    """
    keyframes = np.asarray(keyframes, dtype=np.int64).reshape(-1)
    obs_cameras = np.asarray(obs_cameras, dtype=np.int64).reshape(-1)
    obs_points = np.asarray(obs_points, dtype=np.int64).reshape(-1)
    if obs_cameras.shape != obs_points.shape:
        raise SlamError(
            f"obs_points: expected shape {obs_cameras.shape} like obs_cameras, got {obs_points.shape}"
        )
    if keyframes.size == 0:
        raise SlamError("keyframes: empty window")
    if l < 1:
        raise SlamError(f"l: expected >= 1 free keyframes, got {l}")
    free = keyframes[-l:]
    in_free = np.isin(obs_cameras, free)
    points = np.unique(obs_points[in_free])
    sees = np.isin(obs_points, points)
    older = keyframes[: max(keyframes.size - l, 0)]
    fixed_mask = sees & np.isin(obs_cameras, older)
    fixed_ids = np.unique(obs_cameras[fixed_mask])
    order = {int(c): i for i, c in enumerate(keyframes)}
    fixed = np.array(sorted(fixed_ids.tolist(), key=lambda c: order[c]), dtype=np.int64)
    observations = np.flatnonzero(sees & (in_free | fixed_mask))
    return LocalWindow(free.copy(), fixed, points, observations)
