"""The visual front end: corners tracked through a frame sequence, delivered as keyframe tracks.

:class:`ImageTracks` implements :class:`slam_bridge.frontend.base.ObservationSource` over a
:class:`slam_bridge.frontend.frames.FrameSequence`. Per frame (grayscale, OpenCV throughout):

1. **photometric normalisation**: a global gamma lookup table brings the median grey level to
   ``gamma_target`` (dark dusk and night frames get contrast the detector and the tracker can
   use); the gamma follows a running median, quantised, so that consecutive frames almost always
   share one table and the brightness-constancy assumption of Lucas-Kanade holds;
2. **tracking**: pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) from the previous frame,
   started at a constant-velocity prediction (each track's last displacement; new tracks take
   the mean displacement of the tracks in their grid cell, else the median of all), then
   tracked back; a track survives when both passes converge (LK status), the back-tracked point
   lands within ``fb_threshold_px`` of its start and it stays ``border_px`` inside the image;
3. **epipolar check** (``epipolar`` = ``frame`` or ``both``): ``cv2.findEssentialMat``
   (MAGSAC++ by default) between the previous and the current positions; tracks it rejects are
   dropped. The check is skipped (nothing dropped) with fewer than ``min_epipolar_tracks`` tracks
   or a median displacement under ``min_epipolar_motion_px`` (no motion: the essential matrix is
   undetermined).

After each frame the keyframe rule (:mod:`slam_bridge.frontend.keyframes`) decides whether the
frame is a keyframe. At a keyframe:

4. **epipolar check against the last keyframe** (``epipolar`` = ``keyframe`` or ``both``): the
   same test on the displacement accumulated since the last keyframe (moving vehicles and slow
   drifts, invisible from one frame to the next, show there);
5. **candidates**: Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) at least
   ``min_distance_px`` from each other and from the live tracks;
6. **re-observation** (``reobserve``): the map's triangulated points of the current segment that
   no live track follows are projected (:func:`slam_bridge.camera.project`) with the pose that
   :meth:`slam_bridge.slam.map.Map.predict_pose` predicts; each is matched to the candidates
   within ``match_radius_px`` by its stored ORB descriptor (Hamming distance at most
   ``max_descriptor_distance``, ratio test ``match_ratio`` against the second best candidate,
   one point per candidate); a matched candidate becomes a track with the point's old id;
7. **top-up**: the other candidates, strongest first, fill the grid cells (``grid`` cells,
   ``max_tracks / cells`` tracks each, then what is left of ``max_tracks`` to any cell up to twice
   that) with new ids;
8. **descriptors**: ORB (``cv2.ORB_create``, upright, one pyramid level: the tracks follow the
   scale, and upright descriptors are more distinctive for a camera that does not roll) for every
   new track and, with ``refresh_descriptors``, every live track: a lost point is then matched
   by its latest appearance.

Before tracking on, :meth:`ImageTracks.next_keyframe` drops the tracks whose observation in the
previous keyframe the loop rejected (``Map.obs_active`` False).

The first frame is the first keyframe; :meth:`ImageTracks.next_keyframe` returns None once the
frames are exhausted (frames after the last keyframe are not delivered). Pixel lengths of the
config (``min_distance_px``, ``border_px``, ``match_radius_px``, the keyframe parallax) are given
at ``reference_width`` and scaled by ``W / reference_width``; accuracies (``fb_threshold_px``,
``ransac_threshold_px``) and the LK window are in pixels of the images as they are.

Segments: keyframes of different map segments share no point. When the loop starts a new segment
it calls :meth:`ImageTracks.start_segment`, which gives every live track a fresh id (returning the
new ids of the ids it is given) and limits re-observation to points born after it.

Timing of each stage is accumulated in :attr:`ImageTracks.timings` (seconds, see
:meth:`ImageTracks.timing_report`).
"""

from __future__ import annotations

import logging
import math
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np
from scipy.spatial import cKDTree

from slam_bridge.camera import project
from slam_bridge.errors import SlamError
from slam_bridge.frontend.base import KeyframeObservations
from slam_bridge.frontend.frames import FrameSequence, check_intrinsics
from slam_bridge.frontend.keyframes import DistanceFn, KeyframeConfig, KeyframeRule
from slam_bridge.geometry import PnPResult, pnp

if TYPE_CHECKING:
    from slam_bridge.slam.map import Map

logger = logging.getLogger(__name__)

__all__ = ["ImageTracksConfig", "ImageTracks"]

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)
_DESC_BYTES = 32


@dataclass
class ImageTracksConfig:
    """Settings of :class:`ImageTracks` (module docstring for the stages).

    Attributes:
        max_tracks: most live tracks (corners are topped up to it at keyframes).
        grid: ``(columns, rows)`` of the bucketing grid.
        min_distance_px: least distance between corners (at ``reference_width``).
        quality_level: Shi-Tomasi threshold, share of the strongest corner's response.
        block_size: Shi-Tomasi neighbourhood (pixels).
        border_px: corners and tracks stay this far inside the image (at ``reference_width``).
        gamma_target: the median grey level is mapped to this share of 255 (only brightened:
            gamma <= 1); None: no normalisation.
        window_px: Lucas-Kanade window side (odd, pixels).
        pyramid_levels: LK pyramid levels above the image (its reach is about
            ``2 ** levels * window_px / 2`` pixels from the prediction).
        lk_iterations: LK iterations per level.
        lk_epsilon: LK convergence threshold (pixels).
        lk_min_eigenvalue: LK's minimal eigenvalue of the window's gradient matrix (divided by
            the window area); weaker windows fail.
        fb_threshold_px: largest forward-backward distance.
        epipolar: where the essential-matrix check runs: ``frame`` (frame to frame),
            ``keyframe`` (keyframe to keyframe), ``both`` or ``off``.
        ransac_method: ``magsac`` (``cv2.USAC_MAGSAC``) or ``ransac`` (``cv2.RANSAC``).
        ransac_threshold_px: inlier threshold (pixels).
        ransac_confidence: RANSAC confidence.
        min_epipolar_tracks: fewer tracks: no check.
        min_epipolar_motion_px: smaller median displacement: no check.
        map_check: at keyframes, estimate the pose from the tracks of triangulated map points
            (:func:`slam_bridge.geometry.pnp`, RANSAC) and drop the tracks it does not explain.
        map_check_threshold_px: reprojection error above which a track fails the map check.
        min_map_points: fewer tracked triangulated points: no map check (the predicted pose
            serves re-observation).
        reobserve: match untracked map points at keyframes (projection-guided).
        match_radius_px: search radius around a point projected with the predicted pose
            (:meth:`~slam_bridge.slam.map.Map.predict_pose`), at ``reference_width``.
        match_radius_pnp_px: the same with the map check's pose (PnP on the tracks).
        max_descriptor_distance: largest Hamming distance (of 256 bits) of a match.
        match_ratio: best / second-best distance must be below this.
        refresh_descriptors: store each live track's descriptor again at every keyframe.
        keyframes: the keyframe rule.
        reference_width: image width at which pixel lengths are given.
        seed: OpenCV RNG seed (RANSAC), for deterministic output.
    """

    max_tracks: int = 600
    grid: tuple[int, int] = (8, 6)
    min_distance_px: float = 12.0
    quality_level: float = 0.001
    block_size: int = 3
    border_px: float = 10.0
    gamma_target: float | None = 0.4
    window_px: int = 11
    pyramid_levels: int = 3
    lk_iterations: int = 20
    lk_epsilon: float = 0.03
    lk_min_eigenvalue: float = 1e-4
    fb_threshold_px: float = 1.0
    epipolar: Literal["frame", "keyframe", "both", "off"] = "both"
    ransac_method: Literal["magsac", "ransac"] = "magsac"
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.999
    min_epipolar_tracks: int = 15
    min_epipolar_motion_px: float = 1.0
    min_eigen_ratio: float = 0.1
    centre_iterations: int = 3
    centre_max_shift_px: float = 2.0
    flow_check: bool = True
    flow_neighbours: int = 8
    flow_abs_px: float = 3.0
    flow_rel: float = 0.3
    map_check: bool = True
    map_check_threshold_px: float = 2.0
    min_map_points: int = 12
    reobserve: bool = True
    match_radius_px: float = 12.0
    match_radius_pnp_px: float = 5.0
    max_descriptor_distance: int = 64
    match_ratio: float = 0.8
    refresh_descriptors: bool = True
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    reference_width: int = 640
    seed: int = 0

    def __post_init__(self) -> None:
        def positive(key: str, integer: bool = False) -> None:
            v = getattr(self, key)
            kinds = int if integer else int | float
            if isinstance(v, bool) or not isinstance(v, kinds) or not v > 0:
                raise SlamError(f"ImageTracksConfig.{key}: expected a number > 0, got {v!r}")

        for key in ("max_tracks", "block_size", "lk_iterations", "reference_width"):
            positive(key, integer=True)
        for key in (
            "min_distance_px",
            "quality_level",
            "lk_epsilon",
            "fb_threshold_px",
            "ransac_threshold_px",
            "match_radius_px",
        ):
            positive(key)
        if not (isinstance(self.window_px, int) and self.window_px >= 5 and self.window_px % 2):
            raise SlamError(
                f"ImageTracksConfig.window_px: expected an odd integer >= 5, got {self.window_px!r}"
            )
        if len(self.grid) != 2 or min(self.grid) < 1:
            raise SlamError(
                f"ImageTracksConfig.grid: expected (columns, rows) >= 1, got {self.grid}"
            )
        if self.epipolar not in ("frame", "keyframe", "both", "off"):
            raise SlamError(
                f"ImageTracksConfig.epipolar: expected frame, keyframe, both or off, got "
                f"{self.epipolar!r}"
            )
        if self.ransac_method not in ("magsac", "ransac"):
            raise SlamError(
                f"ImageTracksConfig.ransac_method: expected magsac or ransac, got "
                f"{self.ransac_method!r}"
            )
        if self.gamma_target is not None and not 0.0 < self.gamma_target < 1.0:
            raise SlamError(
                f"ImageTracksConfig.gamma_target: expected a share in (0, 1) or None, got "
                f"{self.gamma_target!r}"
            )
        if not 0 < self.match_ratio <= 1:
            raise SlamError(
                f"ImageTracksConfig.match_ratio: expected a number in (0, 1], got {self.match_ratio!r}"
            )


class ImageTracks:
    """Keyframe tracks from a frame sequence (module docstring).

    Args:
        frames: the images, their timestamps and intrinsics.
        config: settings (defaults: :class:`ImageTracksConfig`).
        distance: optional ``distance(t0, t1) -> metres`` driven between two timestamps (wheel
            odometry, GPS): keyframes are then spaced by ``config.keyframes.spacing_m``.

    Attributes:
        K: ``(3, 3)`` intrinsics of the frames.
        image_size: ``(W, H)``.
        frames: the frame sequence.
        timings: seconds spent per stage (``read``, ``gray``, ``track``, ``epipolar``,
            ``detect``, ``describe``, ``reobserve``, ``total``) and counts (``frames``,
            ``keyframes``).
        stats: counters (``reobserved``, ``rejected_by_loop``, ``fb_lost``, ``epipolar_frame``,
            ``epipolar_keyframe``, ...).
    """

    def __init__(
        self,
        frames: FrameSequence,
        config: ImageTracksConfig | None = None,
        *,
        distance: DistanceFn | None = None,
    ) -> None:
        self.frames = frames
        self.config = cfg = config or ImageTracksConfig()
        self.K = check_intrinsics(frames.K, "frames.K")
        W, H = (int(v) for v in frames.image_size)
        self.image_size = (W, H)
        if len(frames) < 1:
            raise SlamError("frames: expected at least one frame, got an empty sequence")
        s = W / cfg.reference_width
        self._min_dist = cfg.min_distance_px * s
        self._border = max(cfg.border_px * s, cfg.window_px / 2 + 1)
        self._radius = cfg.match_radius_px * s
        self._flow_abs = cfg.flow_abs_px * s
        self._radius_pnp = cfg.match_radius_pnp_px * s
        self._rule = KeyframeRule(cfg.keyframes, W, distance)
        self._lk = dict(
            winSize=(cfg.window_px, cfg.window_px),
            maxLevel=cfg.pyramid_levels,
            criteria=(
                cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                cfg.lk_iterations,
                cfg.lk_epsilon,
            ),
            minEigThreshold=cfg.lk_min_eigenvalue,
        )
        self._orb = cv2.ORB_create(nlevels=1, edgeThreshold=16, patchSize=31)
        # live tracks
        self._ids = np.zeros(0, dtype=np.int64)
        self._uv = np.zeros((0, 2), dtype=np.float32)
        self._vel = np.zeros((0, 2), dtype=np.float32)
        self._uv_kf = np.zeros((0, 2), dtype=np.float32)
        self._n_kf = 0  # tracks at the last keyframe
        # per point id
        self._desc = np.zeros((0, _DESC_BYTES), dtype=np.uint8)
        self._has_desc = np.zeros(0, dtype=bool)
        self._next_id = 0
        self._segment_first_id = 0
        # frame state
        self._next_frame = 0
        self._prev_gray: np.ndarray | None = None
        self._kf_frame = -1
        self._kf_time = math.nan
        self._median_gray: float | None = None
        self._gamma = 1.0
        self._lut: np.ndarray | None = None
        self.pose_estimate: tuple[np.ndarray, np.ndarray] | None = None
        self.timings: dict[str, float] = defaultdict(float)
        self.stats: dict[str, int] = defaultdict(int)

    # ------------------------------------------------------------------------------ protocol
    def next_keyframe(self, slam_map: Map | None) -> KeyframeObservations | None:
        """Track frames up to the next keyframe and return its observations.

        Args:
            slam_map: the loop's map (read only): its poses predict where untracked points
                appear, its rejected observations end tracks. None: no re-observation and no
                rejection feedback.

        Returns:
            The keyframe, or None when the frames are exhausted.
        """
        t_start = time.perf_counter()
        try:
            if self._next_frame >= len(self.frames):
                return None
            if slam_map is not None and self._next_frame > 0:
                self._drop_rejected(slam_map)
            while self._next_frame < len(self.frames):
                i = self._next_frame
                self._next_frame += 1
                t, rgb, gray = self._read(i)
                if i == 0:
                    return self._keyframe(i, t, rgb, gray, slam_map, "first")
                self._track(gray)
                self._prev_gray = gray
                self.timings["frames"] += 1
                reason = self._rule.decide(
                    i - self._kf_frame, self._kf_time, t, *self._since_keyframe()
                )
                if reason is not None:
                    return self._keyframe(i, t, rgb, gray, slam_map, reason)
            return None
        finally:
            self.timings["total"] += time.perf_counter() - t_start

    def start_segment(self, point_ids: np.ndarray | None = None) -> np.ndarray:
        """Give every live track a fresh id (the loop starts a new map segment).

        Args:
            point_ids: ``(N,)`` ids to translate (e.g. the last keyframe's, so that the loop can
                add that keyframe to the new segment); ids without a live track get fresh ids
                too.

        Returns:
            ``(N,)`` the new ids of ``point_ids`` (empty when None).
        """
        old = self._ids
        self._segment_first_id = self._next_id
        self._ids = self._new_ids(old.size)
        self._copy_descriptors(old, self._ids)
        if point_ids is None:
            return np.zeros(0, dtype=np.int64)
        point_ids = np.asarray(point_ids, dtype=np.int64).reshape(-1)
        lookup = dict(zip(old.tolist(), self._ids.tolist()))
        out = np.array([lookup.get(p, -1) for p in point_ids.tolist()], dtype=np.int64)
        missing = out < 0
        out[missing] = self._new_ids(int(missing.sum()))
        return out

    # ------------------------------------------------------------------------------ frames
    def _read(self, i: int) -> tuple[float, np.ndarray, np.ndarray]:
        t0 = time.perf_counter()
        t, rgb = self.frames[i]
        t1 = time.perf_counter()
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        if self.config.gamma_target is not None:
            gray = self._normalise(gray)
        self.timings["read"] += t1 - t0
        self.timings["gray"] += time.perf_counter() - t1
        return float(t), rgb, gray

    def _normalise(self, gray: np.ndarray) -> np.ndarray:
        """Global gamma lookup: median grey -> ``gamma_target`` (brighten only)."""
        median = float(np.median(gray[::8, ::8])) + 0.5
        self._median_gray = (
            median if self._median_gray is None else 0.8 * self._median_gray + 0.2 * median
        )
        m = min(max(self._median_gray / 255.0, 1e-3), 0.999)
        gamma = math.log(self.config.gamma_target) / math.log(m)
        gamma = min(1.0, max(0.2, round(gamma * 20) / 20))  # quantised: one table for long
        if gamma >= 1.0:
            return gray
        if self._lut is None or gamma != self._gamma:
            self._gamma = gamma
            self._lut = np.round(255.0 * (np.arange(256) / 255.0) ** gamma).astype(np.uint8)
        return cv2.LUT(gray, self._lut)

    # ------------------------------------------------------------------------------ tracking
    def _track(self, gray: np.ndarray) -> None:
        n = self._ids.size
        if n == 0 or self._prev_gray is None:
            return
        cfg = self.config
        t0 = time.perf_counter()
        p0 = self._uv.reshape(-1, 1, 2)
        guess = (self._uv + self._predicted_velocity()).reshape(-1, 1, 2).astype(np.float32)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(
            self._prev_gray, gray, p0, guess, flags=flags, **self._lk
        )
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            gray, self._prev_gray, p1, p0.copy(), flags=flags, **self._lk
        )
        p1 = p1.reshape(-1, 2)
        fb = np.linalg.norm(back.reshape(-1, 2) - self._uv, axis=1)
        ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb < cfg.fb_threshold_px)
        ok &= self._inside(p1)
        self.stats["fb_lost"] += int(n - ok.sum())
        t1 = time.perf_counter()
        self.timings["track"] += t1 - t0
        if cfg.epipolar in ("frame", "both"):
            inl = self._epipolar_inliers(self._uv[ok], p1[ok])
            self.stats["epipolar_frame"] += int((~inl).sum())
            ok[np.flatnonzero(ok)[~inl]] = False
            self.timings["epipolar"] += time.perf_counter() - t1
        self._vel = (p1 - self._uv)[ok]
        self._uv = p1[ok]
        self._ids = self._ids[ok]
        self._uv_kf = self._uv_kf[ok]

    def _predicted_velocity(self) -> np.ndarray:
        """``(N, 2)`` each track's last displacement; new tracks (NaN) take their cell's mean,
        else the median of all, else zero."""
        vel = self._vel.copy()
        known = np.isfinite(vel[:, 0])
        if known.all():
            return vel
        if not known.any():
            vel[:] = 0.0
            return vel
        cells = self._cells(self._uv)
        ncell = self.config.grid[0] * self.config.grid[1]
        count = np.bincount(cells[known], minlength=ncell)
        mean = np.zeros((ncell, 2))
        for d in range(2):
            mean[:, d] = np.bincount(cells[known], weights=vel[known, d], minlength=ncell)
        mean /= np.maximum(count, 1)[:, None]
        fill = np.where(count[cells][:, None] > 0, mean[cells], np.median(vel[known], axis=0))
        vel[~known] = fill[~known]
        return vel

    def _inside(self, uv: np.ndarray) -> np.ndarray:
        W, H = self.image_size
        b = self._border
        with np.errstate(invalid="ignore"):
            return (
                (uv[:, 0] >= b)
                & (uv[:, 0] <= W - 1 - b)
                & (uv[:, 1] >= b)
                & (uv[:, 1] <= H - 1 - b)
            )

    def _cells(self, uv: np.ndarray) -> np.ndarray:
        gx, gy = self.config.grid
        W, H = self.image_size
        cx = np.clip((uv[:, 0] * gx / W).astype(np.int64), 0, gx - 1)
        cy = np.clip((uv[:, 1] * gy / H).astype(np.int64), 0, gy - 1)
        return cy * gx + cx

    def _epipolar_inliers(self, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: consistent with one essential matrix (all True when the check is
        skipped: too few tracks, too little motion, or no model found)."""
        cfg = self.config
        n = uv0.shape[0]
        keep = np.ones(n, dtype=bool)
        if n < max(cfg.min_epipolar_tracks, 5):
            return keep
        if np.median(np.linalg.norm(uv1 - uv0, axis=1)) < cfg.min_epipolar_motion_px:
            return keep
        method = cv2.USAC_MAGSAC if cfg.ransac_method == "magsac" else cv2.RANSAC
        cv2.setRNGSeed(cfg.seed)
        E, mask = cv2.findEssentialMat(
            uv0.astype(np.float64),
            uv1.astype(np.float64),
            self.K,
            method,
            cfg.ransac_confidence,
            cfg.ransac_threshold_px,
        )
        if E is None or mask is None or E.shape != (3, 3):
            self.stats["epipolar_skipped"] += 1
            return keep
        inl = mask.reshape(-1) > 0
        if inl.sum() < 0.3 * n:  # a model that explains so little is no model
            self.stats["epipolar_skipped"] += 1
            return keep
        return inl

    def _gradients(self, gray: np.ndarray) -> _Gradients:
        """Sobel gradients of the keyframe and integral images of their products."""
        Ix16 = cv2.Sobel(gray, cv2.CV_16S, 1, 0, ksize=3)
        Iy16 = cv2.Sobel(gray, cv2.CV_16S, 0, 1, ksize=3)
        products = (
            cv2.multiply(Ix16, Ix16, dtype=cv2.CV_32F),
            cv2.multiply(Iy16, Iy16, dtype=cv2.CV_32F),
            cv2.multiply(Ix16, Iy16, dtype=cv2.CV_32F),
        )
        integrals = tuple(cv2.integral(p, sdepth=cv2.CV_64F) for p in products)
        return _Gradients(Ix16.astype(np.float32), Iy16.astype(np.float32), *integrals)

    def _window_tensor(self, grads: _Gradients, uv: np.ndarray) -> tuple[np.ndarray, ...]:
        """``(Sxx, Syy, Sxy)``, each ``(N,)``: gradient products summed over the LK window
        centred at the pixel nearest to ``uv`` (clipped at the image border)."""
        H, W = grads.Ix.shape
        r = self.config.window_px // 2
        u = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, W - 1)
        v = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, H - 1)
        u0, u1 = np.maximum(u - r, 0), np.minimum(u + r + 1, W)
        v0, v1 = np.maximum(v - r, 0), np.minimum(v + r + 1, H)
        return tuple(
            I[v1, u1] - I[v0, u1] - I[v1, u0] + I[v0, u0] for I in (grads.Ixx, grads.Iyy, grads.Ixy)
        )

    def _isotropic(self, grads: _Gradients, uv: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: the LK window at ``uv`` has ``lambda_min / lambda_max`` of at least
        ``min_eigen_ratio`` (not an edge: no aperture problem)."""
        a, b, c = self._window_tensor(grads, uv)
        half_tr = 0.5 * (a + b)
        disc = np.sqrt(np.maximum(half_tr * half_tr - (a * b - c * c), 0.0))
        return half_tr - disc >= self.config.min_eigen_ratio * np.maximum(half_tr + disc, 1e-12)

    def _centre(self, grads: _Gradients, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Move corners to the point that LK follows under a change of scale.

        Under a scaling about ``o`` by ``s``, LK's translation for a window at ``p`` is
        ``(s - 1) (c - o)`` with ``c = G^-1 sum(g g^T x)`` (``g`` the gradient at ``x``, ``G``
        the window's structure tensor): LK follows ``c``, not ``p``, so a track started at
        ``p != c`` drifts by ``(s - 1) (c - p)`` at every step while the vehicle approaches.
        Starting at the fixed point ``p = c`` (a few iterations) removes that drift.

        Returns:
            ``(uv (N, 2) float32, ok (N,) bool)``: ok when the point moved at most
            ``centre_max_shift_px`` and stays inside the border.
        """
        cfg = self.config
        if cfg.centre_iterations == 0 or uv.shape[0] == 0:
            return uv.astype(np.float32), np.ones(uv.shape[0], dtype=bool)
        H, W = grads.Ix.shape
        r = cfg.window_px // 2
        off = np.arange(-r, r + 1)
        gxf, gyf = grads.Ix.ravel(), grads.Iy.ravel()
        p = uv.astype(np.float64)
        for _ in range(cfg.centre_iterations):
            ui = np.round(p[:, 0]).astype(np.int64)
            vi = np.round(p[:, 1]).astype(np.int64)
            U = np.clip(ui[:, None] + off, 0, W - 1)  # (N, w)
            V = np.clip(vi[:, None] + off, 0, H - 1)
            flat = (V[:, :, None] * W + U[:, None, :]).reshape(p.shape[0], -1)  # (N, w * w)
            gx, gy = gxf[flat], gyf[flat]
            xx = np.broadcast_to((U - p[:, :1])[:, None, :], (p.shape[0], off.size, off.size))
            yy = np.broadcast_to((V - p[:, 1:])[:, :, None], (p.shape[0], off.size, off.size))
            xx, yy = xx.reshape(p.shape[0], -1), yy.reshape(p.shape[0], -1)
            a, b, c = gx * gx, gy * gy, gx * gy
            Sa, Sb, Sc = a.sum(axis=1), b.sum(axis=1), c.sum(axis=1)
            mx = np.einsum("ij,ij->i", a, xx) + np.einsum("ij,ij->i", c, yy)
            my = np.einsum("ij,ij->i", c, xx) + np.einsum("ij,ij->i", b, yy)
            det = Sa * Sb - Sc * Sc
            det = np.where(np.abs(det) > 1e-9 * (Sa + Sb) ** 2, det, np.inf)
            d = np.stack([(Sb * mx - Sc * my) / det, (Sa * my - Sc * mx) / det], axis=1)
            p += np.clip(d, -1.0, 1.0)
        ok = (np.linalg.norm(p - uv, axis=1) <= cfg.centre_max_shift_px) & self._inside(p)
        return p.astype(np.float32), ok

    def _flow_consistent(self, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: each track's displacement agrees with the median displacement of its
        ``flow_neighbours`` nearest tracks within ``flow_abs_px + flow_rel * |median|``."""
        cfg = self.config
        d = (uv1 - uv0).astype(np.float64)
        k = cfg.flow_neighbours
        _, nb = cKDTree(uv1).query(uv1, k=k + 1)
        med = np.median(d[nb[:, 1:]], axis=1)
        dev = np.linalg.norm(d - med, axis=1)
        return dev <= self._flow_abs + cfg.flow_rel * np.linalg.norm(med, axis=1)

    def _since_keyframe(self) -> tuple[float, float]:
        """``(share of the last keyframe's tracks still tracked, their median displacement)``."""
        if self._n_kf == 0:
            return 0.0, math.nan
        share = self._ids.size / self._n_kf
        if self._ids.size == 0:
            return share, math.nan
        flow = np.linalg.norm(self._uv - self._uv_kf, axis=1)
        return share, float(np.median(flow))

    # ------------------------------------------------------------------------------ feedback
    def _drop_rejected(self, slam_map: Map) -> None:
        """Drop the tracks whose observation in our last keyframe the loop rejected."""
        C = slam_map.num_keyframes
        if C == 0 or self._ids.size == 0:
            return
        hits = np.flatnonzero(slam_map.timestamps == self._kf_time)
        if hits.size == 0:
            return
        obs = slam_map.keyframe_observations(int(hits[-1]))
        rejected = slam_map.obs_point[obs][~slam_map.obs_active[obs]]
        if rejected.size:
            keep = ~np.isin(self._ids, rejected)
            self.stats["rejected_by_loop"] += int((~keep).sum())
            self._ids, self._uv = self._ids[keep], self._uv[keep]
            self._vel, self._uv_kf = self._vel[keep], self._uv_kf[keep]

    # ------------------------------------------------------------------------------ keyframes
    def _keyframe(
        self,
        i: int,
        t: float,
        rgb: np.ndarray,
        gray: np.ndarray,
        slam_map: Map | None,
        reason: str,
    ) -> KeyframeObservations:
        cfg = self.config
        self.stats[f"keyframe_{reason}"] += 1
        self.timings["keyframes"] += 1
        if reason == "first":
            self._prev_gray = gray
            self.timings["frames"] += 1
        t0 = time.perf_counter()
        if cfg.epipolar in ("keyframe", "both") and self._ids.size:
            inl = self._epipolar_inliers(self._uv_kf, self._uv)
            self.stats["epipolar_keyframe"] += int((~inl).sum())
            self._keep(inl)
        t1 = time.perf_counter()
        self.timings["epipolar"] += t1 - t0
        grads = self._gradients(gray)
        if cfg.min_eigen_ratio > 0 and self._ids.size:
            ok = self._isotropic(grads, self._uv)
            self.stats["aperture_rejected"] += int((~ok).sum())
            self._keep(ok)
        if cfg.flow_check and self._ids.size > cfg.flow_neighbours:
            ok = self._flow_consistent(self._uv_kf, self._uv)
            self.stats["flow_rejected"] += int((~ok).sum())
            self._keep(ok)
        self.pose_estimate = None
        if slam_map is not None and cfg.map_check:
            self.pose_estimate = self._map_check(slam_map)
        t1b = time.perf_counter()
        self.timings["map_check"] += t1b - t1
        t1 = t1b
        cand = self._detect(gray)
        if cfg.min_eigen_ratio > 0 and cand.shape[0]:
            cand = cand[self._isotropic(grads, cand)]
        t2 = time.perf_counter()
        self.timings["detect"] += t2 - t1
        # descriptors of the live tracks (refresh) and of the candidates, in one ORB call
        n_live = self._ids.size
        describe_live = cfg.refresh_descriptors and n_live > 0
        pts = np.concatenate([self._uv, cand]) if describe_live else cand
        desc, has = self._describe(gray, pts)
        if describe_live:
            self._store_descriptors(self._ids, desc[:n_live], has[:n_live])
            desc, has = desc[n_live:], has[n_live:]
        t3 = time.perf_counter()
        self.timings["describe"] += t3 - t2
        taken = np.zeros(cand.shape[0], dtype=bool)
        if cfg.reobserve and slam_map is not None and cand.shape[0]:
            point, cidx = self._reobserve(t, slam_map, cand, desc, has)
            uv, ok = self._centre(grads, cand[cidx])
            if ok.any():
                taken[cidx[ok]] = True
                self._append(point[ok], uv[ok])
                self.stats["reobserved"] += int(ok.sum())
        t4 = time.perf_counter()
        self.timings["reobserve"] += t4 - t3
        new = self._top_up(cand, taken)
        uv, ok = self._centre(grads, cand[new])
        new, uv = new[ok], uv[ok]
        if new.size:
            ids = self._new_ids(new.size)
            self._append(ids, uv)
            self._store_descriptors(ids, desc[new], has[new])
        self.timings["detect"] += time.perf_counter() - t4
        self._uv_kf = self._uv.copy()
        self._n_kf = self._ids.size
        self._kf_frame, self._kf_time = i, t
        logger.debug("keyframe at frame %d (%s): %d tracks", i, reason, self._ids.size)
        return KeyframeObservations(
            timestamp=t,
            point_ids=self._ids.copy(),
            uv=self._uv.astype(np.float64),
            frame_index=i,
            image=rgb,
        )

    def _map_check(self, slam_map: Map) -> tuple[np.ndarray, np.ndarray] | None:
        """PnP on the live tracks of triangulated points; drops the tracks it rejects.

        Returns:
            The keyframe's estimated ``(R_wc, t_wc)``, or None (too few points, PnP failed).
        """
        ids = self._ids
        sel = np.flatnonzero(ids < slam_map.num_points)
        sel = sel[slam_map.triangulated[ids[sel]]]
        res = self._pnp(slam_map.X_w[ids[sel]], self._uv[sel])
        if res is None:
            return None
        keep = np.ones(ids.size, dtype=bool)
        keep[sel[~res.inliers]] = False
        self.stats["map_rejected"] += int((~keep).sum())
        self._keep(keep)
        return res.R_wc, res.t_wc

    def _pnp(self, X_w: np.ndarray, uv: np.ndarray) -> PnPResult | None:
        """:func:`slam_bridge.geometry.pnp` with the config's threshold, or None (too few
        points, failure)."""
        cfg = self.config
        if X_w.shape[0] < cfg.min_map_points:
            return None
        try:
            return pnp(
                self.K,
                X_w,
                uv.astype(np.float64),
                threshold_px=cfg.map_check_threshold_px,
                min_inliers=cfg.min_map_points,
                seed=cfg.seed,
            )
        except SlamError as err:
            self.stats["pnp_failed"] += 1
            logger.debug("pnp failed: %s", err)
            return None

    def _keep(self, keep: np.ndarray) -> None:
        self._ids, self._uv, self._vel = self._ids[keep], self._uv[keep], self._vel[keep]
        self._uv_kf = self._uv_kf[keep]

    def _append(self, ids: np.ndarray, uv: np.ndarray) -> None:
        uv = uv.astype(np.float32)
        self._ids = np.concatenate([self._ids, ids])
        self._uv = np.concatenate([self._uv, uv])
        self._vel = np.concatenate([self._vel, np.full_like(uv, np.nan)])
        self._uv_kf = np.concatenate([self._uv_kf, uv])

    def _new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    def _detect(self, gray: np.ndarray) -> np.ndarray:
        """``(M, 2)`` float32 candidate corners, strongest first, ``min_distance`` from each
        other and from the live tracks, inside the border."""
        cfg = self.config
        W, H = self.image_size
        room = cfg.max_tracks - self._ids.size
        if room <= 0 and not cfg.reobserve:
            return np.zeros((0, 2), dtype=np.float32)
        b = int(math.ceil(self._border))
        mask = np.zeros((H, W), dtype=np.uint8)
        mask[b : H - b, b : W - b] = 255
        want = 2 * cfg.max_tracks + self._ids.size
        pts = cv2.goodFeaturesToTrack(
            gray,
            maxCorners=want,
            qualityLevel=cfg.quality_level,
            minDistance=self._min_dist,
            mask=mask,
            blockSize=cfg.block_size,
        )
        if pts is None:
            return np.zeros((0, 2), dtype=np.float32)
        pts = pts.reshape(-1, 2)
        if self._ids.size:
            d, _ = cKDTree(self._uv).query(pts, k=1, distance_upper_bound=self._min_dist)
            pts = pts[~np.isfinite(d)]
        return pts.astype(np.float32)

    def _top_up(self, cand: np.ndarray, taken: np.ndarray) -> np.ndarray:
        """Indices of the candidates that become new tracks: strongest first, ``quota`` tracks
        per grid cell, then what room is left up to ``2 * quota`` per cell."""
        cfg = self.config
        room = cfg.max_tracks - self._ids.size
        free = np.flatnonzero(~taken)
        if room <= 0 or free.size == 0:
            return np.zeros(0, dtype=np.int64)
        ncell = cfg.grid[0] * cfg.grid[1]
        quota = int(math.ceil(cfg.max_tracks / ncell))
        count = np.bincount(self._cells(self._uv), minlength=ncell)
        cells = self._cells(cand[free])
        chosen = np.zeros(free.size, dtype=bool)
        for limit in (quota, 2 * quota):
            rank = _rank_within_cells(cells, ~chosen)
            ok = np.flatnonzero(~chosen & (rank + count[cells] < limit))
            ok = ok[: room - int(chosen.sum())]
            chosen[ok] = True
            count += np.bincount(cells[ok], minlength=ncell)
            if chosen.sum() >= room:
                break
        return free[chosen]

    # ------------------------------------------------------------------------------ descriptors
    def _describe(self, gray: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M, 32)`` uint8 ORB descriptors at ``uv`` and ``(M,)`` bool (False near the border,
        where ORB gives none)."""
        m = uv.shape[0]
        desc = np.zeros((m, _DESC_BYTES), dtype=np.uint8)
        has = np.zeros(m, dtype=bool)
        if m == 0:
            return desc, has
        kps = [
            cv2.KeyPoint(float(x), float(y), 31.0, 0.0, 0.0, 0, j)
            for j, (x, y) in enumerate(uv.tolist())
        ]
        kps, d = self._orb.compute(gray, kps)
        if d is not None and len(kps):
            idx = np.array([k.class_id for k in kps], dtype=np.int64)
            desc[idx] = d
            has[idx] = True
        return desc, has

    def _store_descriptors(self, ids: np.ndarray, desc: np.ndarray, has: np.ndarray) -> None:
        if ids.size == 0:
            return
        need = int(ids.max()) + 1
        if need > self._desc.shape[0]:
            cap = max(need, 2 * self._desc.shape[0], 1024)
            d = np.zeros((cap, _DESC_BYTES), dtype=np.uint8)
            d[: self._desc.shape[0]] = self._desc
            h = np.zeros(cap, dtype=bool)
            h[: self._has_desc.size] = self._has_desc
            self._desc, self._has_desc = d, h
        self._desc[ids[has]] = desc[has]
        self._has_desc[ids[has]] = True

    def _copy_descriptors(self, old: np.ndarray, new: np.ndarray) -> None:
        if old.size:
            ok = old < self._has_desc.size
            self._store_descriptors(new[ok], self._desc[old[ok]], self._has_desc[old[ok]])

    def _reobserve(
        self, t: float, slam_map: Map, cand: np.ndarray, desc: np.ndarray, has: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(point ids (R,), candidate indices (R,))`` of untracked map points matched to
        candidates (module docstring, step 6)."""
        cfg = self.config
        empty = np.zeros(0, dtype=np.int64)
        pose, radius = self.pose_estimate, self._radius_pnp
        if pose is None:
            pose, radius = slam_map.predict_pose(t), self._radius
        if pose is None or not has.any():
            return empty, empty
        ids, X = slam_map.triangulated_points()
        sel = (ids >= self._segment_first_id) & (ids < self._has_desc.size)
        ids, X = ids[sel], X[sel]
        sel = self._has_desc[ids] & ~np.isin(ids, self._ids) & np.isfinite(X).all(axis=1)
        ids, X = ids[sel], X[sel]
        if ids.size == 0:
            return empty, empty
        uv, _, front = project(self.K, pose[0], pose[1], X)
        inside = front & self._inside(np.where(front[:, None], uv, -1.0))
        ids, uv, X = ids[inside], uv[inside], X[inside]
        cidx = np.flatnonzero(has)
        if ids.size == 0 or cidx.size == 0:
            return empty, empty
        pairs = cKDTree(uv).sparse_distance_matrix(
            cKDTree(cand[cidx].astype(np.float64)), radius, output_type="ndarray"
        )
        if pairs.size == 0:
            return empty, empty
        pi, cj = pairs["i"].astype(np.int64), cidx[pairs["j"]]
        ham = _POPCOUNT[self._desc[ids[pi]] ^ desc[cj]].sum(axis=1, dtype=np.int64)
        order = np.lexsort((cj, ham, pi))  # per point: best first (ties: lowest candidate)
        pi, cj, ham = pi[order], cj[order], ham[order]
        start = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
        best = ham[start]
        nxt = np.minimum(start + 1, pi.size - 1)
        has_second = (start + 1 < pi.size) & (pi[nxt] == pi[start])
        second = np.where(has_second, ham[nxt], 256)
        ok = (best <= cfg.max_descriptor_distance) & (best < cfg.match_ratio * second)
        mp, mc, mh = pi[start][ok], cj[start][ok], best[ok]
        # one point per candidate: the closest in descriptor space
        order = np.lexsort((mp, mh))
        mp, mc = mp[order], mc[order]
        _, first = np.unique(mc, return_index=True)
        mp, mc = mp[first], mc[first]
        if cfg.map_check and mp.size:
            ok = self._verify(slam_map, X[mp], cand[mc])
            self.stats["reobserve_rejected"] += int((~ok).sum())
            mp, mc = mp[ok], mc[ok]
        return ids[mp], mc

    def _verify(self, slam_map: Map, X_w: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """``(R,)`` bool: re-observations consistent with the keyframe's pose: the map check's
        pose when there is one (reprojection error), else the pose that PnP estimates from them
        and the tracked triangulated points (whose outliers are then dropped too)."""
        thr = self.config.map_check_threshold_px
        if self.pose_estimate is not None:
            uv_hat, _, front = project(self.K, *self.pose_estimate, X_w)
            return front & (np.linalg.norm(uv_hat - uv, axis=1) < thr)
        ids = self._ids
        sel = np.flatnonzero(ids < slam_map.num_points)
        sel = sel[slam_map.triangulated[ids[sel]]]
        res = self._pnp(
            np.concatenate([slam_map.X_w[ids[sel]], X_w]), np.concatenate([self._uv[sel], uv])
        )
        if res is None:
            return np.zeros(uv.shape[0], dtype=bool)
        self.pose_estimate = (res.R_wc, res.t_wc)
        keep = np.ones(ids.size, dtype=bool)
        keep[sel[~res.inliers[: sel.size]]] = False
        self.stats["map_rejected"] += int((~keep).sum())
        self._keep(keep)
        return res.inliers[sel.size :]

    # ------------------------------------------------------------------------------ report
    def timing_report(self) -> dict[str, float]:
        """Milliseconds per frame of each stage, and per keyframe of the keyframe stages."""
        n = max(self.timings.get("frames", 0), 1)
        k = max(self.timings.get("keyframes", 0), 1)
        out = {
            f"{s}_ms_per_frame": 1e3 * self.timings.get(s, 0.0) / n
            for s in ("read", "gray", "track", "epipolar", "total")
        }
        out.update(
            {
                f"{s}_ms_per_keyframe": 1e3 * self.timings.get(s, 0.0) / k
                for s in ("detect", "describe", "reobserve")
            }
        )
        out["frontend_ms_per_frame"] = out["total_ms_per_frame"] - out["read_ms_per_frame"]
        out["frames"], out["keyframes"] = float(n), float(k)
        return out


@dataclass
class _Gradients:
    """Gradients of a keyframe, ``(H, W)`` float32, and integral images of their products,
    ``(H + 1, W + 1)`` float64."""

    Ix: np.ndarray
    Iy: np.ndarray
    Ixx: np.ndarray
    Iyy: np.ndarray
    Ixy: np.ndarray


def _rank_within_cells(cells: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Rank of each active entry among the active entries of its cell (in array order); inactive
    entries get a rank beyond any quota."""
    rank = np.full(cells.size, np.iinfo(np.int64).max // 2, dtype=np.int64)
    idx = np.flatnonzero(active)
    c = cells[idx]
    order = np.argsort(c, kind="stable")
    sc = c[order]
    first = np.searchsorted(sc, sc, side="left")
    r = np.empty(idx.size, dtype=np.int64)
    r[order] = np.arange(idx.size) - first
    rank[idx] = r
    return rank
