"""The visual front end: corners tracked through a frame sequence, delivered as keyframe tracks.

:class:`ImageTracks` implements :class:`slam_bridge.frontend.base.ObservationSource` over a
:class:`slam_bridge.frontend.frames.FrameSequence` (OpenCV throughout, grayscale).

Every frame:

1. **photometric normalisation**: a global gamma lookup table maps the median grey level to
   ``gamma_target`` (dusk and night frames get contrast that the detector and the tracker can
   use); the gamma follows a running median and is quantised, so consecutive frames almost
   always share one table and Lucas-Kanade's brightness constancy holds;
2. **tracking**: pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) from the previous frame,
   started at a constant-velocity prediction (each track's last displacement; new tracks take
   the mean of their grid cell, else the median of all), then tracked back: a track survives when
   both passes converge, the back-tracked point lands within ``fb_threshold_px`` of its start and
   it stays ``border_px`` inside the image;
3. **epipolar check** (``epipolar`` = ``frame`` or ``both``): ``cv2.findEssentialMat`` (MAGSAC++
   by default) between the previous and the current positions drops the tracks it rejects;
   skipped (nothing dropped) with fewer than ``min_epipolar_tracks`` tracks, a median
   displacement under ``min_epipolar_motion_px`` (no motion, no model) or a model with under 30 %
   inliers.

After each frame, the keyframe rule (:mod:`slam_bridge.frontend.keyframes`) decides. At a
keyframe, the live tracks are checked, in order:

4. **epipolar check against the last keyframe** (``epipolar`` = ``keyframe`` or ``both``): the
   displacement accumulated since the last keyframe shows moving vehicles and slow slides;
5. **aperture**: a track whose window became an edge (structure-tensor eigenvalue ratio under
   ``min_eigen_ratio``) slides along it: dropped;
6. **local flow**: a track whose displacement since the last keyframe differs from the median of
   its ``flow_neighbours`` nearest tracks by more than ``flow_abs_px + flow_rel * |median|`` is
   stuck or has jumped (repeated texture): dropped;
7. **deformation**: the local linear map of each track's neighbourhood since the last keyframe
   (least squares over its neighbours) is accumulated since the track's birth; once its singular
   values leave ``exp(+-max_deformation)`` (scale change, foreshortening), LK's translation model
   no longer holds and the track drifts: it is **renewed** (a new id from here, re-centred);
8. **map check** (``map_check``, when the map has at least ``min_map_points`` triangulated
   points among the tracks): the pose from PnP (:func:`slam_bridge.geometry.pnp`, RANSAC +
   refinement) on those tracks; the tracks it does not explain within
   ``map_check_threshold_px`` are dropped. The pose is kept in :attr:`ImageTracks.pose_estimate`.

Then new observations:

9. **candidates**: Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) ``min_distance_px`` from
   each other and from the live tracks, with the eigenvalue ratio of step 5;
10. **re-observation** (``reobserve``): the map's triangulated points of the current segment
    that no track follows (and that no check dropped: retired points) are projected (:func:`slam_bridge.camera.project`) with the map-check
    pose (radius ``match_radius_pnp_px``) or, without it, with
    :meth:`slam_bridge.slam.map.Map.predict_pose` (radius ``match_radius_px``) and matched to the
    candidates by their stored ORB descriptor (Hamming <= ``max_descriptor_distance``, ratio test
    ``match_ratio``, one point per candidate); the matches are verified against the map-check
    pose, or by a PnP of their own with the tracked points, within ``map_check_threshold_px``; a
    verified candidate becomes a track with the point's old id;
11. **top-up**: the other candidates, strongest first, fill the grid (``grid`` cells,
    ``max_tracks / cells`` tracks each, then what is left of ``max_tracks`` up to twice that);
12. **centring**: new and re-observed tracks start at the fixed point of LK under a change of
    scale (:func:`slam_bridge.frontend.features.centre`), so that they do not drift while the
    vehicle approaches their surface;
13. **descriptors**: upright ORB for the new tracks and (``refresh_descriptors``) every live
    track: a lost point is then matched by its latest appearance.

Before tracking on, :meth:`ImageTracks.next_keyframe` drops the tracks whose observation in the
previous keyframe the loop rejected (``Map.obs_active`` False).

The first frame is the first keyframe; :meth:`ImageTracks.next_keyframe` returns None once the
frames are exhausted (the frames after the last keyframe are not delivered). A keyframe left
without any track (a blank frame) is not delivered: the next frame is a keyframe instead. Pixel lengths of the
config (``min_distance_px``, ``border_px``, ``match_radius*_px``, ``flow_abs_px``, the keyframe
parallax) are given at ``reference_width`` and scaled by ``W / reference_width``; accuracies
(``fb_threshold_px``, ``ransac_threshold_px``, ``map_check_threshold_px``) and the LK window are
in pixels of the images as they are.

Segments: keyframes of different map segments share no point. When the loop starts a segment it
calls :meth:`ImageTracks.start_segment`, which gives every live track a fresh id (returning the
new ids of the ids it is given) and limits re-observation to points born after it.

The time of each stage is accumulated in :attr:`ImageTracks.timings` (see
:meth:`ImageTracks.timing_report`) and the effect of each check in :attr:`ImageTracks.stats`.
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
from slam_bridge.frontend import features as ft
from slam_bridge.frontend.base import KeyframeObservations
from slam_bridge.frontend.frames import FrameSequence, check_intrinsics
from slam_bridge.frontend.keyframes import DistanceFn, KeyframeConfig, KeyframeRule
from slam_bridge.geometry import PnPResult, pnp

if TYPE_CHECKING:
    from slam_bridge.slam.map import Map

logger = logging.getLogger(__name__)

__all__ = ["ImageTracksConfig", "ImageTracks"]


@dataclass
class ImageTracksConfig:
    """Settings of :class:`ImageTracks` (the module docstring numbers the stages).

    Attributes:
        max_tracks: most live tracks (corners are topped up to it at keyframes).
        grid: ``(columns, rows)`` of the bucketing grid.
        min_distance_px: least distance between corners (at ``reference_width``).
        quality_level: Shi-Tomasi threshold, share of the strongest corner's response.
        block_size: Shi-Tomasi neighbourhood (pixels).
        border_px: corners and tracks stay this far inside the image (at ``reference_width``).
        gamma_target: the median grey level is mapped to this share of 255 (brighten only);
            None: no normalisation.
        window_px: Lucas-Kanade window side (odd, pixels); small windows drift less when the
            view changes.
        pyramid_levels: LK pyramid levels above the image (reach about
            ``2 ** levels * window_px / 2`` pixels from the prediction).
        lk_iterations: LK iterations per level.
        lk_epsilon: LK convergence threshold (pixels).
        lk_min_eigenvalue: LK's least eigenvalue of the window's gradient matrix (divided by
            the window area); weaker windows fail.
        fb_threshold_px: largest forward-backward distance.
        epipolar: where the essential-matrix check runs: ``frame``, ``keyframe``, ``both``,
            ``off``.
        ransac_method: ``magsac`` (``cv2.USAC_MAGSAC``) or ``ransac`` (``cv2.RANSAC``).
        ransac_threshold_px: inlier threshold (pixels).
        ransac_confidence: RANSAC confidence.
        min_epipolar_tracks: fewer tracks: no check.
        min_epipolar_motion_px: smaller median displacement: no check.
        min_eigen_ratio: least ``lambda_min / lambda_max`` of a track's LK window (0: off).
        centre_iterations: LK fixed-point iterations for new tracks (0: off).
        centre_max_shift_px: a corner that centring moves further is not used.
        flow_neighbours: neighbours of the local-flow and deformation checks.
        flow_abs_px: local-flow tolerance, pixels (at ``reference_width``).
        flow_rel: local-flow tolerance, share of the neighbours' median displacement.
        max_deformation: a track is renewed when a singular value of its accumulated local
            linear map leaves ``exp(+-max_deformation)`` (None: never).
        map_check: the PnP check of the tracks of triangulated points (stage 8).
        map_check_threshold_px: reprojection error above which a track fails it.
        min_map_points: fewer tracked triangulated points: no map check.
        reobserve: match untracked map points at keyframes (stage 10).
        reacquire_keyframes: keyframe images kept to re-acquire, by LK, the untracked map points
            that one of them observed (0: descriptors only).
        match_radius_px: search radius around a point projected with the predicted pose (at
            ``reference_width``).
        match_radius_pnp_px: the same with the map-check pose.
        max_descriptor_distance: largest Hamming distance (of 256 bits) of a match.
        match_ratio: best / second-best distance must be below this.
        refresh_descriptors: store each live track's descriptor again at every keyframe.
        adaptive_grid: scale each cell's quota by the first-frame survival of its new tracks.
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
    centre_max_shift_px: float = 3.0
    flow_neighbours: int = 8
    flow_abs_px: float = 3.0
    flow_rel: float = 0.3
    max_deformation: float | None = 0.3
    map_check: bool = True
    map_check_threshold_px: float = 1.5
    min_map_points: int = 12
    reobserve: bool = True
    reacquire_keyframes: int = 3
    match_radius_px: float = 12.0
    match_radius_pnp_px: float = 5.0
    max_descriptor_distance: int = 48
    match_ratio: float = 0.8
    refresh_descriptors: bool = True
    adaptive_grid: bool = True
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    reference_width: int = 640
    seed: int = 0

    def __post_init__(self) -> None:
        def check(key: str, ok: bool, expected: str) -> None:
            if not ok:
                raise SlamError(
                    f"ImageTracksConfig.{key}: expected {expected}, got {getattr(self, key)!r}"
                )

        def number(v: object) -> bool:
            return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)

        def integer(v: object) -> bool:
            return isinstance(v, int) and not isinstance(v, bool)

        for key in ("max_tracks", "block_size", "lk_iterations", "reference_width"):
            v = getattr(self, key)
            check(key, integer(v) and v > 0, "an integer > 0")
        for key in ("pyramid_levels", "centre_iterations", "min_epipolar_tracks"):
            v = getattr(self, key)
            check(key, integer(v) and v >= 0, "an integer >= 0")
        v = self.flow_neighbours
        check("flow_neighbours", integer(v) and v >= 2, "an integer >= 2")
        for key in (
            "min_distance_px",
            "quality_level",
            "lk_epsilon",
            "fb_threshold_px",
            "ransac_threshold_px",
            "match_radius_px",
            "match_radius_pnp_px",
            "map_check_threshold_px",
            "flow_abs_px",
            "centre_max_shift_px",
        ):
            v = getattr(self, key)
            check(key, number(v) and v > 0, "a number > 0")
        for key in ("border_px", "lk_min_eigenvalue", "min_epipolar_motion_px", "flow_rel"):
            v = getattr(self, key)
            check(key, number(v) and v >= 0, "a number >= 0")
        w = self.window_px
        check("window_px", integer(w) and w >= 5 and w % 2 == 1, "an odd integer >= 5")
        g = self.grid
        ok = isinstance(g, tuple | list) and len(g) == 2 and all(integer(c) and c >= 1 for c in g)
        check("grid", ok, "(columns, rows), integers >= 1")
        check("epipolar", self.epipolar in ("frame", "keyframe", "both", "off"), "frame, "
              "keyframe, both or off")  # fmt: skip
        check("ransac_method", self.ransac_method in ("magsac", "ransac"), "magsac or ransac")
        check("ransac_confidence", 0 < self.ransac_confidence < 1, "a number in (0, 1)")
        gt = self.gamma_target
        check("gamma_target", gt is None or (number(gt) and 0 < gt < 1), "None or in (0, 1)")
        check("min_eigen_ratio", number(self.min_eigen_ratio) and 0 <= self.min_eigen_ratio < 1,
              "a number in [0, 1)")  # fmt: skip
        md = self.max_deformation
        check("max_deformation", md is None or (number(md) and md > 0), "None or a number > 0")
        check("match_ratio", number(self.match_ratio) and 0 < self.match_ratio <= 1, "in (0, 1]")
        d = self.max_descriptor_distance
        check("max_descriptor_distance", integer(d) and 0 <= d <= 256, "an integer in [0, 256]")
        check("min_map_points", integer(self.min_map_points) and self.min_map_points >= 6,
              "an integer >= 6")  # fmt: skip


@dataclass
class _Tracks:
    """The live tracks (``N``): ids, pixels, last displacement (NaN: unknown), pixels at the
    last keyframe and the local linear map accumulated since the track's birth."""

    ids: np.ndarray
    uv: np.ndarray
    vel: np.ndarray
    uv_kf: np.ndarray
    A: np.ndarray

    @classmethod
    def empty(cls) -> _Tracks:
        z = np.zeros((0, 2), dtype=np.float32)
        return cls(np.zeros(0, np.int64), z, z.copy(), z.copy(), np.zeros((0, 2, 2)))

    def __len__(self) -> int:
        return int(self.ids.size)

    def keep(self, mask: np.ndarray) -> None:
        for name in ("ids", "uv", "vel", "uv_kf", "A"):
            setattr(self, name, getattr(self, name)[mask])

    def append(self, ids: np.ndarray, uv: np.ndarray) -> None:
        uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
        self.ids = np.concatenate([self.ids, ids])
        self.uv = np.concatenate([self.uv, uv])
        self.vel = np.concatenate([self.vel, np.full_like(uv, np.nan)])
        self.uv_kf = np.concatenate([self.uv_kf, uv])
        self.A = np.concatenate([self.A, np.broadcast_to(np.eye(2), (len(ids), 2, 2))])


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
        pose_estimate: ``(R_wc (3, 3), t_wc (3,))`` of the last keyframe from the map check's
            PnP (in the map's frame), or None (no map check at that keyframe).
        keyframe_log: per delivered keyframe, ``(reason, tracked share, median displacement
            px)`` as the keyframe rule saw them (reasons: ``first``, ``spacing``, ``parallax``,
            ``tracks``, ``gap``; :mod:`slam_bridge.frontend.keyframes`).
        timings: seconds per stage (``read``, ``gray``, ``track``, ``epipolar``, ``checks``,
            ``map_check``, ``detect``, ``describe``, ``reobserve``, ``total``) and counts
            (``frames``, ``keyframes``).
        stats: how many tracks each check dropped, keyframes per reason, re-observations.
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
        self._radius_pnp = cfg.match_radius_pnp_px * s
        self._flow_abs = cfg.flow_abs_px * s
        self._rule = KeyframeRule(cfg.keyframes, W, distance)
        criteria = (
            cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
            cfg.lk_iterations,
            cfg.lk_epsilon,
        )
        self._lk = dict(
            winSize=(cfg.window_px, cfg.window_px),
            maxLevel=cfg.pyramid_levels,
            criteria=criteria,
            minEigThreshold=cfg.lk_min_eigenvalue,
        )
        self._orb = ft.OrbDescriptors()
        self._tracks = _Tracks.empty()
        self._n_kf = 0  # established tracks (tracked through a frame) at the last keyframe
        self._established: np.ndarray | None = np.zeros(0, dtype=np.int64)  # their ids
        ncell = cfg.grid[0] * cfg.grid[1]
        self._born = np.zeros(ncell)  # new tracks per cell (decaying sum)
        self._survived = np.zeros(ncell)  # of which tracked through their first frame
        self._desc = np.zeros((0, ft.DESCRIPTOR_BYTES), dtype=np.uint8)  # per point id
        self._has_desc = np.zeros(0, dtype=bool)
        self._next_id = 0
        self._segment_first_id = 0
        self._retired = np.zeros(0, dtype=bool)  # per point id: dropped by a check
        self._kf_count = 0  # keyframes made (delivered or not)
        self._kf_grays: dict[int, np.ndarray] = {}  # the last few keyframes' images
        self._last_kf = np.zeros(0, dtype=np.int64)  # per point id: last keyframe seen (-1)
        self._last_uv = np.zeros((0, 2), dtype=np.float32)  # ... and where
        self._next_frame = 0
        self._prev_gray: np.ndarray | None = None
        self._kf_frame = -1
        self._kf_time = math.nan
        self._median_gray: float | None = None
        self._gamma = 1.0
        self._lut: np.ndarray | None = None
        self.pose_estimate: tuple[np.ndarray, np.ndarray] | None = None
        self.keyframe_log: list[tuple[str, float, float]] = []
        self.timings: dict[str, float] = defaultdict(float)
        self.stats: dict[str, int] = defaultdict(int)

    # ------------------------------------------------------------------------------ protocol
    def next_keyframe(self, slam_map: Map | None) -> KeyframeObservations | None:
        """Track frames up to the next keyframe and return its observations.

        Args:
            slam_map: the loop's map (read only): its points verify the tracks and are
                re-observed, its rejected observations end tracks. None: none of that.

        Returns:
            The keyframe, or None when the frames are exhausted.
        """
        t_start = time.perf_counter()
        try:
            if slam_map is not None and self._next_frame > 0:
                self._drop_rejected(slam_map)
            while self._next_frame < len(self.frames):
                i = self._next_frame
                self._next_frame += 1
                t, rgb, gray = self._read(i)
                self.timings["frames"] += 1
                if i == 0:
                    reason: str | None = "first"
                    share, flow = 1.0, 0.0
                else:
                    self._track(gray)
                    share, flow = self._since_keyframe()
                    reason = self._rule.decide(i - self._kf_frame, self._kf_time, t, share, flow)
                self._prev_gray = gray
                if reason is None:
                    continue
                kf = self._keyframe(i, t, rgb, gray, slam_map, reason)
                if kf.point_ids.size:
                    self.keyframe_log.append((reason, share, flow))
                    return kf
                self.stats["empty_keyframes"] += 1  # nothing to observe: not delivered
            return None
        finally:
            self.timings["total"] += time.perf_counter() - t_start

    def start_segment(self, point_ids: np.ndarray | None = None) -> np.ndarray:
        """Give every live track a fresh id (the loop starts a new map segment).

        Args:
            point_ids: ``(N,)`` ids to translate (e.g. the last keyframe's, so that the loop can
                add that keyframe to the new segment); ids without a live track get fresh ids.

        Returns:
            ``(N,)`` the new ids of ``point_ids`` (empty when None).
        """
        old = self._tracks.ids
        self._segment_first_id = self._next_id
        self._tracks.ids = self._new_ids(old.size)
        ok = old < self._has_desc.size
        self._store_descriptors(self._tracks.ids[ok], self._desc[old[ok]], self._has_desc[old[ok]])
        if point_ids is None:
            return np.zeros(0, dtype=np.int64)
        point_ids = np.asarray(point_ids, dtype=np.int64).reshape(-1)
        lookup = dict(zip(old.tolist(), self._tracks.ids.tolist()))
        out = np.array([lookup.get(p, -1) for p in point_ids.tolist()], dtype=np.int64)
        missing = out < 0
        out[missing] = self._new_ids(int(missing.sum()))
        return out

    def timing_report(self) -> dict[str, float]:
        """Milliseconds per frame of each stage (``*_ms_per_frame``; ``frontend``: all but
        reading the image) and per keyframe of the keyframe stages (``*_ms_per_keyframe``)."""
        n = max(self.timings.get("frames", 0), 1)
        k = max(self.timings.get("keyframes", 0), 1)
        per_frame = ("read", "gray", "track", "epipolar", "total")
        per_kf = ("checks", "map_check", "detect", "describe", "reobserve", "keyframe")
        out = {f"{s}_ms_per_frame": 1e3 * self.timings.get(s, 0.0) / n for s in per_frame}
        out.update({f"{s}_ms_per_keyframe": 1e3 * self.timings.get(s, 0.0) / k for s in per_kf})
        out["frontend_ms_per_frame"] = out["total_ms_per_frame"] - out["read_ms_per_frame"]
        out["frames"], out["keyframes"] = float(n), float(k)
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
        m0 = self._median_gray
        self._median_gray = median if m0 is None else 0.8 * m0 + 0.2 * median
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
        tr = self._tracks
        if len(tr) == 0 or self._prev_gray is None:
            return
        cfg = self.config
        t0 = time.perf_counter()
        p0 = tr.uv.reshape(-1, 1, 2)
        guess = (tr.uv + self._predicted_velocity()).astype(np.float32).reshape(-1, 1, 2)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        prev = self._prev_gray
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, gray, p0, guess, flags=flags, **self._lk)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev, p1, p0.copy(), flags=flags, **self._lk)
        p1 = p1.reshape(-1, 2)
        fb = np.linalg.norm(back.reshape(-1, 2) - tr.uv, axis=1)
        ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb < cfg.fb_threshold_px)
        ok &= self._inside(p1)
        self.stats["fb_lost"] += int(len(tr) - ok.sum())
        t1 = time.perf_counter()
        self.timings["track"] += t1 - t0
        if cfg.epipolar in ("frame", "both"):
            inl = self._epipolar_inliers(tr.uv[ok], p1[ok])
            outliers = np.flatnonzero(ok)[~inl]
            self.stats["epipolar_frame"] += outliers.size
            self._retire(tr.ids[outliers])
            ok[outliers] = False
            self.timings["epipolar"] += time.perf_counter() - t1
        new = np.isnan(tr.vel[:, 0])
        if new.any():  # first-frame survival of new tracks, per grid cell
            cells = ft.grid_cells(tr.uv[new], cfg.grid, self.image_size)
            n = self._born.size
            self._born = 0.8 * self._born + np.bincount(cells, minlength=n)
            self._survived = 0.8 * self._survived + np.bincount(cells[ok[new]], minlength=n)
        tr.vel = p1 - tr.uv
        tr.uv = p1
        tr.keep(ok)

    def _predicted_velocity(self) -> np.ndarray:
        """``(N, 2)`` each track's last displacement; new tracks (NaN) take their cell's mean,
        else the median of all, else zero."""
        tr = self._tracks
        vel = tr.vel.copy()
        known = np.isfinite(vel[:, 0])
        if known.all():
            return vel
        if not known.any():
            return np.zeros_like(vel)
        cells = ft.grid_cells(tr.uv, self.config.grid, self.image_size)
        ncell = self.config.grid[0] * self.config.grid[1]
        count = np.bincount(cells[known], minlength=ncell)
        mean = (
            np.stack(
                [np.bincount(cells[known], weights=vel[known, d], minlength=ncell) for d in (0, 1)],
                axis=1,
            )
            / np.maximum(count, 1)[:, None]
        )
        fill = np.where(count[cells][:, None] > 0, mean[cells], np.median(vel[known], axis=0))
        vel[~known] = fill[~known]
        return vel

    def _inside(self, uv: np.ndarray) -> np.ndarray:
        W, H = self.image_size
        b = self._border
        with np.errstate(invalid="ignore"):
            u, v = uv[:, 0], uv[:, 1]
            return (u >= b) & (u <= W - 1 - b) & (v >= b) & (v <= H - 1 - b)

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
        inl = None if mask is None else mask.reshape(-1) > 0
        if E is None or E.shape != (3, 3) or inl is None or inl.sum() < 0.3 * n:
            self.stats["epipolar_skipped"] += 1  # a model that explains so little is no model
            return keep
        return inl

    def _since_keyframe(self) -> tuple[float, float]:
        """``(share of the last keyframe's established tracks still tracked, median
        displacement of the tracks since the last keyframe)``. Established: tracked through at
        least one frame before that keyframe (when none was, the tracks that survive the first
        frame after it): corners that do not survive their first frame trigger no keyframe."""
        tr = self._tracks
        if self._established is None:  # no established track at the last keyframe: from now
            self._established = tr.ids.copy()
            self._n_kf = len(tr)
        if self._n_kf == 0 or len(tr) == 0:
            return 0.0, math.nan
        alive = int(np.isin(self._established, tr.ids, assume_unique=True).sum())
        flow = np.linalg.norm(tr.uv - tr.uv_kf, axis=1)
        return alive / self._n_kf, float(np.median(flow))

    def _drop_rejected(self, slam_map: Map) -> None:
        """Drop the tracks whose observation in our last keyframe the loop rejected."""
        if slam_map.num_keyframes == 0 or len(self._tracks) == 0:
            return
        hits = np.flatnonzero(slam_map.timestamps == self._kf_time)
        if hits.size == 0:
            return
        obs = slam_map.keyframe_observations(int(hits[-1]))
        rejected = slam_map.obs_point[obs][~slam_map.obs_active[obs]]
        if rejected.size:
            self._drop(~np.isin(self._tracks.ids, rejected), "rejected_by_loop")

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
        t0 = time.perf_counter()
        self.stats[f"keyframe_{reason}"] += 1
        self.timings["keyframes"] += 1
        grads = ft.gradients(gray)
        self._check_tracks(grads)
        t1 = time.perf_counter()
        self.timings["checks"] += t1 - t0
        self.pose_estimate = None
        if slam_map is not None and self.config.map_check:
            self.pose_estimate = self._map_check(slam_map)
        self.timings["map_check"] += time.perf_counter() - t1
        self._add_tracks(t, gray, grads, slam_map)
        tr = self._tracks
        tr.uv_kf = tr.uv.copy()
        self._remember(gray)
        established = np.isfinite(tr.vel[:, 0])
        self._established = tr.ids[established] if established.any() else None
        self._n_kf = int(established.sum())
        self._kf_frame, self._kf_time = i, t
        self.timings["keyframe"] += time.perf_counter() - t0
        logger.debug("keyframe at frame %d (%s): %d tracks", i, reason, len(tr))
        return KeyframeObservations(
            timestamp=t,
            point_ids=tr.ids.copy(),
            uv=tr.uv.astype(np.float64),
            frame_index=i,
            image=rgb,
        )

    def _check_tracks(self, grads: ft.Gradients) -> None:
        """Stages 4-7 on the live tracks (module docstring)."""
        cfg, tr = self.config, self._tracks
        if len(tr) and cfg.epipolar in ("keyframe", "both"):
            t0 = time.perf_counter()
            self._drop(self._epipolar_inliers(tr.uv_kf, tr.uv), "epipolar_keyframe")
            self.timings["epipolar"] += time.perf_counter() - t0
        if len(tr) and cfg.min_eigen_ratio > 0:
            self._drop(
                ft.isotropic(grads, tr.uv, cfg.window_px, cfg.min_eigen_ratio), "aperture_rejected"
            )
        if len(tr) <= cfg.flow_neighbours:
            return
        nb = ft.neighbours(tr.uv, cfg.flow_neighbours)
        ok = ft.flow_consistent(tr.uv_kf, tr.uv, nb, self._flow_abs, cfg.flow_rel)
        if cfg.max_deformation is not None:
            tr.A = ft.local_affine(tr.uv_kf, tr.uv, nb) @ tr.A
        self._drop(ok, "flow_rejected")
        if cfg.max_deformation is not None:
            sv = np.linalg.svd(tr.A, compute_uv=False)
            renew = np.abs(np.log(np.maximum(sv, 1e-9))).max(axis=1) > cfg.max_deformation
            if renew.any():
                idx = np.flatnonzero(renew)
                uv, good = self._centred(grads, tr.uv[idx])
                self._retire(tr.ids[idx])
                r = idx[good]
                tr.ids[r] = self._new_ids(r.size)
                tr.uv[r], tr.vel[r], tr.A[r] = uv[good], np.nan, np.eye(2)
                keep = np.ones(len(tr), dtype=bool)
                keep[idx[~good]] = False
                tr.keep(keep)
                self.stats["renewed"] += int(r.size)

    def _drop(self, keep: np.ndarray, reason: str) -> None:
        """Drop the tracks outside ``keep`` ``(N,)`` for ``reason`` (a stats key): their points
        are retired (never re-acquired nor re-observed)."""
        tr = self._tracks
        self.stats[reason] += int((~keep).sum())
        self._retire(tr.ids[~keep])
        tr.keep(keep)

    def _retire(self, ids: np.ndarray) -> None:
        if ids.size == 0:
            return
        if ids.max() >= self._retired.size:
            grow = max(int(ids.max()) + 1, 2 * self._retired.size, 1024) - self._retired.size
            self._retired = np.concatenate([self._retired, np.zeros(grow, dtype=bool)])
        self._retired[ids] = True

    def _map_check(self, slam_map: Map) -> tuple[np.ndarray, np.ndarray] | None:
        """Stage 8: PnP on the tracks of triangulated points, dropping those it rejects.

        Returns:
            The keyframe's estimated ``(R_wc, t_wc)``, or None (too few points, PnP failed).
        """
        tr = self._tracks
        sel = self._triangulated_tracks(slam_map)
        res = self._pnp(slam_map.X_w[tr.ids[sel]], tr.uv[sel])
        if res is None:
            return None
        keep = np.ones(len(tr), dtype=bool)
        keep[sel[~res.inliers]] = False
        self._drop(keep, "map_rejected")
        return res.R_wc, res.t_wc

    def _triangulated_tracks(self, slam_map: Map) -> np.ndarray:
        """Indices of the live tracks whose point the map has triangulated."""
        ids = self._tracks.ids
        sel = np.flatnonzero(ids < slam_map.num_points)
        return sel[slam_map.triangulated[ids[sel]]]

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

    def _add_tracks(
        self, t: float, gray: np.ndarray, grads: ft.Gradients, slam_map: Map | None
    ) -> None:
        """Stages 9-13: candidates, re-observation, top-up, centring, descriptors."""
        cfg, tr = self.config, self._tracks
        t0 = time.perf_counter()
        cand = ft.detect_corners(
            gray,
            max_corners=2 * cfg.max_tracks + len(tr),
            quality_level=cfg.quality_level,
            min_distance=self._min_dist,
            border=self._border,
            block_size=cfg.block_size,
            avoid=tr.uv,
        )
        if cfg.min_eigen_ratio > 0 and cand.shape[0]:
            cand = cand[ft.isotropic(grads, cand, cfg.window_px, cfg.min_eigen_ratio)]
        t1 = time.perf_counter()
        self.timings["detect"] += t1 - t0
        proj = None
        near = np.zeros(0, dtype=np.int64)
        if cfg.reobserve and slam_map is not None and cand.shape[0]:
            proj = self._projected_points(t, slam_map)
        if proj is not None and cfg.reacquire_keyframes > 0:
            point, uv, tried = self._reacquire(slam_map, proj, gray)
            tr.append(point, uv)
            self.stats["reacquired"] += int(point.size)
            keep = ~tried
            proj = (proj[0][keep], proj[1][keep], proj[2][keep], proj[3]) if keep.any() else None
            if point.size:  # no new corner on them
                d, _ = cKDTree(uv).query(cand, k=1, distance_upper_bound=self._min_dist)
                cand = cand[~np.isfinite(d)]
        if proj is not None:  # candidates that may be a projected point, centred like tracks
            d, _ = cKDTree(proj[1]).query(cand, k=1, distance_upper_bound=proj[3])
            near = np.flatnonzero(np.isfinite(d))
            uv, ok = self._centred(grads, cand[near])
            near = near[ok]
            cand[near] = uv[ok]
        live = len(tr) if cfg.refresh_descriptors else 0
        desc, has = self._orb.compute(gray, np.concatenate([tr.uv[:live], cand[near]]))
        self._store_descriptors(tr.ids[:live], desc[:live], has[:live])
        t2 = time.perf_counter()
        self.timings["describe"] += t2 - t1
        taken = np.zeros(cand.shape[0], dtype=bool)
        if proj is not None and near.size:
            point, ci = self._reobserve(slam_map, proj, cand[near], desc[live:], has[live:])
            taken[near[ci]] = True
            tr.append(point, cand[near[ci]])
            self.stats["reobserved"] += int(point.size)
        t3 = time.perf_counter()
        self.timings["reobserve"] += t3 - t2
        room = cfg.max_tracks - len(tr)
        free = np.flatnonzero(~taken)
        if room > 0 and free.size:
            chosen = ft.grid_top_up(
                ft.grid_cells(cand[free], cfg.grid, self.image_size),
                ft.grid_cells(tr.uv, cfg.grid, self.image_size),
                self._cell_quota(),
                room,
            )
            uv, ok = self._centred(grads, cand[free[chosen]])
            uv = uv[ok]
            ids = self._new_ids(uv.shape[0])
            tr.append(ids, uv)
            t4 = time.perf_counter()
            self._store_descriptors(ids, *self._orb.compute(gray, uv))
            self.timings["describe"] += time.perf_counter() - t4
        self.timings["detect"] += time.perf_counter() - t3

    def _remember(self, gray: np.ndarray) -> None:
        """Keep this keyframe's image and where each live track is, for re-acquisition."""
        n = self.config.reacquire_keyframes
        if n <= 0:
            return
        self._kf_grays[self._kf_count] = gray
        self._kf_grays.pop(self._kf_count - n, None)
        tr = self._tracks
        if len(tr) and tr.ids.max() >= self._last_kf.size:
            cap = max(int(tr.ids.max()) + 1, 2 * self._last_kf.size, 1024)
            self._last_kf = np.concatenate(
                [self._last_kf, np.full(cap - self._last_kf.size, -1, dtype=np.int64)]
            )
            self._last_uv = np.concatenate(
                [self._last_uv, np.zeros((cap - self._last_uv.shape[0], 2), dtype=np.float32)]
            )
        self._last_kf[tr.ids] = self._kf_count
        self._last_uv[tr.ids] = tr.uv
        self._kf_count += 1

    def _reacquire(
        self, slam_map: Map, proj: tuple[np.ndarray, np.ndarray, np.ndarray, float], gray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stage 10, first part: LK from the last keyframe that saw each projected point (if
        kept) to this one, started at the projection; forward-backward check, within the search
        radius of the projection, verified like the matches.

        Returns:
            ``(ids (R,), uv (R, 2) float32, tried (P,) bool)``: the re-acquired points and which
            of ``proj`` were tried (the others go to descriptor matching).
        """
        ids, uv_pred, X, radius = proj
        cfg = self.config
        seen = np.full(ids.size, -1, dtype=np.int64)
        known = ids < self._last_kf.size
        seen[known] = self._last_kf[ids[known]]
        tried = np.isin(seen, list(self._kf_grays))
        got = np.zeros(ids.size, dtype=bool)
        uv_out = np.zeros((ids.size, 2), dtype=np.float32)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        for k in np.unique(seen[tried]):
            sel = np.flatnonzero(seen == k)
            p0 = self._last_uv[ids[sel]].reshape(-1, 1, 2)
            guess = uv_pred[sel].astype(np.float32).reshape(-1, 1, 2)
            old = self._kf_grays[int(k)]
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(old, gray, p0, guess, flags=flags, **self._lk)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(
                gray, old, p1, p0.copy(), flags=flags, **self._lk
            )
            p1 = p1.reshape(-1, 2)
            ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & self._inside(p1)
            ok &= (
                np.linalg.norm(back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
                < cfg.fb_threshold_px
            )
            ok &= np.linalg.norm(p1 - uv_pred[sel], axis=1) < radius
            got[sel[ok]] = True
            uv_out[sel] = p1
        idx = np.flatnonzero(got)
        if cfg.map_check and idx.size:
            ok = self._verify(slam_map, X[idx], uv_out[idx])
            self.stats["reacquire_rejected"] += int((~ok).sum())
            idx = idx[ok]
        return ids[idx], uv_out[idx], tried

    def _cell_quota(self) -> np.ndarray:
        """``(C,)`` new tracks per grid cell: ``max_tracks / C`` scaled by the cell's recent
        first-frame survival of new tracks (``rate / 0.5``, clipped to ``[0.2, 1]``): cells
        whose corners do not survive a frame (aliased or fast-moving road) get fewer."""
        cfg = self.config
        ncell = self._born.size
        rate = (self._survived + 1.0) / (self._born + 2.0)
        share = np.clip(rate / 0.5, 0.2, 1.0) if cfg.adaptive_grid else np.ones(ncell)
        return np.ceil(cfg.max_tracks / ncell * share).astype(np.int64)

    def _centred(self, grads: ft.Gradients, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stage 12: ``(uv (M, 2) float32, ok (M,))``, ok when centring moved the point at most
        ``centre_max_shift_px`` and it stays inside the border."""
        cfg = self.config
        c = ft.centre(grads, uv, cfg.window_px, cfg.centre_iterations)
        ok = (np.linalg.norm(c - uv, axis=1) <= cfg.centre_max_shift_px) & self._inside(c)
        return c.astype(np.float32), ok

    def _new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    def _store_descriptors(self, ids: np.ndarray, desc: np.ndarray, has: np.ndarray) -> None:
        if ids.size == 0:
            return
        need = int(ids.max()) + 1
        if need > self._desc.shape[0]:
            cap = max(need, 2 * self._desc.shape[0], 1024)
            d = np.zeros((cap, ft.DESCRIPTOR_BYTES), dtype=np.uint8)
            d[: self._desc.shape[0]] = self._desc
            h = np.zeros(cap, dtype=bool)
            h[: self._has_desc.size] = self._has_desc
            self._desc, self._has_desc = d, h
        self._desc[ids[has]] = desc[has]
        self._has_desc[ids[has]] = True

    def _projected_points(
        self, t: float, slam_map: Map
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        """The map's triangulated points of the current segment that no track follows and that
        the loop did not just reject, projected with the map-check pose or the predicted one:
        ``(ids (P,), uv (P, 2), X_w (P, 3), search radius)``, or None (no pose, no point)."""
        pose, radius = self.pose_estimate, self._radius_pnp
        if pose is None:
            pose, radius = slam_map.predict_pose(t), self._radius
        if pose is None:
            return None
        ids, X = slam_map.triangulated_points()
        sel = (ids >= self._segment_first_id) & (ids < self._has_desc.size)
        ids, X = ids[sel], X[sel]
        sel = self._has_desc[ids] & np.isfinite(X).all(axis=1)
        sel &= ~np.isin(ids, self._tracks.ids)
        ids, X = ids[sel], X[sel]
        ids_ok = ids < self._retired.size
        sel = np.ones(ids.size, dtype=bool)
        sel[ids_ok] = ~self._retired[ids[ids_ok]]
        ids, X = ids[sel], X[sel]
        if ids.size == 0:
            return None
        uv, _, front = project(self.K, pose[0], pose[1], X)
        inside = front & self._inside(np.where(front[:, None], uv, -1.0))
        if not inside.any():
            return None
        return ids[inside], uv[inside], X[inside], radius

    def _reobserve(
        self,
        slam_map: Map,
        proj: tuple[np.ndarray, np.ndarray, np.ndarray, float],
        cand: np.ndarray,
        desc: np.ndarray,
        has: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Stage 10: ``(point ids (R,), candidate indices (R,))`` of the verified matches of the
        projected points ``proj`` (:meth:`_projected_points`) with the candidates ``cand``
        ``(C, 2)`` (centred) and their descriptors."""
        cfg = self.config
        ids, uv, X, radius = proj
        cidx = np.flatnonzero(has)
        mp, mc = ft.match_in_radius(
            uv,
            self._desc[ids],
            cand[cidx],
            desc[cidx],
            radius=radius,
            max_distance=cfg.max_descriptor_distance,
            ratio=cfg.match_ratio,
        )
        mc = cidx[mc]
        if cfg.map_check and mp.size:
            ok = self._verify(slam_map, X[mp], cand[mc])
            self.stats["reobserve_rejected"] += int((~ok).sum())
            mp, mc = mp[ok], mc[ok]
        return ids[mp], mc

    def _verify(self, slam_map: Map, X_w: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """``(R,)`` bool: re-observations consistent with the keyframe's pose: the map check's
        pose when there is one, else the pose that PnP estimates from them and the tracked
        triangulated points (whose outliers are then dropped too)."""
        thr = self.config.map_check_threshold_px
        if self.pose_estimate is not None:
            uv_hat, _, front = project(self.K, *self.pose_estimate, X_w)
            return front & (np.linalg.norm(uv_hat - uv, axis=1) < thr)
        tr = self._tracks
        sel = self._triangulated_tracks(slam_map)
        res = self._pnp(
            np.concatenate([slam_map.X_w[tr.ids[sel]], X_w]), np.concatenate([tr.uv[sel], uv])
        )
        if res is None:
            return np.zeros(uv.shape[0], dtype=bool)
        self.pose_estimate = (res.R_wc, res.t_wc)
        keep = np.ones(len(tr), dtype=bool)
        keep[sel[~res.inliers[: sel.size]]] = False
        self._drop(keep, "map_rejected")
        return res.inliers[sel.size :]
