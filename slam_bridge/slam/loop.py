"""The keyframe loop: one keyframe at a time from an observation source, nothing of the future.

:func:`run_slam` pulls keyframes from an :class:`slam_bridge.frontend.base.ObservationSource`
into a :class:`slam_bridge.slam.map.Map` and runs, for each keyframe ``k``:

0. *Start-up* (before the first tracked keyframe): a :class:`StartUp` places the first
   keyframes and fixes the gauge (:class:`KnownStartPoses`: given poses, the chapter-3
   experiment; :class:`slam_bridge.slam.initialization.TwoViewStart`: two-view geometry, scale
   from odometry, georeferencing to the GPS, for images).
1. *Tracking* (:mod:`slam_bridge.slam.tracking`): the pose of ``k`` from its observations of
   mapped points; when too few are left, from the tracks it shares with ``k - 1`` and the
   distance driven (*bridged*). A lost tracking is reported in the keyframe's record and
   recovered from by the start-up's ``restart`` (a new segment), never by killing the run when
   the start-up can restart.
2. *Mapping* (:mod:`slam_bridge.slam.mapping`): triangulation of the new points.
3. *k-BA* (:mod:`slam_bridge.slam.windows`): ``X* = argmin zeta``, plain or hybrid window.
4. *Fusion* (:mod:`slam_bridge.slam.fusion`): barrier fusion with the constraint providers'
   families for ``k`` (GPS, DEM once the map is georeferenced; odometry).
5. *Gating* (:func:`slam_bridge.slam.mapping.gate_window`): bad observations of the fusion
   window deactivated, degenerate points untriangulated.

Each keyframe leaves a :class:`KeyframeRecord` (tracking state, inliers, window sizes, timings,
Hessian memory). After the last keyframe the points that left a hybrid window are
re-triangulated with the final poses.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from threadpoolctl import threadpool_limits

from geoseg.errors import check_finite, check_shape
from slam_bridge.errors import SlamError
from slam_bridge.frontend.base import KeyframeObservations, ObservationSource
from slam_bridge.slam.config import SlamConfig
from slam_bridge.slam.fusion import ConstraintProvider, fuse
from slam_bridge.slam.map import Map
from slam_bridge.slam.mapping import MappingConfig, gate_window, refine_points, triangulate_new
from slam_bridge.slam.tracking import TrackingLost, bridge_two_view, track_keyframe
from slam_bridge.slam.windows import METHODS, carry_points, hessian_bytes, optimise_window

logger = logging.getLogger(__name__)

__all__ = [
    "StartUp",
    "StartResult",
    "KnownStartPoses",
    "KeyframeRecord",
    "SlamResult",
    "run_slam",
]

#: tracking states of a keyframe record
TRACKING_STATES = ("start", "tracked", "weak", "bridged", "lost", "restart")


@dataclass
class StartResult:
    """What a start-up leaves in the map.

    Attributes:
        fixed_keyframes: ``(A,)`` keyframe ids placed and held fixed (the gauge); the first of
            them opens the segment.
        georeferenced: the map is in the world frame (the constraint providers apply).
    """

    fixed_keyframes: np.ndarray
    georeferenced: bool


class StartUp(Protocol):
    """Places the first keyframes of a run, and of a new segment after a lost tracking."""

    def start(self, slam_map: Map, source: ObservationSource) -> StartResult | None:
        """Pull keyframes from ``source`` into the empty map and place them (poses set,
        points triangulated); None when the stream ended before a start was possible."""
        ...

    def restart(self, slam_map: Map, source: ObservationSource, k: int) -> StartResult | None:
        """Start a new segment at keyframe ``k`` (whose tracking was lost) and place it and the
        keyframes it pulls; None when the stream ended first.

        Raises:
            TrackingLost: this start-up cannot restart (the run then stops with that error).
        """
        ...

    def georeference(self, slam_map: Map, k: int) -> bool:
        """Called after each keyframe: move the map into the world frame (or closer to it)
        when enough is known; True when the map was moved."""
        ...


class KnownStartPoses:
    """The first keyframes take given poses and stay fixed (the chapter-3 experiment).

    They stand for the start-up the thesis takes for granted (§3.7 evaluates the fusion on a
    SLAM already expressed in the GPS's projected frame): they fix the metric scale and the
    georeferenced frame once; from then on only the fusion keeps the reconstruction
    georeferenced. The points they see are triangulated. A lost tracking cannot be recovered.

    Args:
        R_wc: ``(F, 3, 3)`` known poses, indexed by the source's ``frame_index`` (the keyframe
            index for simulated tracks, the image index for image tracks).
        t_wc: ``(F, 3)``.
        outlier_gate_px: the start's triangulation gate (the tracking's outlier gate).
        count: how many first keyframes are placed and fixed (default 3).
        mapping: the loop's mapping settings (triangulation parallax).
    """

    def __init__(
        self,
        R_wc: np.ndarray,
        t_wc: np.ndarray,
        outlier_gate_px: float = 20.0,
        count: int = 3,
        mapping: MappingConfig | None = None,
    ) -> None:
        self.R_wc = np.asarray(R_wc, dtype=np.float64)
        self.t_wc = np.asarray(t_wc, dtype=np.float64)
        check_shape("R_wc", self.R_wc, (None, 3, 3))
        check_shape("t_wc", self.t_wc, (self.R_wc.shape[0], 3))
        check_finite("R_wc", self.R_wc)
        check_finite("t_wc", self.t_wc)
        if not 2 <= count <= self.R_wc.shape[0]:
            raise SlamError(
                f"KnownStartPoses: expected 2 <= count <= {self.R_wc.shape[0]} poses, got {count}"
            )
        self.count = int(count)
        self.outlier_gate_px = float(outlier_gate_px)
        self.mapping = mapping or MappingConfig()

    def start(self, slam_map: Map, source: ObservationSource) -> StartResult | None:
        A = self.count
        for _ in range(A):
            obs = source.next_keyframe(slam_map)
            if obs is None:
                return None
            k = slam_map.add_keyframe(obs.timestamp, obs.point_ids, obs.uv)
            if not 0 <= obs.frame_index < self.R_wc.shape[0]:
                raise SlamError(f"KnownStartPoses: no pose for frame {obs.frame_index}")
            slam_map.set_pose(k, self.R_wc[obs.frame_index], self.t_wc[obs.frame_index])
            slam_map.mark_online(k)
        n0 = triangulate_new(slam_map, A - 1, self.mapping, self.outlier_gate_px)
        logger.debug("%d points from the %d known start poses", n0, A)
        return StartResult(np.arange(A), georeferenced=True)

    def restart(self, slam_map: Map, source: ObservationSource, k: int) -> StartResult | None:
        raise TrackingLost("known start poses cannot restart a lost tracking")

    def georeference(self, slam_map: Map, k: int) -> bool:
        return False


@dataclass
class KeyframeRecord:
    """What happened at one keyframe.

    Attributes:
        keyframe: its index.
        tracking: ``start`` (placed by the start-up), ``tracked``, ``weak`` (fewer than
            ``min_tracked`` PnP inliers), ``bridged`` (too few mapped points: placed by two
            views with the previous keyframe), ``lost`` (tracking lost: a new segment starts) or
            ``restart`` (placed by the restart of a new segment).
        segment: its segment.
        n_tracked: PnP inliers.
        n_observations: observations the source gave.
        n_new_points: points triangulated at this keyframe.
        n_gated: observations deactivated (tracking gate + window gate).
        n_culled: points untriangulated after the fusion (degenerate geometry).
        n_pose_graph: pose-graph cameras used.
        n_cameras: free cameras of the window.
        n_points: free points of the window.
        ba_seconds: wall time of ``X* = argmin zeta``.
        ba_iterations: its LM iterations.
        fusion_seconds: wall time of the barrier fusion (0 if not fused).
        fusion_iterations: barrier iterations.
        fusion_seconds_per_iteration: mean time of a barrier iteration (assembly + solves).
        hessian_bytes: memory of the assembled system (:func:`slam_bridge.slam.windows.
            hessian_bytes`).
        constraints: names of the constraint providers fused at this keyframe.
        zeta_star: ``zeta(X*)``.
        zeta: ``zeta`` after the fusion.
        fallback: the hybrid window failed the consistency check: plain k-BA and fusion.
        seconds: wall time of the whole keyframe (source included).
    """

    keyframe: int
    tracking: str = "tracked"
    segment: int = 0
    n_tracked: int = 0
    n_observations: int = 0
    n_new_points: int = 0
    n_gated: int = 0
    n_culled: int = 0
    n_pose_graph: int = 0
    n_cameras: int = 0
    n_points: int = 0
    ba_seconds: float = 0.0
    ba_iterations: int = 0
    fusion_seconds: float = 0.0
    fusion_iterations: int = 0
    fusion_seconds_per_iteration: float = 0.0
    hessian_bytes: int = 0
    constraints: list[str] = field(default_factory=list)
    zeta_star: float = 0.0
    zeta: float = 0.0
    fallback: bool = False
    seconds: float = 0.0

    @property
    def gps_used(self) -> bool:
        """A GPS fix was fused at this keyframe."""
        return "gps" in self.constraints


@dataclass
class SlamResult:
    """Output of :func:`run_slam`.

    Attributes:
        method: ``ba``, ``dpc`` or ``mpc``.
        map: the final map (poses, online poses, points, observations).
        records: one :class:`KeyframeRecord` per keyframe.
        georeferenced: the last segment ended in the world frame.
        georeferenced_segments: the segments placed in the world frame (the others stayed in
            their first camera's frame: a start or restart that never met the GPS).
        seconds: total wall time.
        recoveries: ``(keyframe, rms before, rms after)`` of each time the start-up had to
            georeference a segment again (its fixes had left the trajectory).
        adjustment: the figures of a bundle adjustment of the whole map after the loop
            (:func:`slam_bridge.system.base_fixes.adjust_on_fixes`), or None: the poses are
            the loop's.
        loop_t_wc: ``(C, 3)`` the optical centres the loop left before that adjustment, or
            None.
    """

    method: str
    map: Map
    records: list[KeyframeRecord] = field(default_factory=list)
    georeferenced: bool = True
    georeferenced_segments: list[int] = field(default_factory=list)
    seconds: float = 0.0
    recoveries: list[tuple[int, float, float]] = field(default_factory=list)
    adjustment: dict | None = None
    loop_t_wc: np.ndarray | None = None

    @property
    def placed(self) -> np.ndarray:
        """``(C,)`` bool: the keyframe has a pose (a failed start leaves some without)."""
        return np.isfinite(self.map.t_wc).all(axis=1) & np.isfinite(self.map.R_wc).all(axis=(1, 2))

    @property
    def in_world(self) -> np.ndarray:
        """``(C,)`` bool: the keyframe has a pose in the world frame."""
        return self.placed & np.isin(self.map.segment, self.georeferenced_segments)

    @property
    def R_wc(self) -> np.ndarray:
        """``(C, 3, 3)`` final rotations."""
        return self.map.R_wc

    @property
    def t_wc(self) -> np.ndarray:
        """``(C, 3)`` final optical centres."""
        return self.map.t_wc

    @property
    def tracking_failures(self) -> int:
        """Keyframes whose tracking was lost."""
        return sum(r.tracking == "lost" for r in self.records)

    @property
    def bridged(self) -> int:
        """Keyframes placed by two views with the previous keyframe (too few mapped points)."""
        return sum(r.tracking == "bridged" for r in self.records)


def run_slam(
    source: ObservationSource,
    method: str,
    start: StartUp,
    providers: list[ConstraintProvider] | tuple = (),
    config: SlamConfig | None = None,
    *,
    distance: Callable[[float, float], float] | None = None,
    max_keyframes: int | None = None,
    on_keyframe: Callable[[Map, int, KeyframeObservations | None], None] | None = None,
) -> SlamResult:
    """Run the SLAM over ``source`` (module docstring).

    Args:
        source: the observation source.
        method: ``ba`` (``n = 0``, Lhuillier's barrier BA), ``dpc`` or ``mpc`` (hybrid).
        start: the start-up.
        providers: constraint providers of the fusion (none: vision only).
        config: loop settings.
        distance: metres driven between two times (wheel odometry), the scale of a bridged
            keyframe (default: the last motion's speed).
        max_keyframes: stop after this many keyframes (default: the whole stream).
        on_keyframe: called with ``(map, k, observations)`` after each keyframe the loop
            processes, and with ``(map, k, None)`` for those the start-up placed: the network
            bridge's hook (:class:`slam_bridge.bridge.worker.BridgeWorker`); its time counts in
            the keyframe's.

    Returns:
        A :class:`SlamResult`.

    Raises:
        SlamError: unknown method, a stream too short to start, a lost tracking the start-up
            cannot recover from, a non-finite estimate (never returned silently).
    """
    if method not in METHODS:
        raise SlamError(f"method: expected one of {sorted(METHODS)}, got {method!r}")
    cfg = config or SlamConfig()
    loop = _Loop(source, method, start, list(providers), cfg, max_keyframes, distance)
    loop.on_keyframe = on_keyframe
    if cfg.blas_threads is None:
        return loop.run()
    with threadpool_limits(limits=cfg.blas_threads, user_api="blas"):
        return loop.run()


class _Loop:
    """The state of one run: map, links, fixed keyframes, segment, records."""

    def __init__(
        self, source, method, start, providers, cfg: SlamConfig, max_keyframes, distance
    ) -> None:
        self.source, self.method, self.start_up = source, method, start
        self.providers, self.cfg = providers, cfg
        self.max_keyframes, self.distance = max_keyframes, distance
        self.map = Map(source.K, source.image_size)
        self.links = cfg.window.links()
        self.left = np.zeros(0, dtype=bool)  # points that left a hybrid window (carried)
        self.fixed = np.zeros(0, dtype=np.int64)
        self.georeferenced = False
        self.georeferenced_segments: set[int] = set()
        self.segment_start = 0
        self.first_observation = 0
        self.records: list[KeyframeRecord] = []
        self.on_keyframe: Callable[[Map, int, KeyframeObservations | None], None] | None = None

    def run(self) -> SlamResult:
        t_start = time.perf_counter()
        got = self.start_up.start(self.map, self.source)
        if got is None:
            raise SlamError("the stream ended before the SLAM could start")
        self._begin_segment(got)
        self._start_records(0, "start")
        while self.max_keyframes is None or self.map.num_keyframes < self.max_keyframes:
            t0 = time.perf_counter()
            obs = self.source.next_keyframe(self.map)
            if obs is None:
                break
            k = self.map.add_keyframe(obs.timestamp, obs.point_ids, obs.uv)
            rec = KeyframeRecord(k, n_observations=int(obs.point_ids.size))
            self.records.append(rec)
            self._keyframe(k, rec)
            if self.on_keyframe is not None:
                self.on_keyframe(self.map, k, obs)
            rec.seconds += time.perf_counter() - t0
            if k % 25 == 0:
                logger.info(
                    "%s kf %d: %s, %d cams, %d pts, BA %.0f ms, fusion %d it %.0f ms",
                    self.method, k, rec.tracking, rec.n_cameras, rec.n_points,
                    1e3 * rec.ba_seconds, rec.fusion_iterations, 1e3 * rec.fusion_seconds,
                )  # fmt: skip
        self._refine_segment(None)
        return SlamResult(
            method=self.method,
            map=self.map,
            records=self.records,
            georeferenced=self.georeferenced,
            georeferenced_segments=sorted(self.georeferenced_segments),
            seconds=time.perf_counter() - t_start,
            recoveries=list(getattr(self.start_up, "recoveries", [])),
        )

    def _start_records(self, first: int, state: str) -> None:
        """Records (and the hook's calls, without observations) of the start-up's keyframes."""
        for j in range(first, self.map.num_keyframes):
            self.records.append(KeyframeRecord(j, tracking=state, segment=int(self.map.segment[j])))
            if self.on_keyframe is not None:
                self.on_keyframe(self.map, j, None)

    def _refine_segment(self, end_observation: int | None) -> None:
        """Re-triangulate the points that left a hybrid window during the ending segment."""
        left = np.flatnonzero(self.left)
        if left.size:
            n = refine_points(self.map, left, self.first_observation, end_observation)
            logger.debug("%s: %d carried points re-triangulated", self.method, n)
        self.left = np.zeros(self.map.num_points, dtype=bool)

    def _begin_segment(self, got: StartResult) -> None:
        self.fixed = np.asarray(got.fixed_keyframes, dtype=np.int64)
        self.georeferenced = got.georeferenced
        if got.georeferenced:
            self.georeferenced_segments.add(int(self.map.segment[self.fixed[0]]))
        self.segment_start = int(self.fixed.min())
        self.first_observation = int(self.map.starts[self.segment_start])

    def _keyframe(self, k: int, rec: KeyframeRecord) -> None:
        m, cfg = self.map, self.cfg
        rec.segment = int(m.segment[k])
        # 1. tracking
        try:
            tracked = track_keyframe(m, k, cfg.tracking)
            rec.tracking = "weak" if tracked.weak else "tracked"
        except TrackingLost as exc:
            tracked = bridge_two_view(m, k, distance=self.distance)
            if tracked is None:
                logger.warning("%s", exc)
                rec.tracking = "lost"
                self._restart(k, exc)
                return
            rec.tracking = "bridged"
        rec.n_tracked, rec.n_gated = tracked.inliers, tracked.gated
        m.set_pose(k, tracked.R_wc, tracked.t_wc)
        # 2. mapping
        rec.n_new_points = triangulate_new(
            m, k, cfg.mapping, cfg.tracking.outlier_gate_px, self.first_observation
        )
        self._optimise(k, rec)
        if self.start_up.georeference(m, k):
            self.georeferenced = True
            self.georeferenced_segments.add(int(m.segment[k]))
            self.links = cfg.window.links()  # references re-taken in the moved map

    def _optimise(self, k: int, rec: KeyframeRecord) -> None:
        m, cfg = self.map, self.cfg
        # 3. k-BA
        t0 = time.perf_counter()
        window_terms = [p for p in self.providers if hasattr(p, "window_factors")]
        win = optimise_window(
            m, k, self.method, cfg.window, self.links, self.fixed, self.segment_start,
            extra_terms=(
                (lambda problem: [f for p in window_terms for f in p.window_factors(m, problem)])
                if window_terms else None
            ),
        )  # fmt: skip
        rec.ba_seconds = time.perf_counter() - t0
        rec.ba_iterations, rec.fallback = win.iterations, win.fallback
        problem = win.problem
        st = problem.state
        rec.n_pose_graph = win.n_pose_graph
        rec.n_cameras, rec.n_points = int(st.free_cameras.size), int(st.free_points.size)
        rec.hessian_bytes = hessian_bytes(problem)
        # 4. fusion
        providers = [p for p in self.providers if self.georeferenced or not p.world_frame]
        fused = fuse(m, problem, k, providers, cfg.fusion)
        rec.constraints = fused.constraints
        rec.fusion_seconds, rec.fusion_iterations = fused.seconds, fused.iterations
        rec.fusion_seconds_per_iteration = fused.seconds_per_iteration
        rec.zeta_star, rec.zeta = fused.zeta_star, fused.zeta
        problem.write_back(fused.state, m.R_wc, m.t_wc, m.X_w)
        if win.n_pose_graph > 0:
            moved = carry_points(m, win)
            if self.left.size < m.num_points:
                self.left = np.concatenate(
                    [self.left, np.zeros(m.num_points - self.left.size, bool)]
                )
            self.left[moved] = True
        seg = slice(self.segment_start, k + 1)
        if not (np.all(np.isfinite(m.t_wc[seg])) and np.all(np.isfinite(m.R_wc[seg]))):
            raise SlamError(f"keyframe {k}: non-finite pose estimate")
        m.mark_online(k)
        # 5. gating (the fusion window's reprojection rows)
        o = win.observations[problem.window.observations]
        n_bad, rec.n_culled = gate_window(m, o, k, cfg.mapping, self.first_observation)
        rec.n_gated += n_bad

    def _restart(self, k: int, lost: TrackingLost) -> None:
        """A new segment from keyframe ``k`` whose tracking was lost: the start-up places it
        (or raises). The new segment shares nothing with the old one: its points are
        triangulated anew from its own observations."""
        m = self.map
        self._refine_segment(int(m.starts[k]))
        m.start_segment(k)
        m.triangulated[:] = False
        first_segment = int(m.segment[k])
        try:
            got = self.start_up.restart(m, self.source, k)
        except TrackingLost as exc:
            raise TrackingLost(f"{lost}; {exc}") from exc
        if self.georeferenced:  # re-anchored in the world frame, given-up keyframes included
            self.georeferenced_segments.update(range(first_segment, int(m.segment[-1]) + 1))
        if got is None:
            return
        self._begin_segment(got)
        self._start_records(k + 1, "restart")
