"""The visual front end: corners tracked through a frame sequence, delivered as keyframe tracks.

:class:`ImageTracks` implements :class:`slam_bridge.frontend.base.ObservationSource` over a
:class:`slam_bridge.frontend.frames.FrameSequence` (OpenCV throughout, grayscale).

Every frame:

1. **photometric normalisation**: a global gamma lookup table maps the median grey level to
   ``gamma_target`` (dusk and night frames get contrast that the detector and the tracker can
   use); the gamma follows a running median and is quantised, so consecutive frames almost
   always share one table and Lucas-Kanade's brightness constancy holds. With
   ``equalize_clip``, contrast-limited histogram equalisation (CLAHE over
   ``equalize_tiles`` x ``equalize_tiles`` tiles) instead;
2. **tracking**: pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) from the previous frame,
   started at a constant-velocity prediction (each track's last displacement; new tracks take
   the mean of their grid cell, else the median of all), then tracked back: a track survives when
   both passes converge, the back-tracked point lands within ``fb_threshold_px`` of its start and
   it stays ``border_px`` inside the image. **Recovery**: when fewer than ``recover_share`` of
   the established tracks (tracked through a frame before) survive, the prediction failed (a
   sharp turn: tens of degrees within a frame): the frame's homography is estimated from ORB
   matches (:mod:`slam_bridge.frontend.motion`) and the lost tracks are tracked again from
   it; when that finds ``recover_keyframe_tracks`` or more, the frame is a keyframe (``turn``);
3. **epipolar check** (``epipolar`` = ``frame`` or ``both``): ``cv2.findEssentialMat`` (MAGSAC++
   by default) between the previous and the current positions drops the tracks it rejects;
   skipped (nothing dropped) with fewer than ``min_epipolar_tracks`` tracks, a median
   displacement under ``min_epipolar_motion_px`` (no motion, no model) or a model with under 30 %
   inliers.

After each frame, the keyframe rule (:mod:`slam_bridge.frontend.keyframes`: distance driven,
share and number of the last keyframe's tracks still tracked, recovered turns) decides. At a
keyframe, the live tracks are checked, in order:

4. **epipolar check against the last keyframe** (``epipolar`` = ``keyframe`` or ``both``): the
   displacement accumulated since the last keyframe shows moving vehicles and slow slides;
5. **aperture**: a track whose window became an edge (structure-tensor eigenvalue ratio under
   ``min_eigen_ratio``) slides along it: dropped;
6. **local flow**: a track whose displacement since the last keyframe differs from the median of
   its ``flow_neighbours`` nearest tracks by more than ``flow_abs_px + flow_rel * |median|`` is
   stuck or has jumped (repeated texture): dropped; a track whose neighbours lie farther than
   ``flow_radius_px`` (median) is not judged by them: where tracks are sparse (open ground)
   they sit on other surfaces at other depths and move otherwise (measured on car_dense's open
   stretch: of the tracks the check dropped with neighbours over 60 px away, 13 % were off by
   more than 2 px, against 9 % of those it kept: it dropped good tracks where they are scarce);
7. **deformation** (off by default): the local linear map of each track's neighbourhood since
   the last keyframe (least squares over its neighbours) is accumulated since the track's birth;
   once its singular values leave ``exp(+-max_deformation)`` or their ratio exceeds
   ``exp(max_shear)``, LK's translation model no longer holds and the track drifts: it is
   **renewed** (a new id from here, re-centred). It lowers the share of observations more than
   2 px from their true depth-referenced projection, but the shorter tracks cost the SLAM more
   than the drift does (measured with ``geoseg slam run`` on a 300 m car and a 200 m tram drive:
   renewal at ``max_shear = 0.4`` took the bad share from 0.09 / 0.10 to 0.06 / 0.02 and the
   error from 0.21 / 0.18 m to 0.28 / 1.07 m, with tracking failures; the drift left is along
   the epipolar lines, a slightly wrong depth of a consistent point);
8. **alignment** (``align``): every track that started at an earlier keyframe is moved to where
   the patch around its pixel in that keyframe (its *reference*), warped by the track's local
   linear map since then (the least-squares map of its neighbours' displacements), matches the
   image best (:mod:`slam_bridge.frontend.patch_alignment`: translation and brightness, a
   ``2 align_half_window + 1`` window, accepted when it moves the track at most
   ``align_max_shift_px`` with a correlation of at least ``align_min_zncc``; otherwise the
   track is left where LK put it). The frame-to-frame drift then does not accumulate over a
   track's life (measured in ``docs/lessons.md``). The accumulated warp does, as
   the view changes: once the map tracks them, a track ends (its point retired)
   ``max_track_keyframes`` keyframes after its reference (``too_old``);
9. **map check** (``map_check``, when the map has at least ``min_map_points`` triangulated
   points among the tracks): the pose from PnP (:func:`slam_bridge.geometry.multiview.pnp`, RANSAC +
   refinement) on those tracks; the tracks it does not explain within
   ``map_check_threshold_px`` are dropped. The pose is kept in :attr:`ImageTracks.pose_estimate`.

Then new observations:

10. **candidates**: Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) ``min_distance_px`` from
   each other and from the live tracks, with the eigenvalue ratio of step 5;
11. **re-observation** (``reobserve``, :mod:`slam_bridge.frontend.reobservation`): the map's
    triangulated points of the current segment that no track follows and no check dropped
    (*retired* points) are projected with the map-check pose (search radius
    ``match_radius_pnp_px``) or, without it, with :meth:`slam_bridge.slam.map.Map.predict_pose`
    (radius ``match_radius_px``). Those that one of the last ``reacquire_keyframes`` keyframes
    saw are **re-acquired** by LK from that keyframe's image, started at the projection
    (forward-backward checked, within the radius); the others are **matched** by their stored ORB
    descriptor to the candidates within the radius (Hamming <= ``max_descriptor_distance``,
    ratio test ``match_ratio``, one point per candidate). Both are verified against the
    map-check pose, or by a PnP of their own with the tracked points, within
    ``map_check_threshold_px``, and then tracked on with the point's old id;
12. **top-up**: the other candidates, strongest first, fill the grid (``grid`` cells,
    ``max_tracks / cells`` tracks each, then what is left of ``max_tracks`` up to twice that);
13. **centring**: new and re-observed tracks start at the fixed point of LK under a change of
    scale (:func:`slam_bridge.frontend.features.centre`), so that they do not drift while the
    vehicle approaches their surface;
14. **descriptors**: upright ORB for the new tracks and (``refresh_descriptors``) every live
    track: a lost point is then matched by its latest appearance.

New corners go preferably where corners survive: a grid cell's quota is scaled by the recent
first-frame survival of its new tracks (``adaptive_grid``; the near road of a forward camera,
aliased or too fast, loses most of them), and corners that do not survive their first frame do
not count in the keyframe rule's tracked share.

Before tracking on, :meth:`ImageTracks.next_keyframe` drops the tracks whose observation in the
previous keyframe the loop rejected (``Map.obs_active`` False; unless it deactivated most of the
keyframe: that gives up the keyframe, not its points).

The first frame is the first keyframe; :meth:`ImageTracks.next_keyframe` returns None once the
frames are exhausted (the frames after the last keyframe are not delivered). A keyframe left
without any track (a blank frame) is not delivered: the next frame is a keyframe instead.

Pixel lengths of the config (``min_distance_px``, ``border_px``, ``match_radius*_px``,
``flow_abs_px``, the keyframe parallax) are given at ``reference_width`` and scaled by
``W / reference_width``; accuracies (``fb_threshold_px``, ``ransac_threshold_px``,
``map_check_threshold_px``) and the LK window are in pixels of the images as they are.

Segments: keyframes of different map segments share no point. When the loop starts a segment it
calls :meth:`ImageTracks.start_segment`, which gives every live track a fresh id (returning the
new ids of the ids it is given) and limits re-observation to points born after it.

The CPU time of each stage is accumulated in :attr:`ImageTracks.timings` (see
:meth:`ImageTracks.timing_report`) and the effect of each check in :attr:`ImageTracks.stats`.
Deterministic: the same frames, config and map give the same keyframes (``seed`` fixes
OpenCV's RANSAC).
"""

from __future__ import annotations

import logging
import math
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager

import cv2
import numpy as np
from scipy.spatial import cKDTree

from slam_bridge.errors import SlamError
from slam_bridge.frontend import features as ft
from slam_bridge.frontend.base import KeyframeObservations, MapView
from slam_bridge.frontend.frames import FrameSequence, check_intrinsics
from slam_bridge.frontend.keyframes import DistanceFn, KeyframeRule
from slam_bridge.frontend.motion import GlobalMotion
from slam_bridge.frontend.patch_alignment import align_patches, reference_patches
from slam_bridge.frontend.reobservation import PointMemory
from slam_bridge.frontend.tracks_config import ImageTracksConfig
from slam_bridge.geometry.camera import project
from slam_bridge.geometry.multiview import PnPResult, pnp

logger = logging.getLogger(__name__)

__all__ = ["ImageTracksConfig", "ImageTracks"]


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
        timings: CPU seconds of the process (``time.process_time``: all its threads; a busy
            shared machine does not inflate them) per stage (``read``, ``gray``, ``track``,
            ``epipolar``, ``checks``, ``align``, ``map_check``, ``detect``, ``reobserve``,
            ``describe``, ``topup``, ``keyframe``: all the keyframe stages, ``total``) and
            counts (``frames``, ``keyframes``).
        stats: how many tracks each check dropped (``fb_lost``, ``epipolar_frame``,
            ``epipolar_keyframe``, ``aperture_rejected``, ``flow_rejected``, ``too_old``,
            ``map_rejected``, ``rejected_by_loop``), ``renewed``, ``reacquired``,
            ``reobserved`` and their rejected matches, keyframes per reason (``keyframe_*``),
            ``empty_keyframes``.
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
        self._flow_radius = math.inf if cfg.flow_radius_px is None else cfg.flow_radius_px * s
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
        self._tracks = ft.TrackSet.empty()
        self._n_kf = 0  # established tracks (tracked through a frame) at the last keyframe
        self._established: np.ndarray | None = np.zeros(0, dtype=np.int64)  # their ids
        ncell = cfg.grid[0] * cfg.grid[1]
        self._born = np.zeros(ncell)  # new tracks per cell (decaying sum)
        self._survived = np.zeros(ncell)  # of which tracked through their first frame
        self._memory = PointMemory(cfg.reacquire_keyframes)
        self._motion = GlobalMotion()
        self._next_id = 0
        self._next_frame = 0
        self._prev_gray: np.ndarray | None = None
        self._kf_frame = -1
        self._kf_count = 0  # keyframes made so far
        self._ref_grays: dict[int, np.ndarray] = {}  # keyframe -> image, while a track refers to it
        self._kf_time = math.nan
        self._gamma = ft.GammaNormaliser(cfg.gamma_target) if cfg.gamma_target else None
        self._clahe = None
        if cfg.equalize_clip is not None:
            n = cfg.equalize_tiles
            self._clahe = cv2.createCLAHE(clipLimit=cfg.equalize_clip, tileGridSize=(n, n))
        self.pose_estimate: tuple[np.ndarray, np.ndarray] | None = None
        self.keyframe_log: list[tuple[str, float, float]] = []
        self.timings: dict[str, float] = defaultdict(float)
        self.stats: dict[str, int] = defaultdict(int)

    # ------------------------------------------------------------------------------ protocol
    def next_keyframe(self, slam_map: MapView | None) -> KeyframeObservations | None:
        """Track frames up to the next keyframe and return its observations.

        Args:
            slam_map: the loop's map (read only): its points verify the tracks and are
                re-observed, its rejected observations end tracks. None: none of that.

        Returns:
            The keyframe, or None when the frames are exhausted.
        """
        t_start = time.process_time()
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
                    turned = self._track(gray)
                    share, flow, alive = self._since_keyframe()
                    reason = self._rule.decide(
                        i - self._kf_frame, self._kf_time, t, share, flow,
                        tracked=alive, lost=self._n_kf - alive, turned=turned,
                    )  # fmt: skip
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
            self.timings["total"] += time.process_time() - t_start

    def start_segment(self, point_ids: np.ndarray | None = None) -> np.ndarray:
        """Give every live track a fresh id (the loop starts a new map segment).

        Args:
            point_ids: ``(N,)`` ids to translate (e.g. the last keyframe's, so that the loop can
                add that keyframe to the new segment); ids without a live track get fresh ids.

        Returns:
            ``(N,)`` the new ids of ``point_ids`` (empty when None).
        """
        old = self._tracks.ids
        self._memory.first_id = self._next_id
        self._tracks.ids = self._new_ids(old.size)
        self._memory.copy_descriptors(old, self._tracks.ids)
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
        per_kf = (
            "checks", "align", "map_check", "detect", "reobserve", "describe", "topup", "keyframe"
        )  # fmt: skip
        out = {f"{s}_ms_per_frame": 1e3 * self.timings.get(s, 0.0) / n for s in per_frame}
        out.update({f"{s}_ms_per_keyframe": 1e3 * self.timings.get(s, 0.0) / k for s in per_kf})
        out["frontend_ms_per_frame"] = out["total_ms_per_frame"] - out["read_ms_per_frame"]
        out["frames"], out["keyframes"] = float(n), float(k)
        return out

    # ------------------------------------------------------------------------------ frames
    def _read(self, i: int) -> tuple[float, np.ndarray, np.ndarray]:
        t0 = time.process_time()
        t, rgb = self.frames[i]
        t1 = time.process_time()
        gray = rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        if self._clahe is not None:
            gray = self._clahe.apply(gray)
        elif self._gamma is not None:
            gray = self._gamma(gray)
        self.timings["read"] += t1 - t0
        self.timings["gray"] += time.process_time() - t1
        return float(t), rgb, gray

    # ------------------------------------------------------------------------------ tracking
    def _track(self, gray: np.ndarray) -> bool:
        """Stages 2-3; True when a recovery (:meth:`_recover`) found at least
        ``recover_keyframe_tracks`` tracks again."""
        tr = self._tracks
        if len(tr) == 0 or self._prev_gray is None:
            return False
        cfg = self.config
        t0 = time.process_time()
        prev = self._prev_gray
        guess = tr.uv + ft.predicted_velocity(tr, cfg.grid, self.image_size)
        p1, ok = self._lk_track(prev, gray, tr.uv, guess)
        est = np.isfinite(tr.vel[:, 0])
        n_est, least = int(est.sum()), max(cfg.recover_min_tracks, 1)
        if n_est >= least:
            failed = ok[est].sum() < cfg.recover_share * n_est
        else:  # few established tracks (a new segment, a turn): all count, new ones lose more
            failed = len(tr) >= least and ok.sum() < 0.5 * cfg.recover_share * len(tr)
        recovered = self._recover(prev, gray, p1, ok) if failed else 0
        self.stats["fb_lost"] += int(len(tr) - ok.sum())
        t1 = time.process_time()
        self.timings["track"] += t1 - t0
        if cfg.epipolar in ("frame", "both"):
            inl = self._epipolar_inliers(tr.uv[ok], p1[ok])
            outliers = np.flatnonzero(ok)[~inl]
            self.stats["epipolar_frame"] += outliers.size
            self._memory.retire(tr.ids[outliers])
            ok[outliers] = False
            self.timings["epipolar"] += time.process_time() - t1
        new = np.isnan(tr.vel[:, 0])
        if new.any():  # first-frame survival of new tracks, per grid cell
            cells = ft.grid_cells(tr.uv[new], cfg.grid, self.image_size)
            n = self._born.size
            self._born = 0.8 * self._born + np.bincount(cells, minlength=n)
            self._survived = 0.8 * self._survived + np.bincount(cells[ok[new]], minlength=n)
        tr.vel = p1 - tr.uv
        tr.uv = p1
        tr.keep(ok)
        return recovered >= max(cfg.recover_keyframe_tracks, 1)

    def _lk_track(
        self, prev: np.ndarray, gray: np.ndarray, uv: np.ndarray, guess: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pyramidal LK of ``uv`` ``(N, 2)`` from ``prev`` to ``gray`` started at ``guess``,
        tracked back: ``(uv (N, 2) float32, ok (N,))``, ok when both passes converge, the
        back-tracked point lands within ``fb_threshold_px`` and the point stays inside."""
        if uv.shape[0] == 0:
            return np.zeros((0, 2), dtype=np.float32), np.zeros(0, dtype=bool)
        p0 = np.ascontiguousarray(uv, dtype=np.float32).reshape(-1, 1, 2)
        g = np.ascontiguousarray(guess, dtype=np.float32).reshape(-1, 1, 2)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, gray, p0, g, flags=flags, **self._lk)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev, p1, p0.copy(), flags=flags, **self._lk)
        p1 = p1.reshape(-1, 2)
        fb = np.linalg.norm(back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
        ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1) & (fb < self.config.fb_threshold_px)
        return p1, ok & self._inside(p1)

    def _recover(self, prev: np.ndarray, gray: np.ndarray, p1: np.ndarray, ok: np.ndarray) -> int:
        """The prediction failed for most tracks (a sharp turn): track the lost ones again from
        the frame's homography estimated by ORB matches (:mod:`slam_bridge.frontend.motion`).
        Updates ``p1`` ``(N, 2)`` and ``ok`` ``(N,)`` in place; returns how many it found."""
        with self._clock("recover"):
            self.stats["recoveries"] += 1
            motion = self._motion.estimate(prev, gray, seed=self.config.seed)
            if motion is None:
                self.stats["recoveries_failed"] += 1
                return 0
            lost = np.flatnonzero(~ok)
            uv = self._tracks.uv[lost]
            q, good = self._lk_track(prev, gray, uv, motion.apply(uv))
            p1[lost[good]] = q[good]
            ok[lost[good]] = True
            self.stats["recovered"] += int(good.sum())
            return int(good.sum())

    def _inside(self, uv: np.ndarray) -> np.ndarray:
        W, H = self.image_size
        b = self._border
        with np.errstate(invalid="ignore"):
            u, v = uv[:, 0], uv[:, 1]
            return (u >= b) & (u <= W - 1 - b) & (v >= b) & (v <= H - 1 - b)

    def _epipolar_inliers(self, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: consistent with one essential matrix (all True when skipped)."""
        cfg = self.config
        inl = ft.epipolar_inliers(
            uv0, uv1, self.K, magsac=cfg.ransac_method == "magsac",
            threshold_px=cfg.ransac_threshold_px, confidence=cfg.ransac_confidence,
            seed=cfg.seed, min_tracks=cfg.min_epipolar_tracks,
            min_motion_px=cfg.min_epipolar_motion_px,
        )  # fmt: skip
        if inl is None:
            self.stats["epipolar_skipped"] += 1
            return np.ones(uv0.shape[0], dtype=bool)
        return inl

    def _since_keyframe(self) -> tuple[float, float, int]:
        """``(share of the last keyframe's established tracks still tracked, median
        displacement of the tracks since the last keyframe, number still tracked)``.
        Established: tracked through at least one frame before that keyframe (when none was,
        the tracks that survive the first frame after it): corners that do not survive their
        first frame trigger no keyframe."""
        tr = self._tracks
        if self._established is None:  # no established track at the last keyframe: from now
            self._established = tr.ids.copy()
            self._n_kf = len(tr)
        if self._n_kf == 0 or len(tr) == 0:
            return 0.0, math.nan, 0
        alive = int(np.isin(self._established, tr.ids, assume_unique=True).sum())
        flow = np.linalg.norm(tr.uv - tr.uv_kf, axis=1)
        return alive / self._n_kf, float(np.median(flow)), alive

    def _drop_rejected(self, slam_map: MapView) -> None:
        """Drop the tracks whose observation in our last keyframe the loop rejected as outliers.

        When the loop deactivated more than half of that keyframe's observations, it gave up the
        keyframe (no pose, a failed start), not the points: the tracks go on."""
        if slam_map.num_keyframes == 0 or len(self._tracks) == 0:
            return
        hits = np.flatnonzero(slam_map.timestamps == self._kf_time)
        if hits.size == 0:
            return
        obs = slam_map.keyframe_observations(int(hits[-1]))
        rejected = slam_map.obs_point[obs][~slam_map.obs_active[obs]]
        if rejected.size > 0.5 * obs.size:
            self.stats["keyframe_given_up"] += 1
        elif rejected.size:
            self._drop(~np.isin(self._tracks.ids, rejected), "rejected_by_loop")

    # ------------------------------------------------------------------------------ keyframes
    def _keyframe(
        self,
        i: int,
        t: float,
        rgb: np.ndarray,
        gray: np.ndarray,
        slam_map: MapView | None,
        reason: str,
    ) -> KeyframeObservations:
        t0 = time.process_time()
        self.stats[f"keyframe_{reason}"] += 1
        self.timings["keyframes"] += 1
        grads = ft.gradients(gray)
        self._check_tracks(grads)
        self._end_old_tracks(slam_map)
        t1 = time.process_time()
        self.timings["checks"] += t1 - t0
        if self.config.align:
            with self._clock("align"):
                self._align(gray, grads)
            t1 = time.process_time()
        self.pose_estimate = None
        if slam_map is not None and self.config.map_check:
            self.pose_estimate = self._map_check(slam_map)
        self.timings["map_check"] += time.process_time() - t1
        self._add_tracks(t, gray, grads, slam_map)
        tr = self._tracks
        tr.uv_kf = tr.uv.copy()
        self._memory.remember(gray, tr.ids, tr.uv)
        if self.config.align:
            fresh = tr.ref_kf < 0
            tr.ref_kf[fresh], tr.ref_uv[fresh] = self._kf_count, tr.uv[fresh]
            self._ref_grays[self._kf_count] = gray
            used = set(np.unique(tr.ref_kf).tolist())
            self._ref_grays = {k: g for k, g in self._ref_grays.items() if k in used}
        self._kf_count += 1
        established = np.isfinite(tr.vel[:, 0])
        self._established = tr.ids[established] if established.any() else None
        self._n_kf = int(established.sum())
        self._kf_frame, self._kf_time = i, t
        self.timings["keyframe"] += time.process_time() - t0
        logger.debug("keyframe at frame %d (%s): %d tracks", i, reason, len(tr))
        return KeyframeObservations(
            timestamp=t,
            point_ids=tr.ids.copy(),
            uv=tr.uv.astype(np.float64),
            frame_index=i,
            image=rgb,
        )

    def _check_tracks(self, grads: ft.Gradients) -> None:
        """Stages 4-7 on the live tracks (module docstring); with ``align``, the local linear
        maps of stage 7 are accumulated for the alignment (stage 8)."""
        cfg, tr = self.config, self._tracks
        if len(tr) and cfg.epipolar in ("keyframe", "both"):
            t0 = time.process_time()
            self._drop(self._epipolar_inliers(tr.uv_kf, tr.uv), "epipolar_keyframe")
            self.timings["epipolar"] += time.process_time() - t0
        if len(tr) and cfg.min_eigen_ratio > 0:
            self._drop(
                ft.isotropic(grads, tr.uv, cfg.window_px, cfg.min_eigen_ratio), "aperture_rejected"
            )
        if len(tr) <= cfg.flow_neighbours:
            return
        nb = ft.neighbours(tr.uv, cfg.flow_neighbours)
        ok = ft.flow_consistent(
            tr.uv_kf, tr.uv, nb, self._flow_abs, cfg.flow_rel, radius=self._flow_radius
        )
        renewing = cfg.max_deformation is not None or cfg.max_shear is not None
        if renewing or cfg.align:
            tr.A = ft.local_affine(tr.uv_kf, tr.uv, nb) @ tr.A
        self._drop(ok, "flow_rejected")
        if not renewing or len(tr) == 0:
            return
        log_sv = np.log(np.maximum(np.linalg.svd(tr.A, compute_uv=False), 1e-9))  # (N, 2)
        renew = np.zeros(len(tr), dtype=bool)
        if cfg.max_deformation is not None:
            renew |= np.abs(log_sv).max(axis=1) > cfg.max_deformation
        if cfg.max_shear is not None:
            renew |= log_sv[:, 0] - log_sv[:, 1] > cfg.max_shear
        if renew.any():
            idx = np.flatnonzero(renew)
            uv, good = self._centred(grads, tr.uv[idx])
            self._memory.retire(tr.ids[idx])
            r = idx[good]
            tr.ids[r] = self._new_ids(r.size)
            tr.uv[r], tr.vel[r], tr.A[r], tr.ref_kf[r] = uv[good], np.nan, np.eye(2), -1
            keep = np.ones(len(tr), dtype=bool)
            keep[idx[~good]] = False
            tr.keep(keep)
            self.stats["renewed"] += int(r.size)

    def _end_old_tracks(self, slam_map: MapView | None) -> None:
        """End the tracks ``max_track_keyframes`` or more keyframes after their reference, once
        the map tracks them (``min_map_points`` of them triangulated): a start (no map yet, a
        new segment) needs its reference keyframe's tracks for as long as it takes."""
        cfg, tr = self.config, self._tracks
        if cfg.max_track_keyframes is None or len(tr) == 0 or slam_map is None:
            return
        if self._triangulated_tracks(slam_map).size < cfg.min_map_points:
            return
        old = (tr.ref_kf >= 0) & (self._kf_count - tr.ref_kf >= cfg.max_track_keyframes)
        self._drop(~old, "too_old")

    def _align(self, gray: np.ndarray, grads: ft.Gradients) -> None:
        """Stage 8: align the tracks that started at an earlier keyframe to their reference patches
        (:mod:`slam_bridge.frontend.patch_alignment`)."""
        cfg, tr = self.config, self._tracks
        sel = np.flatnonzero(tr.ref_kf >= 0)
        if sel.size == 0:
            return
        P = (2 * cfg.align_half_window + 1) ** 2
        T = np.zeros((sel.size, P))
        warp_ok = np.zeros(sel.size, dtype=bool)
        for k in np.unique(tr.ref_kf[sel]).tolist():
            g = np.flatnonzero(tr.ref_kf[sel] == k)
            i = sel[g]
            T[g], warp_ok[g] = reference_patches(
                self._ref_grays[k], tr.ref_uv[i], tr.A[i], cfg.align_half_window
            )
        res = align_patches(
            T, gray, tr.uv[sel], grads=grads, max_shift=cfg.align_max_shift_px,
            min_zncc=cfg.align_min_zncc,
        )  # fmt: skip
        ok = res.ok & warp_ok & self._inside(res.uv)
        tr.uv[sel[ok]] = res.uv[ok]
        self.stats["aligned"] += int(ok.sum())
        self.stats["align_failed"] += int((~ok).sum())

    def _drop(self, keep: np.ndarray, reason: str) -> None:
        """Drop the tracks outside ``keep`` ``(N,)`` for ``reason`` (a stats key): their points
        are retired (never re-acquired nor re-observed)."""
        tr = self._tracks
        self.stats[reason] += int((~keep).sum())
        self._memory.retire(tr.ids[~keep])
        tr.keep(keep)

    def _map_check(self, slam_map: MapView) -> tuple[np.ndarray, np.ndarray] | None:
        """Stage 9: PnP on the tracks of triangulated points, dropping those it rejects.

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

    def _triangulated_tracks(self, slam_map: MapView) -> np.ndarray:
        """Indices of the live tracks whose point the map has triangulated."""
        ids = self._tracks.ids
        sel = np.flatnonzero(ids < slam_map.num_points)
        return sel[slam_map.triangulated[ids[sel]]]

    def _pnp(self, X_w: np.ndarray, uv: np.ndarray) -> PnPResult | None:
        """:func:`slam_bridge.geometry.multiview.pnp` with the config's threshold, or None (too few
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
        self, t: float, gray: np.ndarray, grads: ft.Gradients, slam_map: MapView | None
    ) -> None:
        """Stages 10-14: candidates, re-observation, top-up, centring, descriptors."""
        cfg, tr = self.config, self._tracks
        with self._clock("detect"):
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
        proj = None
        near = np.zeros(0, dtype=np.int64)
        radius = self._radius_pnp if self.pose_estimate is not None else self._radius
        with self._clock("reobserve"):
            pose = self.pose_estimate
            if cfg.reobserve and slam_map is not None and pose is None:
                pose = slam_map.predict_pose(t)
            if cfg.reobserve and slam_map is not None and pose is not None:
                proj = self._memory.projected(slam_map, pose, self.K, tr.ids, self._inside)
            if proj is not None and cfg.reacquire_keyframes > 0:
                idx, uv, tried = self._memory.reacquire(
                    proj, gray, radius=radius, lk=self._lk, fb_threshold=cfg.fb_threshold_px,
                    inside=self._inside,
                )  # fmt: skip
                if cfg.map_check and idx.size:
                    ok = self._verify(slam_map, proj[2][idx], uv)
                    self.stats["reacquire_rejected"] += int((~ok).sum())
                    idx, uv = idx[ok], uv[ok]
                tr.append(proj[0][idx], uv)
                self.stats["reacquired"] += int(idx.size)
                proj = None if tried.all() else tuple(a[~tried] for a in proj)
                if idx.size:  # no new corner on them
                    d, _ = cKDTree(uv).query(cand, k=1, distance_upper_bound=self._min_dist)
                    cand = cand[~np.isfinite(d)]
            if proj is not None:  # candidates that may be a projected point, centred as tracks
                d, _ = cKDTree(proj[1]).query(cand, k=1, distance_upper_bound=radius)
                near = np.flatnonzero(np.isfinite(d))
                uv, ok = self._centred(grads, cand[near])
                near = near[ok]
                cand[near] = uv[ok]
        with self._clock("describe"):
            live = len(tr) if cfg.refresh_descriptors else 0
            desc, has = self._orb.compute(gray, np.concatenate([tr.uv[:live], cand[near]]))
            self._memory.store_descriptors(tr.ids[:live], desc[:live], has[:live])
        taken = np.zeros(cand.shape[0], dtype=bool)
        if proj is not None and near.size:
            with self._clock("reobserve"):
                pi, ci = self._memory.match(
                    proj, cand[near], desc[live:], has[live:], radius=radius,
                    max_distance=cfg.max_descriptor_distance, ratio=cfg.match_ratio,
                )  # fmt: skip
                if cfg.map_check and pi.size:
                    ok = self._verify(slam_map, proj[2][pi], cand[near[ci]])
                    self.stats["reobserve_rejected"] += int((~ok).sum())
                    pi, ci = pi[ok], ci[ok]
                taken[near[ci]] = True
                tr.append(proj[0][pi], cand[near[ci]])
                self.stats["reobserved"] += int(pi.size)
        room = cfg.max_tracks - len(tr)
        free = np.flatnonzero(~taken)
        if room <= 0 or free.size == 0:
            return
        with self._clock("topup"):
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
        with self._clock("describe"):
            self._memory.store_descriptors(ids, *self._orb.compute(gray, uv))

    @contextmanager
    def _clock(self, stage: str) -> Iterator[None]:
        """Add the CPU time of the block to ``timings[stage]``."""
        t0 = time.process_time()
        try:
            yield
        finally:
            self.timings[stage] += time.process_time() - t0

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
        """Stage 13: ``(uv (M, 2) float32, ok (M,))``, ok when centring moved the point at most
        ``centre_max_shift_px`` and it stays inside the border."""
        cfg = self.config
        c = ft.centre(grads, uv, cfg.window_px, cfg.centre_iterations)
        ok = (np.linalg.norm(c - uv, axis=1) <= cfg.centre_max_shift_px) & self._inside(c)
        return c.astype(np.float32), ok

    def _new_ids(self, n: int) -> np.ndarray:
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    def _verify(self, slam_map: MapView, X_w: np.ndarray, uv: np.ndarray) -> np.ndarray:
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
