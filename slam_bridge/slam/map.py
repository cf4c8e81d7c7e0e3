"""The map that the SLAM stages read and write: keyframes, points, observations, attributes.

One :class:`Map` holds the whole state of a run:

* **keyframes** ``0..C-1`` in arrival order: timestamp, current pose (``R_wc``, ``t_wc``,
  camera-to-world, ``X_w = R_wc X_c + t_wc``), the pose right after the keyframe's own fusion
  (``*_online``: what an online system knew then), a *segment* id (a run restarts a segment
  when it re-initialises after losing its tracking; keyframes of different segments share no
  observation) and world down as measured in the keyframe's image (``down_c``, NaN if not);
* **points** ``0..P-1``, addressed by the ids the observation source gives them: position
  (NaN until triangulated), a triangulated flag, and named per-point attributes that later
  stages attach (labels, normals, weights of the network bridge) without touching the loop;
* **observations** ``0..M-1``, appended one keyframe at a time (so sorted by keyframe): keyframe,
  point, pixel ``uv`` and an *active* flag (False once rejected as an outlier).

Arrays grow by doubling; the properties return views of the used part, valid until the next
:meth:`Map.add_keyframe` (stages re-read them after each keyframe). The map stores no ground
truth: evaluation compares its poses with the truth outside the loop.
"""

from __future__ import annotations

import numpy as np

from geoseg.errors import check_finite, check_shape
from slam_bridge.errors import SlamError

__all__ = ["Map"]


class _Column:
    """A growable array: ``view()`` is the first ``n`` rows of a buffer grown by doubling."""

    def __init__(self, tail: tuple[int, ...], dtype, fill) -> None:
        self._fill = fill
        self._buf = np.full((16, *tail), fill, dtype=dtype)
        self.n = 0

    def resize(self, n: int) -> None:
        if n > self._buf.shape[0]:
            cap = max(n, 2 * self._buf.shape[0])
            buf = np.full((cap, *self._buf.shape[1:]), self._fill, dtype=self._buf.dtype)
            buf[: self.n] = self._buf[: self.n]
            self._buf = buf
        self.n = n

    def view(self) -> np.ndarray:
        return self._buf[: self.n]


class Map:
    """Keyframes, points and observations of one SLAM run (module docstring).

    Args:
        K: ``(3, 3)`` camera intrinsics.
        image_size: ``(W, H)`` pixels.
    """

    def __init__(self, K: np.ndarray, image_size: tuple[int, int]) -> None:
        K = np.asarray(K, dtype=np.float64)
        check_shape("K", K, (3, 3))
        check_finite("K", K)
        self.K = K
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self._timestamps = _Column((), np.float64, np.nan)
        self._segment = _Column((), np.int64, 0)
        self._R = _Column((3, 3), np.float64, 0.0)
        self._t = _Column((3,), np.float64, 0.0)
        self._R_on = _Column((3, 3), np.float64, 0.0)
        self._t_on = _Column((3,), np.float64, 0.0)
        self._down = _Column((3,), np.float64, np.nan)
        self._starts = [0]
        self._X = _Column((3,), np.float64, np.nan)
        self._tri = _Column((), bool, False)
        self._attributes: dict[str, _Column] = {}
        self._obs_kf = _Column((), np.int64, 0)
        self._obs_pt = _Column((), np.int64, 0)
        self._obs_uv = _Column((2,), np.float64, 0.0)
        self._obs_active = _Column((), bool, True)
        self._current_segment = 0

    # ------------------------------------------------------------------------------ growth
    def add_keyframe(self, timestamp: float, point_ids: np.ndarray, uv: np.ndarray) -> int:
        """Append a keyframe with its observations (all active, pose unset: identity at 0).

        Args:
            timestamp: seconds; must exceed the previous keyframe's.
            point_ids: ``(N,)`` non-negative point ids (new ids grow the point arrays), unique.
            uv: ``(N, 2)`` pixels.

        Returns:
            The keyframe's index ``k``.

        Raises:
            SlamError: non-increasing timestamp, bad shapes, negative or repeated ids,
                non-finite pixels.
        """
        point_ids = np.asarray(point_ids, dtype=np.int64).reshape(-1)
        uv = np.asarray(uv, dtype=np.float64)
        check_shape("uv", uv, (point_ids.size, 2))
        check_finite("uv", uv)
        if not np.isfinite(timestamp):
            raise SlamError(f"timestamp: expected a finite number, got {timestamp}")
        C = self.num_keyframes
        if C and not timestamp > self._timestamps.view()[-1]:
            raise SlamError(
                f"timestamp {timestamp}: expected later than the previous keyframe's "
                f"{self._timestamps.view()[-1]}"
            )
        if point_ids.size and point_ids.min() < 0:
            raise SlamError("point_ids: expected non-negative ids")
        if np.unique(point_ids).size != point_ids.size:
            raise SlamError(f"keyframe {C}: a point is observed twice")
        for col in (
            self._timestamps,
            self._segment,
            self._R,
            self._t,
            self._R_on,
            self._t_on,
            self._down,
        ):
            col.resize(C + 1)
        self._timestamps.view()[C] = timestamp
        self._segment.view()[C] = self._current_segment
        for R in (self._R, self._R_on):
            R.view()[C] = np.eye(3)
        if point_ids.size:
            self.ensure_points(int(point_ids.max()) + 1)
        M, N = self.num_observations, point_ids.size
        for col in (self._obs_kf, self._obs_pt, self._obs_uv, self._obs_active):
            col.resize(M + N)
        self._obs_kf.view()[M:] = C
        self._obs_pt.view()[M:] = point_ids
        self._obs_uv.view()[M:] = uv
        self._obs_active.view()[M:] = True
        self._starts.append(M + N)
        return C

    def ensure_points(self, count: int) -> None:
        """Grow the point arrays to at least ``count`` points (new ones untriangulated)."""
        if count > self.num_points:
            for col in (self._X, self._tri, *self._attributes.values()):
                col.resize(count)

    def start_segment(self, first_keyframe: int) -> int:
        """Start a new segment at keyframe ``first_keyframe``: it, the keyframes after it and the
        ones added from now on get the new segment id (returned)."""
        self._current_segment += 1
        self.segment[first_keyframe:] = self._current_segment
        return self._current_segment

    # ------------------------------------------------------------------------------ keyframes
    @property
    def num_keyframes(self) -> int:
        """``C``."""
        return self._timestamps.n

    @property
    def timestamps(self) -> np.ndarray:
        """``(C,)`` seconds."""
        return self._timestamps.view()

    @property
    def segment(self) -> np.ndarray:
        """``(C,)`` segment id of each keyframe."""
        return self._segment.view()

    @property
    def R_wc(self) -> np.ndarray:
        """``(C, 3, 3)`` current camera-to-world rotations (writable view)."""
        return self._R.view()

    @property
    def t_wc(self) -> np.ndarray:
        """``(C, 3)`` current optical centres (writable view)."""
        return self._t.view()

    @property
    def R_wc_online(self) -> np.ndarray:
        """``(C, 3, 3)`` each keyframe's rotation right after its own fusion."""
        return self._R_on.view()

    @property
    def t_wc_online(self) -> np.ndarray:
        """``(C, 3)`` each keyframe's optical centre right after its own fusion."""
        return self._t_on.view()

    @property
    def down_c(self) -> np.ndarray:
        """``(C, 3)`` world down as measured in each keyframe's camera frame (writable view;
        NaN where not measured: :mod:`slam_bridge.frontend.vertical_lines`)."""
        return self._down.view()

    @property
    def starts(self) -> np.ndarray:
        """``(C + 1,)`` observation offsets: keyframe ``k`` owns ``starts[k]:starts[k + 1]``."""
        return np.asarray(self._starts, dtype=np.int64)

    def keyframe_observations(self, k: int) -> np.ndarray:
        """``(N_k,)`` indices of keyframe ``k``'s observations."""
        return np.arange(self._starts[k], self._starts[k + 1])

    def set_pose(self, k: int, R_wc: np.ndarray, t_wc: np.ndarray) -> None:
        """Set keyframe ``k``'s current pose."""
        self.R_wc[k] = R_wc
        self.t_wc[k] = t_wc

    def mark_online(self, k: int) -> None:
        """Record keyframe ``k``'s current pose as its online pose."""
        self.R_wc_online[k] = self.R_wc[k]
        self.t_wc_online[k] = self.t_wc[k]

    def predict_pose(self, timestamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Constant-velocity prediction of the camera pose at ``timestamp`` from the last two
        keyframes of the current segment (None with fewer than two).

        Returns:
            ``(R_wc (3, 3), t_wc (3,))`` or None.
        """
        C = self.num_keyframes
        if C < 2 or self.segment[C - 2] != self.segment[C - 1]:
            return None
        t0, t1 = self.timestamps[C - 2], self.timestamps[C - 1]
        a = (timestamp - t1) / (t1 - t0)
        R0, R1 = self.R_wc[C - 2], self.R_wc[C - 1]
        from slam_bridge.geometry.lie import so3_exp, so3_log

        dR = so3_exp(a * so3_log(R1 @ R0.T))
        return dR @ R1, self.t_wc[C - 1] + a * (self.t_wc[C - 1] - self.t_wc[C - 2])

    # ------------------------------------------------------------------------------ points
    @property
    def num_points(self) -> int:
        """``P``: one more than the largest point id seen."""
        return self._X.n

    @property
    def X_w(self) -> np.ndarray:
        """``(P, 3)`` point positions, NaN where never triangulated (writable view)."""
        return self._X.view()

    @property
    def triangulated(self) -> np.ndarray:
        """``(P,)`` bool, the point has a usable position (writable view)."""
        return self._tri.view()

    def triangulated_points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (T,), X_w (T, 3))`` of the triangulated points."""
        ids = np.flatnonzero(self.triangulated)
        return ids, self.X_w[ids]

    def add_attribute(self, name: str, tail: tuple[int, ...], dtype, fill) -> np.ndarray:
        """Register a per-point attribute ``(P, *tail)`` filled with ``fill``; returns its view.

        Raises:
            SlamError: the name is taken.
        """
        if name in self._attributes:
            raise SlamError(f"point attribute {name!r} exists already")
        col = _Column(tuple(tail), dtype, fill)
        col.resize(self.num_points)
        self._attributes[name] = col
        return col.view()

    def attribute(self, name: str) -> np.ndarray:
        """The view of a registered point attribute ``(P, ...)``.

        Raises:
            SlamError: unknown name.
        """
        if name not in self._attributes:
            raise SlamError(
                f"point attribute {name!r}: not registered ({sorted(self._attributes)})"
            )
        return self._attributes[name].view()

    @property
    def attribute_names(self) -> list[str]:
        """Names of the registered point attributes."""
        return sorted(self._attributes)

    # ------------------------------------------------------------------------------ observations
    @property
    def num_observations(self) -> int:
        """``M``."""
        return self._obs_kf.n

    @property
    def obs_keyframe(self) -> np.ndarray:
        """``(M,)`` keyframe of each observation."""
        return self._obs_kf.view()

    @property
    def obs_point(self) -> np.ndarray:
        """``(M,)`` point id of each observation."""
        return self._obs_pt.view()

    @property
    def obs_uv(self) -> np.ndarray:
        """``(M, 2)`` measured pixels."""
        return self._obs_uv.view()

    @property
    def obs_active(self) -> np.ndarray:
        """``(M,)`` bool, the observation is used (False once rejected; writable view)."""
        return self._obs_active.view()
