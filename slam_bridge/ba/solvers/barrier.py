"""Barrier-term fusion (Lhuillier; thesis eq. 2.3, appendix B), solved with Sherman-Morrison.

Minimises ``f(X) = gamma / (t - zeta(X)) + sum_i C_i(X)`` from ``X*``, the minimiser of the
vision error ``zeta`` (the caller runs the unconstrained k-BA first), with ``t = t_ratio *
zeta(X*)`` (``t_ratio`` 1.05; a floor ``min_slack`` when ``zeta(X*)`` is 0) and ``gamma`` scaled
to the constraint cost by default (``gamma_rel``). Each Newton step is the rank-1 update of a
sparse BA system, solved with one Schur factorisation (:mod:`slam_bridge.ba.solvers.schur`) and
Sherman-Morrison; Levenberg-Marquardt damping refuses infeasible or worse steps, and an
infeasible trial is first retried halved (``max_backtracks``). The derivation, the step rules and
the reasons for them: ``docs/solvers.md`` ("Barrier-term fusion").
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from geoseg.errors import check_positive
from slam_bridge.ba.factor import Factor
from slam_bridge.ba.normal_equations import NormalEquations, assemble
from slam_bridge.ba.solvers.schur import DAMPING_MODES, SchurFactorization
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = [
    "BarrierConfig",
    "BarrierIteration",
    "BarrierResult",
    "BarrierSolver",
    "BarrierSystem",
    "barrier_objective",
    "barrier_system",
    "combine_normal_equations",
    "sherman_morrison_solve",
    "solve_barrier",
    "vision_cost",
]


# ------------------------------------------------------------------------------------ config
@dataclass
class BarrierConfig:
    """Parameters of the barrier fusion (defaults next to the code, docs/architecture.md).

    Attributes:
        t_ratio: ``t = t_ratio * zeta(X*)`` (1.05 in the thesis, following Lhuillier).
        gamma: absolute barrier weight; ``None`` -> ``gamma_rel * (t - zeta*) * C(X*)``.
        gamma_rel: relative barrier weight used when ``gamma`` is None.
        min_slack_per_residual: floor of ``t - zeta*`` per scalar vision residual
            (``zeta* = 0``; a reprojection row counts 2).
        max_iterations: outer iterations (accepted or not).
        initial_lambda: starting LM damping.
        lambda_up: factor applied to lambda after a rejected step.
        lambda_down: factor applied after an accepted step.
        max_lambda: stop when lambda exceeds it (no feasible decrease found).
        max_backtracks: when a trial step crosses the barrier (``zeta >= t``), try it halved up
            to this many times (same direction, no new factorisation) before rejecting it and
            raising ``lambda``; a shortened step that is accepted keeps ``lambda`` (module
            docstring). 0: the thesis's Levenberg-Marquardt alone.
        damping_mode: ``"additive"`` or ``"marquardt"`` (see :mod:`slam_bridge.ba.solvers.schur`).
        rel_tol: stop when an accepted step lowers ``f`` by less than ``rel_tol * |f|``.
        grad_tol: stop when ``max |grad f / 2| < grad_tol``.
    """

    t_ratio: float = 1.05
    gamma: float | None = None
    gamma_rel: float = 0.01
    min_slack_per_residual: float = 1e-4
    max_iterations: int = 30
    initial_lambda: float = 1e-4
    lambda_up: float = 10.0
    lambda_down: float = 0.1
    max_lambda: float = 1e12
    max_backtracks: int = 3
    damping_mode: str = "marquardt"
    rel_tol: float = 1e-6
    grad_tol: float = 1e-12

    def __post_init__(self) -> None:
        if not np.isfinite(self.t_ratio) or self.t_ratio <= 1.0:
            raise SlamError(f"t_ratio: expected a finite number > 1, got {self.t_ratio}")
        if self.gamma is not None:
            check_positive("gamma", self.gamma)
        check_positive("gamma_rel", self.gamma_rel)
        check_positive("min_slack_per_residual", self.min_slack_per_residual)
        check_positive("initial_lambda", self.initial_lambda)
        if self.lambda_up <= 1.0 or not 0.0 < self.lambda_down < 1.0:
            raise SlamError("lambda_up must be > 1 and lambda_down in (0, 1)")
        if self.damping_mode not in DAMPING_MODES:
            raise SlamError(f"damping_mode: expected one of {DAMPING_MODES}")
        if self.max_iterations < 0:
            raise SlamError("max_iterations: expected >= 0")
        if self.max_backtracks < 0:
            raise SlamError(f"max_backtracks: expected >= 0, got {self.max_backtracks}")


@dataclass
class BarrierIteration:
    """One trial step of the barrier LM.

    Attributes:
        iteration: outer iteration index.
        objective: ``f`` at the current (accepted) state before the trial.
        zeta: ``zeta`` at the current state.
        constraint_cost: ``sum C_i`` at the current state.
        lam: damping used for the trial.
        trial_zeta: ``zeta`` at the trial state (``inf`` if not evaluated).
        trial_objective: ``f`` at the trial state (``inf`` if infeasible).
        accepted: whether the trial became the current state.
        reason: ``"accepted"``, ``"infeasible"`` (``zeta >= t``), ``"no_decrease"``,
            ``"invalid_rows"``, ``"non_finite"`` or ``"singular"``.
        step_norm: ``||dX||`` (of the shortened step, see ``step_scale``).
        seconds: wall time of the trial (assembly excluded; a shortened step's trial is only
            its evaluation).
        step_scale: ``1`` for the damped step, ``2^-k`` for its ``k``-th shortening after an
            infeasible trial (:attr:`BarrierConfig.max_backtracks`).
    """

    iteration: int
    objective: float
    zeta: float
    constraint_cost: float
    lam: float
    trial_zeta: float
    trial_objective: float
    accepted: bool
    reason: str
    step_norm: float
    seconds: float
    step_scale: float = 1.0


@dataclass
class BarrierResult:
    """Outcome of :func:`solve_barrier`.

    Attributes:
        state: the fused state (always feasible: ``zeta < t``).
        zeta_star: ``zeta(X*)``.
        t: the barrier threshold.
        gamma: the barrier weight used.
        zeta: final ``zeta``.
        constraint_cost: final ``sum C_i``.
        objective: final ``f``.
        iterations: outer iterations run.
        converged: a stopping test was met (vs. the iteration cap).
        stop_reason: why it stopped.
        history: every trial step.
        seconds_per_iteration: mean wall time of an outer iteration (assembly + solves).
    """

    state: BAState
    zeta_star: float
    t: float
    gamma: float
    zeta: float
    constraint_cost: float
    objective: float
    iterations: int
    converged: bool
    stop_reason: str
    history: list[BarrierIteration] = field(default_factory=list)
    seconds_per_iteration: float = 0.0


# ------------------------------------------------------------------------------- primitives
def vision_cost(factors: Sequence[Factor], state: BAState) -> tuple[float, int]:
    """``zeta(state)`` and the number of invalid rows of the vision families.

    Args:
        factors: the vision families.
        state: where to evaluate.

    Returns:
        ``(zeta, n_invalid)``.
    """
    zeta = 0.0
    n_invalid = 0
    for f in factors:
        fast = getattr(f, "cost_and_invalid", None)  # no Jacobians when the family offers it
        if fast is not None:
            c, n = fast(state)
        else:
            blk = f.evaluate(state)
            c, n = blk.cost(), blk.n_invalid
        zeta += c
        n_invalid += n
    return float(zeta), int(n_invalid)


def _residual_count(factor: Factor, state: BAState) -> int:
    """Scalar residuals of a family: its ``num_residuals`` when it has one (no evaluation: the
    count is needed once per fusion, and an evaluation with Jacobians costs as much as a barrier
    iteration's assembly), else the size of its evaluated rows."""
    n = getattr(factor, "num_residuals", None)
    return int(n) if n is not None else int(factor.evaluate(state).residuals.size)


def barrier_objective(
    vision: Sequence[Factor],
    constraints: Sequence[Factor],
    state: BAState,
    t: float,
    gamma: float,
) -> float:
    """``f = gamma / (t - zeta) + sum C_i`` (eq. 2.3); ``inf`` where ``zeta >= t``."""
    zeta, _ = vision_cost(vision, state)
    if not np.isfinite(zeta) or zeta >= t:
        return float("inf")
    return gamma / (t - zeta) + float(sum(c.cost(state) for c in constraints))


def combine_normal_equations(
    ne_v: NormalEquations, alpha: float, ne_c: NormalEquations
) -> NormalEquations:
    """``alpha * ne_v + ne_c`` blockwise (same free cameras/points).

    Args:
        ne_v: vision normal equations.
        alpha: weight of the vision part (``gamma / s^2``).
        ne_c: constraint normal equations.

    Returns:
        The combined :class:`NormalEquations` (``cost`` = ``alpha * cost_v + cost_c``, for
        information only).
    """
    if ne_v.U.shape != ne_c.U.shape or ne_v.V.shape != ne_c.V.shape:
        raise SlamError("combine_normal_equations: the two systems have different free sets")
    Cf = ne_v.num_free_cameras
    keys = np.concatenate([ne_v.pairs, ne_c.pairs])
    blocks = np.concatenate([alpha * ne_v.U_pairs, ne_c.U_pairs])
    if not ne_c.pairs.shape[0]:  # e.g. GPS only: ne_v's pairs are already unique (assemble)
        pairs, U_pairs = ne_v.pairs, blocks
    elif keys.shape[0]:
        uniq, inv = np.unique(keys[:, 0] * max(Cf, 1) + keys[:, 1], return_inverse=True)
        U_pairs = np.zeros((uniq.size, 6, 6))
        np.add.at(U_pairs, inv.reshape(-1), blocks)
        pairs = np.stack([uniq // max(Cf, 1), uniq % max(Cf, 1)], axis=1).astype(np.int64)
    else:
        pairs, U_pairs = np.zeros((0, 2), dtype=np.int64), np.zeros((0, 6, 6))
    costs = {k: alpha * v for k, v in ne_v.costs.items()}
    for k, v in ne_c.costs.items():
        costs[k] = costs.get(k, 0.0) + v
    if ne_c.W.shape[0]:
        W = np.concatenate([alpha * ne_v.W, ne_c.W])
        W_cameras = np.concatenate([ne_v.W_cameras, ne_c.W_cameras])
        W_points = np.concatenate([ne_v.W_points, ne_c.W_points])
    else:  # camera-only constraints (GPS, DEM, odometry): no copy of the index arrays
        W, W_cameras, W_points = alpha * ne_v.W, ne_v.W_cameras, ne_v.W_points
    return NormalEquations(
        U=alpha * ne_v.U + ne_c.U,
        pairs=pairs,
        U_pairs=U_pairs,
        W=W,
        W_cameras=W_cameras,
        W_points=W_points,
        V=alpha * ne_v.V + ne_c.V,
        g_c=alpha * ne_v.g_c + ne_c.g_c,
        g_p=alpha * ne_v.g_p + ne_c.g_p,
        cost=alpha * ne_v.cost + ne_c.cost,
        n_invalid=ne_v.n_invalid + ne_c.n_invalid,
        costs=costs,
    )


@dataclass
class BarrierSystem:
    """The Newton system of ``f / 2`` at one state (see the module docstring).

    Attributes:
        H_tilde: sparse part ``gamma/s^2 H_v + H_c`` (undamped), as block normal equations whose
            ``g_c``/``g_p`` hold ``g_f`` (half the gradient of ``f``).
        u_c: ``(Cf, 6)`` camera part of the rank-1 vector ``u``.
        u_p: ``(Pf, 3)`` point part of ``u``.
        zeta: ``zeta`` at the state.
        constraint_cost: ``sum C_i``.
        objective: ``f``.
        n_invalid_vision: invalid vision rows at the state (as counted by the families' costs;
            :meth:`BarrierSolver.run` keeps it current).
    """

    H_tilde: NormalEquations
    u_c: np.ndarray
    u_p: np.ndarray
    zeta: float
    constraint_cost: float
    objective: float
    n_invalid_vision: int


def barrier_system(
    vision: Sequence[Factor],
    constraints: Sequence[Factor],
    state: BAState,
    t: float,
    gamma: float,
) -> BarrierSystem:
    """Assemble ``H~``, ``g_f`` and ``u`` (eqs. B.3-B.6, B.14) at ``state``.

    Raises:
        SlamError: ``zeta(state) >= t`` (outside the barrier's domain).
    """
    ne_v = assemble(vision, state)
    ne_c = assemble(constraints, state)
    zeta = ne_v.cost
    s = t - zeta
    if not s > 0.0:
        raise SlamError(f"barrier_system: zeta = {zeta:.6g} >= t = {t:.6g}, outside the barrier")
    alpha = gamma / s**2
    beta = 2.0 * np.sqrt(gamma / s**3)
    H = combine_normal_equations(ne_v, alpha, ne_c)
    return BarrierSystem(
        H_tilde=H,
        u_c=beta * ne_v.g_c,
        u_p=beta * ne_v.g_p,
        zeta=zeta,
        constraint_cost=ne_c.cost,
        objective=gamma / s + ne_c.cost,
        n_invalid_vision=ne_v.n_invalid,
    )


def sherman_morrison_solve(
    factorization: SchurFactorization,
    rhs_c: np.ndarray,
    rhs_p: np.ndarray,
    u_c: np.ndarray,
    u_p: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``(H~ + u u^T) x = rhs`` with two solves of one factorisation (eqs. B.15-B.17).

    Args:
        factorization: factorised ``H~`` (damped as wanted).
        rhs_c: ``(Cf, 6)`` camera right-hand side (``-g_f`` for the barrier step).
        rhs_p: ``(Pf, 3)`` point right-hand side.
        u_c: ``(Cf, 6)`` camera part of ``u``.
        u_p: ``(Pf, 3)`` point part of ``u``.

    Returns:
        ``x_c (Cf, 6)``, ``x_p (Pf, 3)``.
    """
    a_c, a_p = factorization.solve(rhs_c, rhs_p)  # H~ a = rhs   (B.16)
    b_c, b_p = factorization.solve(u_c, u_p)  # H~ b = u     (B.17)
    ua = float(np.sum(u_c * a_c) + np.sum(u_p * a_p))
    ub = float(np.sum(u_c * b_c) + np.sum(u_p * b_p))
    k = ua / (1.0 + ub)  # 1 + u^T H~^-1 u >= 1 for SPD H~
    return a_c - k * b_c, a_p - k * b_p


# ----------------------------------------------------------------------------------- solver
class BarrierSolver:
    """Levenberg-Marquardt on the barrier objective (module docstring).

    Args:
        vision: the families whose summed cost is ``zeta``.
        constraints: the families ``C_i``.
        config: parameters.

    Subclasses may override :meth:`propose_step` (tests plant infeasible steps through it); the
    acceptance test in :meth:`run` is the only place a step is accepted.
    """

    def __init__(
        self,
        vision: Sequence[Factor],
        constraints: Sequence[Factor],
        config: BarrierConfig | None = None,
    ) -> None:
        self.vision = list(vision)
        self.constraints = list(constraints)
        if not self.vision:
            raise SlamError("vision: the barrier needs at least one vision factor family")
        self.config = config or BarrierConfig()

    def threshold(self, state_star: BAState) -> tuple[float, float, int]:
        """``(zeta*, t, n_invalid*)`` at the unconstrained optimum.

        Raises:
            SlamError: non-finite ``zeta*``.
        """
        cfg = self.config
        zeta_star, n_invalid = vision_cost(self.vision, state_star)
        if not np.isfinite(zeta_star):
            raise SlamError("zeta(X*) is not finite: check the observations (NaN/inf)")
        n_res = sum(_residual_count(f, state_star) for f in self.vision)
        min_slack = cfg.min_slack_per_residual * max(n_res, 1)
        t = cfg.t_ratio * zeta_star
        if t - zeta_star < min_slack:
            logger.warning(
                "barrier: zeta(X*) = %.3g is (near) zero: t = %.3g * zeta* leaves no slack; "
                "using t = zeta* + %.3g (min_slack_per_residual = %g)",
                zeta_star,
                cfg.t_ratio,
                min_slack,
                cfg.min_slack_per_residual,
            )
            t = zeta_star + min_slack
        return zeta_star, t, n_invalid

    def propose_step(self, system: BarrierSystem, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """The damped Sherman-Morrison step ``(dc (Cf, 6), dp (Pf, 3))``.

        Raises:
            SlamError: ``H~ + lambda D`` could not be factorised.
        """
        fac = SchurFactorization(system.H_tilde, lam, self.config.damping_mode)
        return sherman_morrison_solve(
            fac, -system.H_tilde.g_c, -system.H_tilde.g_p, system.u_c, system.u_p
        )

    def run(self, state_star: BAState) -> BarrierResult:
        """Fuse, starting from the unconstrained optimum ``state_star``.

        Args:
            state_star: ``X* = argmin zeta`` (e.g. the k-BA's result).

        Returns:
            A :class:`BarrierResult`; its state always satisfies ``zeta < t``.
        """
        cfg = self.config
        zeta_star, t, n_invalid_star = self.threshold(state_star)
        c_star = float(sum(c.cost(state_star) for c in self.constraints))
        if not np.isfinite(c_star):
            raise SlamError("constraint cost at X* is not finite")
        if cfg.gamma is not None:
            gamma = float(cfg.gamma)
        else:
            gamma = cfg.gamma_rel * (t - zeta_star) * max(c_star, 1e-300)
        state = state_star
        lam = cfg.initial_lambda
        history: list[BarrierIteration] = []
        converged = False
        stop = "max_iterations"
        it = 0
        t_start = time.perf_counter()
        system = barrier_system(self.vision, self.constraints, state, t, gamma)
        # invalid rows as counted by the families' own cost (a compressed block may not show them)
        system.n_invalid_vision = n_invalid_star
        while it < cfg.max_iterations:
            g_max = max(
                float(np.max(np.abs(system.H_tilde.g_c), initial=0.0)),
                float(np.max(np.abs(system.H_tilde.g_p), initial=0.0)),
            )
            if g_max < cfg.grad_tol:
                converged, stop = True, "gradient"
                break
            it += 1
            accepted = False
            while not accepted:
                t0 = time.perf_counter()
                try:
                    dc, dp = self.propose_step(system, lam)
                except SlamError as exc:
                    logger.debug("barrier: singular damped system (%s)", exc)
                    dc = dp = None
                else:
                    full_norm = float(np.sqrt(np.sum(dc * dc) + np.sum(dp * dp)))
                scale = 1.0
                for back in range(cfg.max_backtracks + 1):
                    if back:  # the step crossed the barrier: try a shorter one, same direction
                        scale *= 0.5
                        t0 = time.perf_counter()
                    trial_zeta = trial_f = float("inf")
                    step_norm = float("nan")
                    if dc is None:
                        reason = "singular"
                    else:
                        step_norm = scale * full_norm
                        reason, trial_state, trial_zeta, trial_f, trial_invalid = self._judge_trial(
                            state, scale * dc, scale * dp, t, gamma, system, n_invalid_star
                        )
                    accepted = reason == "accepted"
                    history.append(
                        BarrierIteration(
                            iteration=it,
                            objective=system.objective,
                            zeta=system.zeta,
                            constraint_cost=system.constraint_cost,
                            lam=lam,
                            trial_zeta=trial_zeta,
                            trial_objective=trial_f,
                            accepted=accepted,
                            reason=reason,
                            step_norm=step_norm,
                            seconds=time.perf_counter() - t0,
                            step_scale=scale,
                        )
                    )
                    if reason != "infeasible":
                        break
                if accepted:
                    decrease = system.objective - trial_f
                    state = trial_state
                    if scale == 1.0:  # a shortened step keeps the damping: the full one failed
                        lam = max(lam * cfg.lambda_down, 1e-15)
                    system = barrier_system(self.vision, self.constraints, state, t, gamma)
                    system.n_invalid_vision = trial_invalid
                    if decrease <= cfg.rel_tol * abs(system.objective):
                        converged, stop = True, "relative_decrease"
                    break
                lam *= cfg.lambda_up
                if lam > cfg.max_lambda:
                    converged, stop = True, "max_lambda"
                    break
            if converged:
                break
        elapsed = time.perf_counter() - t_start
        if not system.zeta < t:  # never: only feasible trials are accepted
            raise SlamError("barrier: internal error, the final state is infeasible")
        logger.debug(
            "barrier: %d iterations, zeta %.6g -> %.6g (t = %.6g), C %.6g -> %.6g (%s)",
            it,
            zeta_star,
            system.zeta,
            t,
            c_star,
            system.constraint_cost,
            stop,
        )
        return BarrierResult(
            state=state,
            zeta_star=zeta_star,
            t=t,
            gamma=gamma,
            zeta=system.zeta,
            constraint_cost=system.constraint_cost,
            objective=system.objective,
            iterations=it,
            converged=converged,
            stop_reason=stop,
            history=history,
            seconds_per_iteration=elapsed / max(it, 1),
        )

    def _judge_trial(
        self,
        state: BAState,
        dc: np.ndarray,
        dp: np.ndarray,
        t: float,
        gamma: float,
        system: BarrierSystem,
        n_invalid_star: int,
    ) -> tuple[str, BAState | None, float, float, int]:
        """Evaluate a trial step: ``(reason, trial_state, trial_zeta, trial_f, n_invalid)``.

        ``reason == "accepted"`` is the only outcome that lets :meth:`run` take the step; it
        requires a finite ``zeta < t``, no new invalid rows and a lower ``f``.
        """
        inf = float("inf")
        if not (np.all(np.isfinite(dc)) and np.all(np.isfinite(dp))):
            return "non_finite", None, inf, inf, -1
        trial = state.retract(dc, dp)
        try:
            zeta, n_invalid = vision_cost(self.vision, trial)
        except SlamError as exc:  # e.g. a degenerate pose-graph pair at the trial
            logger.debug("barrier: trial rejected (%s)", exc)
            return "non_finite", None, inf, inf, -1
        if not np.isfinite(zeta):
            return "non_finite", None, inf, inf, -1
        if zeta >= t:
            logger.debug("barrier: trial rejected, zeta = %.6g >= t = %.6g", zeta, t)
            return "infeasible", None, zeta, inf, n_invalid
        if n_invalid > max(system.n_invalid_vision, n_invalid_star):
            return "invalid_rows", None, zeta, inf, n_invalid
        c = float(sum(f.cost(trial) for f in self.constraints))
        f = gamma / (t - zeta) + c
        if not np.isfinite(f):
            return "non_finite", None, zeta, inf, n_invalid
        if f >= system.objective:
            return "no_decrease", None, zeta, f, n_invalid
        return "accepted", trial, zeta, f, n_invalid


def solve_barrier(
    vision: Sequence[Factor],
    constraints: Sequence[Factor],
    state_star: BAState,
    config: BarrierConfig | None = None,
) -> BarrierResult:
    """Barrier-term fusion of ``constraints`` into the reconstruction ``state_star`` (eq. 2.3).

    Args:
        vision: the families of ``zeta`` (reprojection; plus DPC/MPC in the hybrid window).
        constraints: the families ``C_i`` (GPS, DEM, odometry, building...).
        state_star: the unconstrained optimum ``X*``.
        config: :class:`BarrierConfig`.

    Returns:
        A :class:`BarrierResult`.
    """
    return BarrierSolver(vision, constraints, config).run(state_star)
