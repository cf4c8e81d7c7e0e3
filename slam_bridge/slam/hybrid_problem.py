"""The hybrid keyframe window: BA window + pose-graph window (thesis §3.3, eq. 3.4).

The window holds the ``l`` most recent keyframes ``z_1..z_l`` (time order, ``z_l`` the newest)::

    ... z_0 | z_1 ... z_n | z_{n+1} ... z_l
     fixed   pose graph     BA window (l - n >= 3)

* **BA window** ``z_{n+1}..z_l``: keeps its reprojection errors; the points are those it
  observes (and only they).
* **Pose-graph window** ``z_1..z_n``: no points (their observations leave the problem); its
  cameras are tied by relative-pose terms ``xi`` between successive cameras (DPC, eq. 3.16, or
  MPC, eq. 3.18), for the pairs ``(z_i, z_{i+1})``, ``i = Id(C empty) .. n`` — that is including
  the link from ``z_n`` to the BA window and, when it exists, from the fixed keyframe ``z_0`` to
  ``z_1``. Option (``HybridWindowConfig.pose_graph_rows``, not in eq. 3.4): the pose-graph
  cameras keep their observations of the BA window's points, a family of their own when
  ``pose_graph_row_sigma`` is set.
* **Fixed cameras**: ``z_0`` (when ``n > 0`` and it exists) and the older keyframes that observe
  the BA window's points (their reprojection errors are kept with the camera held constant: the
  gauge of the k-BA, thesis §1.3.4). Eq. 3.4 sums reprojection errors over ``i = n+1..l`` only;
  keeping the constant terms of older observers changes nothing for ``n > 0`` in practice (a BA
  point is rarely seen ``n + 1`` keyframes earlier) and makes **``n = 0`` exactly the plain
  k-BA** of Lhuillier's barrier fusion (no pose-graph term at all for ``n = 0``: the z_0 link only
  exists to anchor a pose-graph window).

The vision error of the window is ``zeta = sum reprojection + sum xi`` (eq. 3.4), given to
:mod:`slam_bridge.ba.solvers.barrier` as the ``vision`` factor families.

MPC note: the epipolar residual is blind to the length of each baseline, so a chain of MPC
cameras has free directions (one scale per link, minus what the BA window closes); the barrier's
Levenberg-Marquardt damping and the GPS term take care of them, but the undamped Hessian of a
pure MPC window is singular (DPC's is not).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from geoseg.errors import check_finite, check_shape
from slam_bridge.ba.factor import Factor
from slam_bridge.ba.robust import RobustKernel
from slam_bridge.ba.solvers.lm import BAObjective, LMConfig, LMResult, levenberg_marquardt
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.factors.pose_graph_dpc import DPCFactor
from slam_bridge.factors.pose_graph_mpc import MPCDegenerateError, MPCFactor
from slam_bridge.factors.reprojection import ReprojectionFactor

logger = logging.getLogger(__name__)

__all__ = [
    "HybridWindowConfig",
    "HybridWindow",
    "HybridProblem",
    "WindowError",
    "hybrid_window",
    "build_hybrid_problem",
    "minimize_zeta",
]

POSE_GRAPH_KINDS = ("dpc", "mpc")


class WindowError(SlamError):
    """An invalid window: empty, too few BA cameras, inconsistent sizes."""


@dataclass
class HybridWindowConfig:
    """Window sizes and pose-graph term (defaults: thesis §3.7 uses ``l = 40``, ``n = 30``).

    Attributes:
        l: number of optimised keyframes.
        n: pose-graph window size (``0`` = plain barrier BA).
        pose_graph: ``"dpc"`` or ``"mpc"``.
        D: DPC weight ``diag(A, B)`` (``(6,)`` or ``(6, 6)``; identity if None).
        min_ba_cameras: ``l_b``, the fewest BA-window cameras (``>= 3``, §3.3).
        reprojection_sigma: pixel sigma of the reprojection rows.
        reprojection_kernel: robust kernel of the reprojection rows (None = least squares).
        reprojection_kernel_scale: its threshold in pixels (Huber's ``delta``, Geman-McClure's
            ``sigma``); each reprojection family gets it over its own pixel sigma, so the
            down-weighted rows are the same pixel errors in the BA window and in the thinned
            (re-weighted) pose-graph rows. None: the kernel's default in whitened units.
        mpc_sigma: pixel sigma of the MPC rows.
        mpc_min_correspondences: fewest 2D matches a pose-graph pair needs under MPC (pairs
            with fewer get a DPC link, :func:`_mpc_factor`).
        mpc_relative: subtract from each MPC epipolar distance its value at the built state
            (:meth:`MPCFactor.relative_to`), so that ``xi`` measures the change of the relative
            poses from the pre-fusion estimate, as DPC's ``S_hat`` does (§3.5). False = eq.
            3.18 as written: its minimiser fits the noisy pairwise epipolar geometry, not the
            multi-view one, and moves the pose graph along its weak (bas-relief) directions.
        min_point_observations: a BA-window point keeps its place only if at least this many of
            its observations remain (BA-window + fixed older cameras): a point whose other views
            all fell in the pose-graph window would have a free depth (singular ``V`` block).
            Eq. 3.4 is silent on it; 2 is the least that triangulates. Not applied for ``n = 0``
            (the plain k-BA keeps every point).
        pose_graph_rows: also keep the reprojection rows of the BA window's points in the
            pose-graph cameras (the junction: a point seen by ``z_{n+1}..z_l`` is often seen by
            ``z_n, z_{n-1}...`` too). Eq. 3.4 drops them; then only the pose-graph term ties the
            BA window's structure to the pose graph, the window's points lose those views for
            good when the window is the SLAM's k-BA, and the chain bends at the junction at no
            reprojection cost (measured on the 640 m run, sigma_b = 0, DPC, the window as the
            SLAM's k-BA: 0.93 m mean translation error without, 0.18 m with). The pose-graph
            cameras' other points still leave the problem; the Hessian gains the camera/point
            blocks of those rows (counted by :func:`slam_bridge.slam.windows.hessian_bytes`).
        pose_graph_row_sigma: pixel sigma of those rows, as a second reprojection family named
            ``reprojection_pose_graph`` (None: they join the BA window's family with
            ``reprojection_sigma``). A caller that keeps only a share ``s`` of them weighs each
            by ``1 / s`` with ``sigma sqrt(s)``.
    """

    l: int = 40
    n: int = 0
    pose_graph: str = "dpc"
    D: np.ndarray | None = None
    min_ba_cameras: int = 3
    reprojection_sigma: float = 1.0
    reprojection_kernel: str | RobustKernel | None = None
    reprojection_kernel_scale: float | None = None
    mpc_sigma: float = 1.0
    mpc_min_correspondences: int = 5
    mpc_relative: bool = False
    min_point_observations: int = 2
    pose_graph_rows: bool = False
    pose_graph_row_sigma: float | None = None

    def __post_init__(self) -> None:
        if self.pose_graph not in POSE_GRAPH_KINDS:
            raise WindowError(
                f"pose_graph: expected one of {POSE_GRAPH_KINDS}, got {self.pose_graph!r}"
            )
        if self.min_ba_cameras < 3:
            raise WindowError(
                f"min_ba_cameras: expected >= 3 (thesis l_b), got {self.min_ba_cameras}"
            )
        if self.l < 1:
            raise WindowError(f"l: expected >= 1, got {self.l}")
        if self.pose_graph_row_sigma is not None and not self.pose_graph_row_sigma > 0:
            raise WindowError(
                f"pose_graph_row_sigma: expected > 0 or None, got {self.pose_graph_row_sigma}"
            )
        if self.n < 0:
            raise WindowError(f"n: expected >= 0, got {self.n}")
        if self.l - self.n < self.min_ba_cameras:
            raise WindowError(
                f"l - n = {self.l} - {self.n} = {self.l - self.n}: the BA window needs at least "
                f"{self.min_ba_cameras} cameras (thesis §3.3, l - n >= l_b >= 3)"
            )


@dataclass
class HybridWindow:
    """Bookkeeping of one hybrid window (ids are keyframe/point ids of the caller).

    Attributes:
        keyframes: ``(l,)`` ``z_1..z_l`` in time order.
        pose_graph_cameras: ``(n,)`` ``z_1..z_n``.
        ba_cameras: ``(l - n,)`` ``z_{n+1}..z_l``.
        z0: id of the keyframe before ``z_1`` or ``None`` (``C`` empty).
        fixed_cameras: ``(F,)`` fixed cameras in time order (``z_0`` if linked, older observers).
        pose_graph_pairs: ``(Q, 2)`` ids ``(z_i, z_{i+1})`` of the pose-graph terms.
        points: ``(P,)`` ids of the points observed by the BA window.
        observations: ``(M,)`` indices of the input observations kept (reprojection rows).
    """

    keyframes: np.ndarray
    pose_graph_cameras: np.ndarray
    ba_cameras: np.ndarray
    z0: int | None
    fixed_cameras: np.ndarray
    pose_graph_pairs: np.ndarray
    points: np.ndarray
    observations: np.ndarray

    @property
    def n(self) -> int:
        """Pose-graph window size."""
        return int(self.pose_graph_cameras.size)

    @property
    def l(self) -> int:  # noqa: E743
        """Window size."""
        return int(self.keyframes.size)


def hybrid_window(
    keyframes: np.ndarray,
    obs_cameras: np.ndarray,
    obs_points: np.ndarray,
    l: int,
    n: int,
    *,
    min_ba_cameras: int = 3,
    min_point_observations: int = 1,
    pose_graph_rows: bool = False,
) -> HybridWindow:
    """Split the ``l`` latest keyframes into pose-graph and BA windows (module docstring).

    Args:
        keyframes: ``(K,)`` keyframe ids in time order (oldest first).
        obs_cameras: ``(M,)`` keyframe id of each observation.
        obs_points: ``(M,)`` point id of each observation.
        l: window size; clipped to the available keyframes (``l = min(l, K)``).
        n: pose-graph window size.
        min_ba_cameras: fewest BA-window cameras (``>= 3``).
        min_point_observations: for ``n > 0``, drop BA-window points with fewer kept
            observations (their other views fell in the pose-graph window).

    Returns:
        A :class:`HybridWindow`.

    Raises:
        WindowError: empty window, ``l - n < min_ba_cameras``, mismatched arrays.
    """
    keyframes = np.asarray(keyframes, dtype=np.int64).reshape(-1)
    obs_cameras = np.asarray(obs_cameras, dtype=np.int64).reshape(-1)
    obs_points = np.asarray(obs_points, dtype=np.int64).reshape(-1)
    if obs_cameras.shape != obs_points.shape:
        raise WindowError(
            f"obs_points: expected shape {obs_cameras.shape} like obs_cameras, got {obs_points.shape}"
        )
    if keyframes.size == 0:
        raise WindowError("keyframes: the window is empty (no keyframe)")
    if np.unique(keyframes).size != keyframes.size:
        raise WindowError("keyframes: duplicate keyframe ids")
    if min_ba_cameras < 3:
        raise WindowError(f"min_ba_cameras: expected >= 3, got {min_ba_cameras}")
    l_eff = min(int(l), keyframes.size)
    if n < 0 or l_eff - n < min_ba_cameras:
        raise WindowError(
            f"BA window of l - n = {l_eff} - {n} = {l_eff - n} cameras: at least "
            f"{min_ba_cameras} needed (thesis §3.3)"
        )
    window = keyframes[-l_eff:]
    older = keyframes[: keyframes.size - l_eff]
    z0 = int(older[-1]) if older.size else None
    pg = window[:n]
    ba = window[n:]
    in_ba = np.isin(obs_cameras, ba)
    points = np.unique(obs_points[in_ba])
    if points.size == 0:
        raise WindowError("the BA window observes no point")
    sees = np.isin(obs_points, points)
    obs_older = sees & np.isin(obs_cameras, older)
    if n > 0 and min_point_observations > 1:  # n = 0 keeps the plain k-BA's points untouched
        kept = sees & (in_ba | obs_older)
        counts = np.bincount(obs_points[kept], minlength=int(obs_points.max()) + 1)
        points = points[counts[points] >= min_point_observations]
        if points.size == 0:
            raise WindowError(f"no BA-window point keeps {min_point_observations} observations")
        sees = np.isin(obs_points, points)
        obs_older = sees & np.isin(obs_cameras, older)
    observers = set(np.unique(obs_cameras[obs_older]).tolist())
    if n > 0 and z0 is not None:
        observers.add(z0)
    rank = {int(c): i for i, c in enumerate(keyframes)}
    fixed = np.array(sorted(observers, key=lambda c: rank[c]), dtype=np.int64)
    kept_rows = in_ba | obs_older
    if pose_graph_rows:
        kept_rows |= np.isin(obs_cameras, pg)
    observations = np.flatnonzero(sees & kept_rows)
    if n > 0:
        chain = ([z0] if z0 is not None else []) + window[: n + 1].tolist()
        pairs = np.array(list(zip(chain[:-1], chain[1:])), dtype=np.int64).reshape(-1, 2)
    else:
        pairs = np.zeros((0, 2), dtype=np.int64)
    return HybridWindow(
        keyframes=window.copy(),
        pose_graph_cameras=pg.copy(),
        ba_cameras=ba.copy(),
        z0=z0,
        fixed_cameras=fixed,
        pose_graph_pairs=pairs,
        points=points,
        observations=observations,
    )


@dataclass
class HybridProblem:
    """A hybrid window turned into a bundle-adjustment problem.

    Attributes:
        window: the bookkeeping.
        state: cameras = fixed cameras then ``z_1..z_l`` (time order); points = window points.
        camera_ids: ``(C,)`` keyframe id of each state camera.
        point_ids: ``(P,)`` point id of each state point.
        vision: the factor families of ``zeta`` (eq. 3.4): reprojection, then DPC or MPC.
        latest_camera: state index of ``z_l``.
        dropped_points: ``(D,)`` ids of points removed because they are behind every camera
            observing them (logged as a warning).
    """

    window: HybridWindow
    state: BAState
    camera_ids: np.ndarray
    point_ids: np.ndarray
    vision: list[Factor] = field(default_factory=list)
    latest_camera: int = -1
    dropped_points: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def write_back(
        self, state: BAState, R_wc: np.ndarray, t_wc: np.ndarray, X_w: np.ndarray
    ) -> None:
        """Copy the free cameras and points of ``state`` into the global arrays (in place).

        Args:
            state: a state of this problem (e.g. ``BarrierResult.state``).
            R_wc: ``(N, 3, 3)`` all keyframe rotations, indexed by keyframe id.
            t_wc: ``(N, 3)`` all optical centres.
            X_w: ``(Np, 3)`` all points, indexed by point id.
        """
        if state.num_cameras != self.camera_ids.size or state.num_points != self.point_ids.size:
            raise WindowError("write_back: the state does not belong to this problem")
        free = state.free_cameras
        R_wc[self.camera_ids[free]] = state.R_wc[free]
        t_wc[self.camera_ids[free]] = state.t_wc[free]
        fp = state.free_points
        X_w[self.point_ids[fp]] = state.X_w[fp]

    def camera_index(self, keyframe_id: int) -> int:
        """State index of a keyframe id."""
        hit = np.flatnonzero(self.camera_ids == keyframe_id)
        if hit.size == 0:
            raise WindowError(f"keyframe {keyframe_id} is not in the problem")
        return int(hit[0])


def build_hybrid_problem(
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    K: np.ndarray,
    keyframes: np.ndarray,
    obs_cameras: np.ndarray,
    obs_points: np.ndarray,
    uv: np.ndarray,
    config: HybridWindowConfig | None = None,
) -> HybridProblem:
    """Build the state and the vision factors of the hybrid window (eq. 3.4).

    The DPC reference ``S_hat`` (eq. 3.14) is taken from the given poses, which must therefore
    be the pre-fusion estimate ``X*``. MPC correspondences between ``z_i`` and ``z_{i+1}`` are
    the points both observe (any point, not only the BA window's).

    Args:
        R_wc: ``(N, 3, 3)`` rotations of all keyframes, indexed by keyframe id.
        t_wc: ``(N, 3)`` optical centres, indexed by keyframe id.
        X_w: ``(Np, 3)`` all points, indexed by point id.
        K: ``(3, 3)`` or ``(N, 3, 3)`` calibration (indexed by keyframe id).
        keyframes: ``(Kf,)`` keyframe ids in time order.
        obs_cameras: ``(M,)`` keyframe id of each observation.
        obs_points: ``(M,)`` point id of each observation.
        uv: ``(M, 2)`` observed pixels.
        config: window sizes and terms.

    Returns:
        A :class:`HybridProblem`.

    Points behind every camera observing them are dropped with a warning
    (``HybridProblem.dropped_points``); a window where all points are is an error.

    Raises:
        WindowError: invalid window; also, for MPC, coincident optical centres (a pair with
            fewer than ``mpc_min_correspondences`` matches gets a DPC link instead).
        GeosegError: NaN/inf inputs or mismatched shapes.
    """
    cfg = config or HybridWindowConfig()
    R_wc = np.asarray(R_wc, dtype=np.float64)
    t_wc = np.asarray(t_wc, dtype=np.float64)
    X_w = np.asarray(X_w, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    check_shape("R_wc", R_wc, (None, 3, 3))
    check_shape("t_wc", t_wc, (R_wc.shape[0], 3))
    check_shape("X_w", X_w, (None, 3))
    obs_cameras = np.asarray(obs_cameras, dtype=np.int64).reshape(-1)
    obs_points = np.asarray(obs_points, dtype=np.int64).reshape(-1)
    check_shape("uv", uv, (obs_cameras.size, 2))
    check_finite("uv", uv)
    win = hybrid_window(
        keyframes,
        obs_cameras,
        obs_points,
        cfg.l,
        cfg.n,
        min_ba_cameras=cfg.min_ba_cameras,
        min_point_observations=cfg.min_point_observations,
        pose_graph_rows=cfg.pose_graph_rows,
    )
    camera_ids = np.concatenate([win.fixed_cameras, win.keyframes])
    for name, arr in (("R_wc", R_wc[camera_ids]), ("t_wc", t_wc[camera_ids])):
        check_finite(name, arr)
    check_finite("X_w", X_w[win.points])
    win, dropped = _drop_points_behind(win, R_wc, t_wc, X_w, obs_cameras, obs_points)
    fixed = np.zeros(camera_ids.size, dtype=bool)
    fixed[: win.fixed_cameras.size] = True
    state = BAState(R_wc[camera_ids], t_wc[camera_ids], X_w[win.points], camera_fixed=fixed)
    cam_of = {int(c): i for i, c in enumerate(camera_ids)}
    pt_of = np.full(int(max(obs_points.max(initial=0), win.points.max()) + 1), -1, dtype=np.int64)
    pt_of[win.points] = np.arange(win.points.size)
    K = np.asarray(K, dtype=np.float64)
    K_state = K if K.ndim == 2 else K[camera_ids]
    o = win.observations
    vision = _reprojection_factors(cfg, win, K_state, cam_of, pt_of, obs_cameras, obs_points, uv)
    if win.pose_graph_pairs.shape[0]:
        vision += _pose_graph_factors(cfg, win, state, K_state, cam_of, obs_cameras, obs_points, uv)
    logger.debug(
        "hybrid window: l=%d n=%d, %d fixed cameras, %d points, %d observations, %d pg pairs",
        win.l,
        win.n,
        win.fixed_cameras.size,
        win.points.size,
        o.size,
        win.pose_graph_pairs.shape[0],
    )
    return HybridProblem(
        window=win,
        state=state,
        camera_ids=camera_ids,
        point_ids=win.points.copy(),
        vision=vision,
        latest_camera=camera_ids.size - 1,
        dropped_points=dropped,
    )


def _reprojection_factors(
    cfg: HybridWindowConfig,
    win: HybridWindow,
    K_state: np.ndarray,
    cam_of: dict[int, int],
    pt_of: np.ndarray,
    obs_cameras: np.ndarray,
    obs_points: np.ndarray,
    uv: np.ndarray,
) -> list[Factor]:
    """The window's reprojection rows, the pose-graph cameras' apart when they have their own
    sigma (``pose_graph_row_sigma``)."""
    o = win.observations
    junction = np.isin(obs_cameras[o], win.pose_graph_cameras)
    if cfg.pose_graph_row_sigma is None or not np.any(junction):
        families = [(o, cfg.reprojection_sigma, "reprojection")]
    else:  # the pose-graph cameras' rows as their own family, with their own sigma
        families = [
            (o[~junction], cfg.reprojection_sigma, "reprojection"),
            (o[junction], cfg.pose_graph_row_sigma, "reprojection_pose_graph"),
        ]
    return [
        ReprojectionFactor(
            K_state,
            np.array([cam_of[int(c)] for c in obs_cameras[rows]], dtype=np.int64),
            pt_of[obs_points[rows]],
            uv[rows],
            sigma=sigma,
            kernel=cfg.reprojection_kernel,
            kernel_scale=(
                None
                if cfg.reprojection_kernel_scale is None
                else cfg.reprojection_kernel_scale / sigma
            ),
            name=name,
        )
        for rows, sigma, name in families
    ]


def _pose_graph_factors(
    cfg: HybridWindowConfig,
    win: HybridWindow,
    state: BAState,
    K_state: np.ndarray,
    cam_of: dict[int, int],
    obs_cameras: np.ndarray,
    obs_points: np.ndarray,
    uv: np.ndarray,
) -> list[Factor]:
    """The pose-graph terms of the window's successive pairs: DPC, or MPC with a DPC link for
    the pairs with too few shared points.

    Raises:
        WindowError: two successive keyframes share one optical centre.
    """
    out: list[Factor] = []
    pairs_state = np.array(
        [[cam_of[int(a)], cam_of[int(b)]] for a, b in win.pose_graph_pairs], dtype=np.int64
    )
    if np.any(
        np.linalg.norm(state.t_wc[pairs_state[:, 1]] - state.t_wc[pairs_state[:, 0]], axis=1) < 1e-9
    ):
        raise WindowError(
            "pose-graph window: two successive keyframes share one optical centre (all "
            "cameras at one position?)"
        )
    if cfg.pose_graph == "dpc":
        out.append(DPCFactor.from_state(state, pairs_state, D=cfg.D))
    else:
        mpc, fallback = _mpc_factor(
            win, pairs_state, K_state, obs_cameras, obs_points, uv, cfg, state
        )
        if mpc is not None:
            out.append(mpc)
        if fallback.shape[0]:  # documented departure: DPC link where MPC has too few matches
            logger.info(
                "MPC: %d pose-graph pair(s) with fewer than %d shared points use a DPC link",
                fallback.shape[0],
                cfg.mpc_min_correspondences,
            )
            out.append(DPCFactor.from_state(state, fallback, D=cfg.D))
    return out


def _drop_points_behind(
    win: HybridWindow,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    obs_cameras: np.ndarray,
    obs_points: np.ndarray,
    eps: float = 1e-6,
) -> tuple[HybridWindow, np.ndarray]:
    """Remove the points that lie behind every camera observing them (documented behaviour).

    Such a point has no valid reprojection row: its ``V`` block would be zero and its position
    undetermined. It is dropped from the window with a warning instead of poisoning the solve.
    """
    o = win.observations
    X_c = np.einsum("mba,mb->ma", R_wc[obs_cameras[o]], X_w[obs_points[o]] - t_wc[obs_cameras[o]])
    front = X_c[:, 2] > eps
    good = np.unique(obs_points[o][front])
    bad = np.setdiff1d(win.points, good)
    if bad.size == 0:
        return win, np.zeros(0, dtype=np.int64)
    if bad.size == win.points.size:
        raise WindowError("every point of the BA window is behind the cameras observing it")
    logger.warning(
        "hybrid window: dropping %d point(s) behind every camera observing them (ids %s)",
        bad.size,
        bad[:10].tolist(),
    )
    keep = ~np.isin(obs_points[o], bad)
    win = HybridWindow(
        keyframes=win.keyframes,
        pose_graph_cameras=win.pose_graph_cameras,
        ba_cameras=win.ba_cameras,
        z0=win.z0,
        fixed_cameras=win.fixed_cameras,
        pose_graph_pairs=win.pose_graph_pairs,
        points=np.setdiff1d(win.points, bad),
        observations=o[keep],
    )
    return win, bad


def _mpc_factor(
    win: HybridWindow,
    pairs_state: np.ndarray,
    K_state: np.ndarray,
    obs_cameras: np.ndarray,
    obs_points: np.ndarray,
    uv: np.ndarray,
    cfg: HybridWindowConfig,
    state: BAState,
) -> tuple[MPCFactor | None, np.ndarray]:
    """2D correspondences of each pose-graph pair from shared point observations.

    A pair sharing fewer than ``cfg.mpc_min_correspondences`` points (eq. 3.18 needs at least
    5 to pin a relative pose up to scale; the thesis does not say what happens below) is not
    an error: it is returned in the fallback list, and :func:`build_hybrid_problem` links it
    with a DPC term (eq. 3.16) instead, so the chain never breaks.

    Returns:
        ``(MPC factor over the other pairs or None, (F, 2) fallback state pairs)``.
    """
    ci, cj, ui, uj = [], [], [], []
    fallback = []
    for (a, b), (sa, sb) in zip(win.pose_graph_pairs, pairs_state):
        ia = np.flatnonzero(obs_cameras == a)
        ib = np.flatnonzero(obs_cameras == b)
        common, xa, xb = np.intersect1d(obs_points[ia], obs_points[ib], return_indices=True)
        if common.size < cfg.mpc_min_correspondences:
            fallback.append((int(sa), int(sb)))
            continue
        ci.append(np.full(common.size, sa))
        cj.append(np.full(common.size, sb))
        ui.append(uv[ia[xa]])
        uj.append(uv[ib[xb]])
    fallback = np.array(fallback, dtype=np.int64).reshape(-1, 2)
    if not ci:
        return None, fallback
    f = MPCFactor(
        K_state,
        np.concatenate(ci),
        np.concatenate(cj),
        np.concatenate(ui),
        np.concatenate(uj),
        sigma=cfg.mpc_sigma,
    )
    try:
        f.cost(state)
    except MPCDegenerateError as exc:
        raise WindowError(f"MPC: {exc}") from exc
    if cfg.mpc_relative:
        f = f.relative_to(state)
    return f, fallback


def minimize_zeta(
    problem: HybridProblem, config: LMConfig | None = None
) -> tuple[HybridProblem, LMResult]:
    """``X* = argmin zeta`` of the hybrid window (eq. 3.4), the barrier's starting point.

    Dropping the pose-graph observations changes zeta, so the k-BA's output is not exactly its
    minimiser; this runs the core's Levenberg-Marquardt on the window's vision families. The DPC
    reference ``S_hat`` stays the one the problem was built with (the k-BA's relative poses).

    Args:
        problem: the window.
        config: LM settings.

    Returns:
        ``(problem at X*, the LM result)``; the input problem is not modified.
    """
    res = levenberg_marquardt(BAObjective(problem.vision), problem.state, config)
    out = HybridProblem(
        window=problem.window,
        state=res.state,
        camera_ids=problem.camera_ids,
        point_ids=problem.point_ids,
        vision=problem.vision,
        latest_camera=problem.latest_camera,
        dropped_points=problem.dropped_points,
    )
    return out, res
