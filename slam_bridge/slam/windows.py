"""The SLAM's k-BA window at each keyframe: plain (``n = 0``) or hybrid BA / pose graph.

``n = 0`` (method ``ba``): the plain window of the ``l`` latest keyframes with all their
observations, older observers held fixed (:mod:`slam_bridge.slam.hybrid_problem`), minimised by
Levenberg-Marquardt. Hybrids (``dpc``, ``mpc``): the hybrid window of eq. 3.4 with
``n_eff = max(0, min(n, l_eff - (l - n)))`` pose-graph cameras (the BA window keeps ``l - n``
cameras while fewer than ``l`` keyframes exist) *is* the k-BA, so the fusion and the next k-BA
minimise the same ``zeta`` and a fusion is not undone by the next keyframe. Three departures
from eq. 3.4 keep the hybrid SLAM as good as the plain one:

* the pose-graph cameras keep their observations of the BA window's points, thinned to a fixed
  share ``s`` of the points (by point id) and weighted ``1 / s`` (:func:`hybrid_problem`);
* links keep frozen references and information weights (:mod:`slam_bridge.slam.links`);
* a *consistency check*: a hybrid window whose optimum ``X*`` leaves more than
  ``consistency_share`` of its BA-window rows over ``consistency_px`` cannot fit its own
  observations (with 1 px noise a row exceeds 4 px with probability 0.03 %); that keyframe runs
  the plain k-BA instead (``WindowOutcome.fallback``) and the links of its window are re-taken
  when the hybrid resumes.

Points only the pose-graph cameras see leave the problem (eq. 3.4); after the fusion they are
carried along with their newest observer (:func:`carry_points`).

**Hessian memory** (fig. 3.7, :func:`hessian_bytes`), the same definition for every method: the
bytes of the blocks the assembled symmetric system of ``zeta`` stores, in float64,
``8 (36 Cf + 36 Q + 18 N_W + 9 Pf)`` with ``Cf`` free cameras, ``Q`` pairs of free cameras coupled
by a pose-graph term, ``N_W`` distinct (free camera, free point) pairs with an observation and
``Pf`` free points. The GPS term only adds to one camera block and the barrier's rank-1 term is
never formed (Sherman-Morrison), so neither changes the count.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from geoseg.errors import check_positive
from slam_bridge.ba.solvers.lm import LMConfig
from slam_bridge.errors import SlamError
from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.slam.hybrid_problem import (
    HybridWindowConfig,
    WindowError,
    build_hybrid_problem,
    minimize_zeta,
)
from slam_bridge.slam.links import LinkMemory
from slam_bridge.slam.map import Map

logger = logging.getLogger(__name__)

__all__ = [
    "METHODS",
    "WindowConfig",
    "WindowOutcome",
    "optimise_window",
    "carry_points",
    "hessian_bytes",
]

#: method name -> pose-graph kind of its hybrid window (None: the plain ``n = 0`` window)
METHODS: dict[str, str | None] = {"ba": None, "dpc": "dpc", "mpc": "mpc"}


@dataclass
class WindowConfig:
    """The k-BA window (module docstring; thesis §3.7: ``l = 40``, ``n = 30``).

    Attributes:
        l: optimised keyframes.
        n: pose-graph cameras of the hybrid methods (``ba`` always uses 0).
        history_keyframes: keyframes older than the window among which its points' fixed older
            observers are looked for.
        ba_iterations: Levenberg-Marquardt iterations of ``X* = argmin zeta``.
        pose_graph_share: share ``s`` of the points whose observations in the pose-graph
            keyframes stay in the window (MPC's 2D correspondences, eq. 3.18, and the rows tying
            the BA window's points to the pose-graph cameras), each weighted ``1 / s``. All of
            them make MPC slower than ``n = 0``; ``s = 0.25`` divides the Hessian memory by ~3
            without losing inliers.
        dpc_sigma_rot_rad: constant DPC weight ``A = I / sigma_rot^2`` (eq. 3.16) of links
            without an information weight. The thesis's ``D = I`` weighs a relative-pose error of
            1 m like one squared pixel, which lets the barrier bend the pose graph by metres.
        dpc_sigma_trans_m: constant DPC weight ``B = I / sigma_trans^2``.
        dpc_info_scale: factor on the information weights (:class:`LinkMemory`).
        dpc_min_sigma: ``(rad, m)`` floors of the information weights' standard deviations.
        mpc_sigma_px: pixel sigma of MPC's epipolar rows; the chain needs more weight than the
            measurement noise gives, or every later fusion bends it.
        mpc_length_sigma_m: sigma of MPC's baseline-length rows
            (:class:`slam_bridge.factors.baseline_length.BaselineLengthFactor`; None = the
            thesis's pure MPC, whose scale is then free).
        consistency_share: hybrids: the share of BA-window rows over ``consistency_px`` at
            ``X*`` above which the keyframe falls back to the plain k-BA (None: never).
        consistency_px: the pixel error of that test.
        consistency_iterations: LM iterations of the fallback's plain k-BA.
    """

    l: int = 40
    n: int = 30
    history_keyframes: int = 30
    ba_iterations: int = 10
    pose_graph_share: float = 0.25
    dpc_sigma_rot_rad: float = 1e-4
    dpc_sigma_trans_m: float = 1e-3
    dpc_info_scale: float = 10.0
    dpc_min_sigma: tuple[float, float] = (1e-6, 1e-5)
    mpc_sigma_px: float = 0.25
    mpc_length_sigma_m: float | None = 5e-3
    consistency_share: float | None = 0.01
    consistency_px: float = 4.0
    consistency_iterations: int = 50

    def __post_init__(self) -> None:
        if self.l < 3:
            raise SlamError(f"l: expected >= 3 (BA window of at least 3 cameras), got {self.l}")
        if not 0 <= self.n <= self.l - 3:
            raise SlamError(f"n: expected 0 <= n <= l - 3 = {self.l - 3}, got {self.n}")
        if self.history_keyframes < 0:
            raise SlamError(f"history_keyframes: expected >= 0, got {self.history_keyframes}")
        if self.ba_iterations < 1 or self.consistency_iterations < 1:
            raise SlamError("ba_iterations, consistency_iterations: expected >= 1")
        if not 0 < self.pose_graph_share <= 1:
            raise SlamError(f"pose_graph_share: expected in (0, 1], got {self.pose_graph_share}")
        for name in ("dpc_sigma_rot_rad", "dpc_sigma_trans_m", "dpc_info_scale", "mpc_sigma_px"):
            check_positive(name, getattr(self, name))
        if self.mpc_length_sigma_m is not None:
            check_positive("mpc_length_sigma_m", self.mpc_length_sigma_m)
        if self.consistency_share is not None and not 0 <= self.consistency_share < 1:
            raise SlamError(
                f"consistency_share: expected in [0, 1) or None, got {self.consistency_share}"
            )
        check_positive("consistency_px", self.consistency_px)

    def links(self) -> LinkMemory:
        """An empty :class:`LinkMemory` with this config's weights."""
        D = np.concatenate(
            [np.full(3, self.dpc_sigma_rot_rad**-2), np.full(3, self.dpc_sigma_trans_m**-2)]
        )
        return LinkMemory(D, self.dpc_info_scale, self.dpc_min_sigma)


@dataclass
class WindowOutcome:
    """The k-BA of one keyframe.

    Attributes:
        problem: the window at its optimum ``X*`` (a
            :class:`slam_bridge.slam.hybrid_problem.HybridProblem`).
        observations: ``(M_w,)`` map indices of the observations it was built from.
        window_observations: ``(M_a,)`` every active observation of the window's keyframes
            (the hybrid thins the pose-graph ones; the carried points and the gating use all).
        n_pose_graph: pose-graph cameras used (0: plain).
        pose_graph_ids: ``(n,)`` keyframe ids of the pose-graph cameras.
        R_ref: ``(n, 3, 3)`` their rotations before the k-BA (for :func:`carry_points`).
        t_ref: ``(n, 3)`` their optical centres before the k-BA.
        iterations: LM iterations spent.
        fallback: the hybrid window failed the consistency check and ran plain.
    """

    problem: object
    observations: np.ndarray
    window_observations: np.ndarray
    n_pose_graph: int
    pose_graph_ids: np.ndarray
    R_ref: np.ndarray
    t_ref: np.ndarray
    iterations: int
    fallback: bool = False


def window_n(method: str, cfg: WindowConfig, l_eff: int) -> int:
    """Pose-graph cameras of a window of ``l_eff`` keyframes for ``method``."""
    if METHODS[method] is None:
        return 0
    return max(0, min(cfg.n, l_eff - (cfg.l - cfg.n)))


def optimise_window(
    slam_map: Map,
    k: int,
    method: str,
    cfg: WindowConfig,
    links: LinkMemory,
    fixed_keyframes: np.ndarray,
    segment_start: int = 0,
    extra_terms=None,
) -> WindowOutcome:
    """``X* = argmin zeta`` of keyframe ``k``'s window (module docstring).

    Args:
        slam_map: the map (poses of keyframes ``<= k`` set, points triangulated).
        k: the newest keyframe.
        method: ``ba``, ``dpc`` or ``mpc``.
        cfg: window settings.
        links: the run's pose-graph links (updated).
        fixed_keyframes: keyframe ids held fixed (the gauge of the start-up).
        segment_start: first keyframe of ``k``'s segment (the window never reaches before it).
        extra_terms: ``problem -> list of factor families`` joining ``zeta`` beside the
            reprojection rows (the wheel odometry between keyframes), or None.

    Returns:
        A :class:`WindowOutcome`; the map is not modified.
    """
    kind = METHODS[method]
    first = max(segment_start, k + 1 - cfg.l - cfg.history_keyframes)
    keyframes = np.arange(first, k + 1)
    l_eff = min(cfg.l, k + 1 - segment_start)
    n_eff = window_n(method, cfg, l_eff)
    lo, hi = slam_map.starts[first], slam_map.starts[k + 1]
    ok = slam_map.obs_active[lo:hi] & slam_map.triangulated[slam_map.obs_point[lo:hi]]
    sel = lo + np.flatnonzero(ok)
    none = np.zeros(0, dtype=np.int64)
    if n_eff == 0:
        problem, lm = _plain_kba(
            slam_map, keyframes, sel, cfg.l, k, cfg.ba_iterations, fixed_keyframes, extra_terms
        )
        return WindowOutcome(
            problem, sel, sel, 0, none, np.zeros((0, 3, 3)), np.zeros((0, 3)), int(lm.iterations)
        )
    pg_ids = np.arange(k + 1 - l_eff, k + 1 - l_eff + n_eff)
    R_ref, t_ref = slam_map.R_wc[pg_ids].copy(), slam_map.t_wc[pg_ids].copy()
    sel_h, problem = hybrid_problem(slam_map, cfg, kind, links.D, keyframes, sel, l_eff, n_eff, k)
    problem.state.camera_fixed[np.isin(problem.camera_ids, fixed_keyframes)] = True
    links.freeze(problem)
    if kind == "mpc":
        links.add_length_terms(problem, cfg.mpc_length_sigma_m)
    if extra_terms is not None:
        problem.vision.extend(extra_terms(problem))
    if problem.state.free_cameras.size == 0:
        raise SlamError(f"keyframe {k}: the window has no free camera")
    problem, lm = minimize_zeta(problem, LMConfig(max_iterations=cfg.ba_iterations))
    iterations = int(lm.iterations)
    misfit = (
        bad_row_share(problem.vision[0], problem.state, cfg.consistency_px)
        if cfg.consistency_share is not None
        else 0.0
    )
    if cfg.consistency_share is not None and misfit > cfg.consistency_share:
        logger.warning(
            "keyframe %d: %s window inconsistent (%.1f %% of its BA-window rows over %.0f px "
            "at X*): plain k-BA (n = 0) for this keyframe, its links re-taken",
            k, method, 100 * misfit, cfg.consistency_px,
        )  # fmt: skip
        links.forget_from(int(pg_ids[0]))
        problem, lm = _plain_kba(
            slam_map, keyframes, sel, cfg.l, k, cfg.consistency_iterations, fixed_keyframes,
            extra_terms,
        )  # fmt: skip
        return WindowOutcome(
            problem, sel, sel, 0, none, np.zeros((0, 3, 3)), np.zeros((0, 3)),
            iterations + int(lm.iterations), fallback=True,
        )  # fmt: skip
    if kind == "dpc":
        links.remember_entry_information(problem)
    return WindowOutcome(problem, sel_h, sel, n_eff, pg_ids, R_ref, t_ref, iterations)


def _plain_kba(
    slam_map: Map,
    keyframes: np.ndarray,
    sel: np.ndarray,
    l: int,
    k: int,
    iterations: int,
    fixed_keyframes: np.ndarray,
    extra_terms=None,
):
    """The plain (``n = 0``) k-BA of the ``l`` latest keyframes over the observations ``sel``,
    minimised by ``iterations`` LM iterations, ``fixed_keyframes`` held fixed, with the
    families of ``extra_terms(problem)`` beside the reprojection rows.

    Returns:
        ``(problem at its optimum, the LM result)``.
    """
    m = slam_map
    kba = build_hybrid_problem(
        m.R_wc, m.t_wc, m.X_w, m.K, keyframes, m.obs_keyframe[sel], m.obs_point[sel],
        m.obs_uv[sel], HybridWindowConfig(l=l, n=0),
    )  # fmt: skip
    kba.state.camera_fixed[np.isin(kba.camera_ids, fixed_keyframes)] = True
    if kba.state.free_cameras.size == 0:
        raise SlamError(f"keyframe {k}: the window has no free camera")
    if extra_terms is not None:
        kba.vision.extend(extra_terms(kba))
    return minimize_zeta(kba, LMConfig(max_iterations=iterations))


def hybrid_problem(
    slam_map: Map,
    cfg: WindowConfig,
    kind: str,
    D: np.ndarray,
    keyframes: np.ndarray,
    sel: np.ndarray,
    l_eff: int,
    n_eff: int,
    k: int,
):
    """The hybrid window of keyframe ``k`` (eq. 3.4) over the observations ``sel``.

    The pose-graph keyframes' observations are thinned to the ``pose_graph_share`` ``s`` of the
    points (by a hash of the point id), keyframes left with fewer than 40 observations keeping
    them all; if the thinned window is invalid the full one is used. The kept rows' pixel sigma
    is multiplied by ``sqrt(s)``: each kept row stands for the ``1 / s`` it represents, so the
    chain and its tie to the BA window are about as stiff as with all of them.

    Returns:
        ``(observations used, problem)``.
    """
    m = slam_map
    kf_obs, pt_obs = m.obs_keyframe, m.obs_point
    sel_all = sel
    share = cfg.pose_graph_share
    thinned = share < 1.0
    if thinned:
        pg_end = k + 1 - (l_eff - n_eff)
        in_pg = kf_obs[sel] < pg_end
        h = (pt_obs[sel] * 2654435761) % 1000
        thin = in_pg & (h >= 1000 * share)
        left = np.bincount(kf_obs[sel][~thin], minlength=k + 1)
        thin &= left[kf_obs[sel]] >= 40
        sel = sel[~thin]
    wcfg = HybridWindowConfig(
        l=cfg.l,
        n=n_eff,
        pose_graph=kind,
        D=D,
        mpc_sigma=cfg.mpc_sigma_px * (np.sqrt(share) if thinned else 1.0),
        mpc_relative=True,
        pose_graph_rows=True,
        pose_graph_row_sigma=float(np.sqrt(share)) if thinned else None,
    )

    def build(rows: np.ndarray, window_cfg: HybridWindowConfig):
        return build_hybrid_problem(
            m.R_wc, m.t_wc, m.X_w, m.K, keyframes, kf_obs[rows], pt_obs[rows], m.obs_uv[rows],
            window_cfg,
        )  # fmt: skip

    try:
        problem = build(sel, wcfg)
    except WindowError:
        if sel_all is sel:
            raise
        logger.debug("keyframe %d: hybrid window without thinning", k)
        sel = sel_all
        problem = build(
            sel, dataclasses.replace(wcfg, mpc_sigma=cfg.mpc_sigma_px, pose_graph_row_sigma=None)
        )
    return sel, problem


def bad_row_share(rep, state, threshold_px: float) -> float:
    """Share of the rows of a reprojection family erring by more than ``threshold_px`` (or
    invalid) at ``state`` (residuals are pixels over ``rep.sigma``)."""
    r, ok = rep.residuals(state)
    err = np.linalg.norm(r, axis=1) * rep.sigma
    return float(np.mean(~ok | (err > threshold_px))) if r.shape[0] else 0.0


def carry_points(slam_map: Map, outcome: WindowOutcome) -> np.ndarray:
    """Move the points only the pose-graph cameras see along with their newest observer.

    The hybrid fusion moves the pose-graph cameras (from ``R_ref, t_ref``, their poses before
    the k-BA, to the fused ones now in the map) without the points that left the problem (eq.
    3.4): left in place they would contradict the fused cameras, and the next k-BA would pull
    the cameras back toward them, undoing the GPS correction. Each such point is carried
    rigidly by its newest pose-graph observer ``c``: ``X <- R_c R_ref_c^T (X - t_ref_c) + t_c``.
    Not in the thesis (which does not say what becomes of those points).

    Returns:
        ``(M,)`` ids of the points moved (``slam_map.X_w`` is updated in place).
    """
    m, o = slam_map, outcome.window_observations
    pg_ids = outcome.pose_graph_ids
    obs_points, obs_keyframes = m.obs_point[o], m.obs_keyframe[o]
    in_pg = np.isin(obs_keyframes, pg_ids) & ~np.isin(obs_points, outcome.problem.point_ids)
    if not np.any(in_pg):
        return np.zeros(0, dtype=np.int64)
    pts, kfs = obs_points[in_pg], obs_keyframes[in_pg]
    X_w = m.X_w
    newest = np.full(X_w.shape[0], -1, dtype=np.int64)
    np.maximum.at(newest, pts, kfs)
    moved = np.unique(pts)
    c = np.searchsorted(pg_ids, newest[moved])
    X_c = np.einsum("mba,mb->ma", outcome.R_ref[c], X_w[moved] - outcome.t_ref[c])
    X_w[moved] = np.einsum("mab,mb->ma", m.R_wc[pg_ids[c]], X_c) + m.t_wc[pg_ids[c]]
    return moved


def hessian_bytes(problem) -> int:
    """Memory of the assembled system of ``zeta`` (module docstring).

    Args:
        problem: a :class:`slam_bridge.slam.hybrid_problem.HybridProblem` (its state's fixed
            masks count).

    Returns:
        ``8 (36 Cf + 36 Q + 18 N_W + 9 Pf)`` bytes.
    """
    st = problem.state
    cmap, pmap = st.camera_index_map, st.point_index_map
    Cf, Pf = int(st.free_cameras.size), int(st.free_points.size)
    reps = [f for f in problem.vision if isinstance(f, ReprojectionFactor)]
    c = cmap[np.concatenate([f.cameras for f in reps])]
    p = pmap[np.concatenate([f.points for f in reps])]
    keep = (c >= 0) & (p >= 0)
    n_w = int(np.unique(c[keep] * max(Pf, 1) + p[keep]).size)
    q = 0
    if problem.window.pose_graph_pairs.shape[0]:
        idx = {int(k): i for i, k in enumerate(problem.camera_ids)}
        for a, b in problem.window.pose_graph_pairs:
            if cmap[idx[int(a)]] >= 0 and cmap[idx[int(b)]] >= 0:
                q += 1
    return 8 * (36 * Cf + 36 * q + 18 * n_w + 9 * Pf)
