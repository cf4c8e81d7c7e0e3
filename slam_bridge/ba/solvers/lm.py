"""Levenberg-Marquardt (thesis eqs. 1.25-1.26), separated from the objective it minimises.

The solver only decides damping and acceptance; everything problem-specific lives in an
**objective** (:class:`LMObjective`):

* ``cost(state) -> float``: the full objective ``F`` at a state;
* ``linearize(state) -> Linearization``: a local model with ``.cost`` (``F`` at the state) and
  ``.solve(damping) -> LMStep`` returning the damped step, the model's predicted decrease of
  ``F`` (``> 0``) and the step's size;
* ``retract(state, delta) -> state``;
* ``is_feasible(state) -> bool``: optional hard constraint (the barrier solver's ``zeta < t``;
  :class:`BAObjective`'s "no new points behind cameras"); an infeasible trial is rejected like a
  cost increase and the damping is raised, never accepted.

:class:`BAObjective` is the bundle-adjustment objective ``F = sum rho(||r||^2)`` over factor
families (:mod:`slam_bridge.ba.factor`), linearised by
:func:`slam_bridge.ba.normal_equations.assemble` and solved by the Schur complement
(:mod:`slam_bridge.ba.solvers.schur`).

**Damping** (``LMConfig.damping_mode``): ``"marquardt"`` (default) solves
``(H + lambda diag(H)) d = -g``; ``"additive"`` solves ``(H + lambda I) d = -g``.
**Update** (gain ratio ``rho = actual decrease / predicted decrease``, Nielsen's rule): on
``rho > 0`` accept, ``lambda *= max(1/3, 1 - (2 rho - 1)^3)``, ``nu = 2``; otherwise reject,
``lambda *= nu``, ``nu *= 2``.
**Stops** when a successful step decreases the cost by less than ``rel_cost_tol`` relative, or
the step's max-norm is below ``step_tol``, or the cost is below ``abs_cost_tol``, or after
``max_iterations`` iterations (each trial step counts as one), or when ``lambda`` exceeds
``max_lambda`` (failure).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from slam_bridge.ba.factor import Factor
from slam_bridge.ba.normal_equations import NormalEquations, assemble
from slam_bridge.ba.solvers.schur import DAMPING_MODES, SchurFactorization
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = [
    "LMConfig",
    "LMStep",
    "LMResult",
    "LMObjective",
    "Linearization",
    "BAObjective",
    "BALinearization",
    "levenberg_marquardt",
]


@dataclass
class LMConfig:
    """Levenberg-Marquardt settings (module docstring)."""

    max_iterations: int = 50
    initial_lambda: float = 1e-4
    damping_mode: str = "marquardt"
    rel_cost_tol: float = 1e-10
    step_tol: float = 1e-10
    abs_cost_tol: float = 0.0
    min_lambda: float = 1e-15
    max_lambda: float = 1e12


@dataclass
class LMStep:
    """A damped step.

    Attributes:
        delta: the increment, in the objective's format (``(dc (Cf, 6), dp (Pf, 3))`` for BA).
        predicted_decrease: decrease of ``F`` predicted by the local model (``>= 0``).
        norm: max-norm of the increment.
    """

    delta: Any
    predicted_decrease: float
    norm: float


@runtime_checkable
class Linearization(Protocol):
    """A local model of the objective at a state."""

    cost: float

    def solve(self, damping: float) -> LMStep:
        """The damped step for ``lambda = damping``."""
        ...


@runtime_checkable
class LMObjective(Protocol):
    """What Levenberg-Marquardt minimises (module docstring)."""

    def cost(self, state: Any) -> float: ...

    def linearize(self, state: Any) -> Linearization: ...

    def retract(self, state: Any, delta: Any) -> Any: ...


@dataclass
class LMResult:
    """Outcome of :func:`levenberg_marquardt`.

    Attributes:
        state: the final (best) state.
        cost: its cost.
        initial_cost: the starting cost.
        cost_history: costs after each accepted step (first entry: initial cost).
        iterations: number of iterations (trial steps, accepted or not).
        accepted: number of accepted steps.
        iteration_times: ``(iterations,)`` wall time of each iteration in seconds (linearisation,
            when one was needed, + solve + retraction + cost).
        lambdas: damping used at each iteration.
        termination: why it stopped.
        converged: True when it stopped on a tolerance (not on the iteration budget or damping).
    """

    state: Any
    cost: float
    initial_cost: float
    cost_history: list[float] = field(default_factory=list)
    iterations: int = 0
    accepted: int = 0
    iteration_times: list[float] = field(default_factory=list)
    lambdas: list[float] = field(default_factory=list)
    termination: str = ""
    converged: bool = False

    @property
    def time_per_iteration(self) -> float:
        """Mean seconds per iteration."""
        return float(np.mean(self.iteration_times)) if self.iteration_times else 0.0


def levenberg_marquardt(
    objective: LMObjective,
    state: Any,
    config: LMConfig | None = None,
    callback: Callable[[int, Any, float], None] | None = None,
) -> LMResult:
    """Minimise ``objective`` from ``state``.

    Args:
        objective: an :class:`LMObjective`.
        state: the starting state (not modified).
        config: settings; defaults if None.
        callback: called as ``callback(iteration, state, cost)`` after each accepted step.

    Returns:
        An :class:`LMResult`.
    """
    cfg = config or LMConfig()
    if cfg.damping_mode not in DAMPING_MODES:
        raise SlamError(f"damping_mode: expected one of {DAMPING_MODES}, got {cfg.damping_mode!r}")
    feasible = getattr(objective, "is_feasible", None)
    t0 = time.perf_counter()
    lin = objective.linearize(state)
    cost = float(lin.cost)
    if not np.isfinite(cost):
        raise SlamError("levenberg_marquardt: the initial cost is not finite")
    res = LMResult(state=state, cost=cost, initial_cost=cost, cost_history=[cost])
    lam, nu = cfg.initial_lambda, 2.0
    pending = time.perf_counter() - t0  # first linearisation is charged to iteration 1
    if cost <= cfg.abs_cost_tol:
        res.termination, res.converged = "cost below abs_cost_tol", True
        return res
    while res.iterations < cfg.max_iterations:
        t0 = time.perf_counter()
        res.iterations += 1
        res.lambdas.append(lam)
        try:
            step = lin.solve(lam)
        except SlamError as exc:  # not positive definite at this damping
            logger.debug("LM: solve failed at lambda=%g (%s)", lam, exc)
            step = None
        ok = False
        if step is not None and np.isfinite(step.norm):
            if step.norm <= cfg.step_tol:
                res.iteration_times.append(pending + time.perf_counter() - t0)
                res.termination, res.converged = "step below step_tol", True
                break
            trial = objective.retract(state, step.delta)
            new_cost = float(objective.cost(trial))
            if np.isfinite(new_cost) and (feasible is None or feasible(trial)):
                actual = cost - new_cost
                pred = max(step.predicted_decrease, 1e-300)
                gain = actual / pred
                ok = gain > 0
        if ok:
            state, old = trial, cost
            cost = new_cost
            res.accepted += 1
            res.cost_history.append(cost)
            lam = max(lam * max(1 / 3, 1 - (2 * gain - 1) ** 3), cfg.min_lambda)
            nu = 2.0
            if callback is not None:
                callback(res.iterations, state, cost)
            small = (old - cost) <= cfg.rel_cost_tol * old or cost <= cfg.abs_cost_tol
            if not small:
                lin = objective.linearize(state)
            res.iteration_times.append(pending + time.perf_counter() - t0)
            pending = 0.0
            if small:
                res.termination, res.converged = "relative cost decrease below rel_cost_tol", True
                break
        else:
            lam *= nu
            nu *= 2.0
            res.iteration_times.append(pending + time.perf_counter() - t0)
            pending = 0.0
            if lam > cfg.max_lambda:
                res.termination = "damping exceeded max_lambda"
                break
    else:
        res.termination = "max_iterations"
    res.state, res.cost = state, cost
    logger.debug(
        "LM: %s after %d iterations (%d accepted), cost %.6g -> %.6g",
        res.termination,
        res.iterations,
        res.accepted,
        res.initial_cost,
        res.cost,
    )
    return res


class BALinearization:
    """Block normal equations at a state, solved by the Schur complement.

    Args:
        neq: :class:`slam_bridge.ba.normal_equations.NormalEquations` (of ``0.5 * F``).
        mode: damping mode.
    """

    def __init__(self, neq: NormalEquations, mode: str = "marquardt") -> None:
        self.neq = neq
        self.mode = mode
        self.cost = neq.cost

    def solve(self, damping: float) -> LMStep:
        """Damped Gauss-Newton step ``(H + lambda D) d = -g`` with its predicted decrease.

        For ``F = 2 * (0.5 F)`` the model decrease is ``-g.d + lambda d^T D d`` (both halves of
        ``2 * (-g.d - 0.5 d^T H d)`` rewritten with the damped equation).
        """
        neq = self.neq
        fac = SchurFactorization(neq, damping, self.mode)
        dc, dp = fac.solve(-neq.g_c, -neq.g_p)
        gd = float(np.sum(neq.g_c * dc) + np.sum(neq.g_p * dp))
        if self.mode == "additive":
            dDd = float(np.sum(dc * dc) + np.sum(dp * dp))
        else:
            ic, ip = np.arange(6), np.arange(3)
            Dc = np.maximum(neq.U[:, ic, ic], 1e-12)
            Dp = np.maximum(neq.V[:, ip, ip], 1e-12)
            dDd = float(np.sum(Dc * dc * dc) + np.sum(Dp * dp * dp))
        pred = -gd + damping * dDd
        norm = float(max(np.max(np.abs(dc), initial=0.0), np.max(np.abs(dp), initial=0.0)))
        return LMStep((dc, dp), pred, norm)


class BAObjective:
    """Bundle adjustment ``F = sum over families of sum rho(||r||^2)``.

    Args:
        factors: factor families (:class:`slam_bridge.ba.factor.Factor`).
        damping_mode: ``"marquardt"`` or ``"additive"``.
        forbid_new_invalid: reject steps that increase the number of invalid rows (points that
            would cross behind their camera), instead of letting them leave the cost.
    """

    def __init__(
        self,
        factors: Sequence[Factor],
        damping_mode: str = "marquardt",
        forbid_new_invalid: bool = True,
    ) -> None:
        self.factors = list(factors)
        if not self.factors:
            raise SlamError("BAObjective: no factor family given")
        self.damping_mode = damping_mode
        self.forbid_new_invalid = forbid_new_invalid
        self._n_invalid = 0
        self._trial_invalid = 0

    def _cost_invalid(self, state: BAState) -> tuple[float, int]:
        total, bad = 0.0, 0
        for f in self.factors:
            ci = getattr(f, "cost_and_invalid", None)
            if ci is not None:
                c, n = ci(state)
            else:
                c, n = f.cost(state), 0
            total += c
            bad += n
        return total, bad

    def cost(self, state: BAState) -> float:
        """``F(state)``."""
        c, self._trial_invalid = self._cost_invalid(state)
        return c

    def linearize(self, state: BAState) -> BALinearization:
        """Assemble the block normal equations."""
        neq = assemble(self.factors, state)
        self._n_invalid = neq.n_invalid
        return BALinearization(neq, self.damping_mode)

    def retract(self, state: BAState, delta: tuple[np.ndarray, np.ndarray]) -> BAState:
        """``state.retract(dc, dp)``."""
        return state.retract(*delta)

    def is_feasible(self, state: BAState) -> bool:
        """False when the trial (last :meth:`cost` call) has more invalid rows than the current."""
        return not self.forbid_new_invalid or self._trial_invalid <= self._n_invalid
