"""The bundle-adjustment state: cameras, points, fixed masks and the retraction.

:class:`BAState` holds ``C`` cameras named by frame (``R_wc (C, 3, 3)``, ``t_wc (C, 3)`` =
optical centre ``T_i``; ``X_w = R_wc X_c + t_wc``, eq. 1.3), ``P`` points ``X_w (P, 3)`` and
masks of fixed cameras/points (the gauge and the k-BA's fixed older cameras). Free
cameras/points are numbered in increasing state order (``free_cameras``, ``free_points``); the
free count is ``Cf``/``Pf``.

**Increments** (:meth:`BAState.retract`): camera ``[dw (3), dT (3)]`` applied as
``R_wc <- exp(hat(dw)) R_wc`` (left perturbation, thesis eq. 1.56) and ``t_wc <- t_wc + dT``;
points additive.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from geoseg.errors import check_finite, check_shape
from slam_bridge.ba.compiled import _njit, numba_enabled
from slam_bridge.geometry.lie import so3_exp

__all__ = ["BAState"]


@dataclass
class BAState:
    """Cameras and points of a bundle-adjustment problem.

    Attributes:
        R_wc: ``(C, 3, 3)`` camera-to-world rotations.
        t_wc: ``(C, 3)`` optical centres in the world frame.
        X_w: ``(P, 3)`` points in the world frame.
        camera_fixed: ``(C,)`` bool, cameras held constant (gauge / older k-BA cameras).
        point_fixed: ``(P,)`` bool, points held constant.
    """

    R_wc: np.ndarray
    t_wc: np.ndarray
    X_w: np.ndarray
    camera_fixed: np.ndarray | None = None
    point_fixed: np.ndarray | None = None
    _cam_map: np.ndarray = field(init=False, repr=False)
    _pt_map: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.R_wc = np.asarray(self.R_wc, dtype=np.float64)
        self.t_wc = np.asarray(self.t_wc, dtype=np.float64)
        self.X_w = np.asarray(self.X_w, dtype=np.float64)
        check_shape("R_wc", self.R_wc, (None, 3, 3))
        C = self.R_wc.shape[0]
        check_shape("t_wc", self.t_wc, (C, 3))
        check_shape("X_w", self.X_w, (None, 3))
        P = self.X_w.shape[0]
        for name, v in (("R_wc", self.R_wc), ("t_wc", self.t_wc), ("X_w", self.X_w)):
            check_finite(name, v)
        if self.camera_fixed is None:
            self.camera_fixed = np.zeros(C, dtype=bool)
        if self.point_fixed is None:
            self.point_fixed = np.zeros(P, dtype=bool)
        self.camera_fixed = np.asarray(self.camera_fixed, dtype=bool).copy()
        self.point_fixed = np.asarray(self.point_fixed, dtype=bool).copy()
        check_shape("camera_fixed", self.camera_fixed, (C,))
        check_shape("point_fixed", self.point_fixed, (P,))
        self._cam_map = _index_map(self.camera_fixed)
        self._pt_map = _index_map(self.point_fixed)

    # ----------------------------------------------------------------------------- bookkeeping
    @property
    def num_cameras(self) -> int:
        """``C``."""
        return self.R_wc.shape[0]

    @property
    def num_points(self) -> int:
        """``P``."""
        return self.X_w.shape[0]

    @property
    def free_cameras(self) -> np.ndarray:
        """``(Cf,)`` state indices of the free cameras, increasing."""
        return np.flatnonzero(~self.camera_fixed)

    @property
    def free_points(self) -> np.ndarray:
        """``(Pf,)`` state indices of the free points, increasing."""
        return np.flatnonzero(~self.point_fixed)

    @property
    def camera_index_map(self) -> np.ndarray:
        """``(C,)`` int: free index of each camera, ``-1`` if fixed (follows in-place mask edits)."""
        if self._cam_map.size != self.camera_fixed.size or np.any(
            (self._cam_map < 0) != self.camera_fixed
        ):
            self._cam_map = _index_map(self.camera_fixed)
        return self._cam_map

    @property
    def point_index_map(self) -> np.ndarray:
        """``(P,)`` int: free index of each point, ``-1`` if fixed (follows in-place mask edits)."""
        if self._pt_map.size != self.point_fixed.size or np.any(
            (self._pt_map < 0) != self.point_fixed
        ):
            self._pt_map = _index_map(self.point_fixed)
        return self._pt_map

    def copy(self) -> BAState:
        """Deep copy."""
        return BAState(
            self.R_wc.copy(),
            self.t_wc.copy(),
            self.X_w.copy(),
            self.camera_fixed.copy(),
            self.point_fixed.copy(),
        )

    def retract(self, delta_cameras: np.ndarray, delta_points: np.ndarray) -> BAState:
        """Apply increments to the free parameters and return a new state.

        Args:
            delta_cameras: ``(Cf, 6)`` ``[dw, dT]`` per free camera:
                ``R_wc <- exp(hat(dw)) R_wc``, ``t_wc <- t_wc + dT``.
            delta_points: ``(Pf, 3)`` additive point increments.

        Returns:
            A new :class:`BAState` (masks shared by value).
        """
        fc, fp = self.free_cameras, self.free_points
        dc = np.asarray(delta_cameras, dtype=np.float64)
        dp = np.asarray(delta_points, dtype=np.float64)
        check_shape("delta_cameras", dc, (fc.size, 6))
        check_shape("delta_points", dp, (fp.size, 3))
        check_finite("delta_cameras", dc)
        check_finite("delta_points", dp)
        R_wc, t_wc = self.R_wc.copy(), self.t_wc.copy()
        if numba_enabled():  # one pass instead of so3_exp's series/branch arrays (~40 us)
            _rotate_kernel(np.ascontiguousarray(dc), fc, R_wc, t_wc)
        elif fc.size:
            R_wc[fc] = so3_exp(dc[:, :3]) @ self.R_wc[fc]
            t_wc[fc] += dc[:, 3:]
        if fp.size == self.X_w.shape[0]:  # every point free (a window's usual case)
            X_w = self.X_w + dp
        else:
            X_w = self.X_w.copy()
            X_w[fp] += dp
        for name, v in (("R_wc", R_wc), ("t_wc", t_wc), ("X_w", X_w)):
            check_finite(name, v)  # finite + finite can still overflow
        # the shapes and masks are this state's: skip the constructor's checks (a trial state
        # per solver step, where they cost as much as the update)
        new = object.__new__(BAState)
        new.R_wc, new.t_wc, new.X_w = R_wc, t_wc, X_w
        new.camera_fixed = self.camera_fixed.copy()
        new.point_fixed = self.point_fixed.copy()
        new._cam_map = self.camera_index_map.copy()
        new._pt_map = self.point_index_map.copy()
        return new


@_njit
def _rotate_kernel(dc, fc, R, t):  # pragma: no cover - compiled
    """In place, per free camera ``k`` (state index ``fc[k]``): ``R <- exp(hat(dw)) R`` and
    ``t <- t + dT`` with ``[dw, dT] = dc[k]``; Rodrigues' formula with the small-angle series of
    :func:`slam_bridge.geometry.lie.so3_exp` below 0.1 rad."""
    for k in range(fc.shape[0]):
        c = fc[k]
        w0, w1, w2 = dc[k, 0], dc[k, 1], dc[k, 2]
        t2 = w0 * w0 + w1 * w1 + w2 * w2
        if t2 < 0.01:
            a = 1.0 + t2 * (-1 / 6 + t2 * (1 / 120 + t2 * (-1 / 5040 + t2 / 362880)))
            b = 0.5 + t2 * (-1 / 24 + t2 * (1 / 720 + t2 * (-1 / 40320 + t2 / 3628800)))
        else:
            th = np.sqrt(t2)
            a = np.sin(th) / th
            b = (1.0 - np.cos(th)) / t2
        # E = I + a W + b W^2, W = hat(w), W^2 = w w^T - t2 I
        e00 = 1.0 + b * (w0 * w0 - t2)
        e11 = 1.0 + b * (w1 * w1 - t2)
        e22 = 1.0 + b * (w2 * w2 - t2)
        e01 = -a * w2 + b * w0 * w1
        e10 = a * w2 + b * w0 * w1
        e02 = a * w1 + b * w0 * w2
        e20 = -a * w1 + b * w0 * w2
        e12 = -a * w0 + b * w1 * w2
        e21 = a * w0 + b * w1 * w2
        for j in range(3):
            r0, r1, r2 = R[c, 0, j], R[c, 1, j], R[c, 2, j]
            R[c, 0, j] = e00 * r0 + e01 * r1 + e02 * r2
            R[c, 1, j] = e10 * r0 + e11 * r1 + e12 * r2
            R[c, 2, j] = e20 * r0 + e21 * r1 + e22 * r2
        t[c, 0] += dc[k, 3]
        t[c, 1] += dc[k, 4]
        t[c, 2] += dc[k, 5]


def _index_map(fixed: np.ndarray) -> np.ndarray:
    m = np.full(fixed.shape[0], -1, dtype=np.int64)
    free = np.flatnonzero(~fixed)
    m[free] = np.arange(free.size)
    return m
