"""The visual front end: corners tracked through a frame sequence, delivered as keyframe tracks.

:class:`ImageTracks` implements :class:`slam_bridge.frontend.base.ObservationSource` over a
:class:`slam_bridge.frontend.frames.FrameSequence` (OpenCV throughout, grayscale). Every frame is
normalised photometrically, tracked by pyramidal Lucas-Kanade (re-tracked from a homography after
a sharp turn) and checked epipolarly; at each keyframe (:mod:`slam_bridge.frontend.keyframes`)
the live tracks are checked (aperture, local flow, alignment to their reference patch, the map's
PnP pose) and new corners, re-observed map points and descriptors are added. Each step, its
settings and the measurements behind them: ``docs/frontend.md``.

Pixel lengths of the config are given at ``reference_width`` and scaled to the images; the CPU
time of each stage is in :attr:`ImageTracks.timings`, the effect of each check in
:attr:`ImageTracks.stats`. Deterministic: the same frames, config and map give the same keyframes
(``seed`` fixes OpenCV's RANSAC).
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
