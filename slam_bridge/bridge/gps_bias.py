"""A GPS receiver's bias, estimated from the building model (thesis §4.4).

The thesis couples the building constraints with odometry, or with the GPS "if its bias is
acceptable"; an urban receiver's error is mostly a locally constant bias of several metres
(:mod:`geoseg.synth.gps`), which GPS fusion alone cannot remove: the map follows the fixes,
bias included. The building model sees it. Where the map is off the truth by ``e``, the map
points associated with a facade lie off its plane by ``n . e`` (``n`` the facade's horizontal
normal; plus the model's own error for that facade); the window's cameras are off by the same
``e``, so a fix (``true + b``) lies ``b - e`` from its camera. Their sum measures the bias
alone, ``n . b``, whatever the map's own error (a start georeferenced on a few fixes, a drift).
Facades of several orientations (the two sides of a street, a cross street) make both
components of ``b`` observable; odometry and the DEM carry the map between them.

:class:`BuildingGpsBias` is the GPS's bias source (:class:`slam_bridge.slam.fusion.
GpsBiasSource`). At each keyframe's fusion, before its fix is used:

1. the window's cameras with a fix give ``g``, the mean of ``fix - T`` (optical centres at the
   k-BA's optimum ``X*``, the antenna's lever arm removed);
2. every facade of the current association with at least ``min_points`` points in the window
   gives one offset, the median of its points' signed plane distances ``n . X - d`` (robust to
   a few wrong associations); offsets larger than ``max_offset_m`` are dropped (a wrong facade
   or a lost map, not a bias); ``y = offset + n . g`` measures ``n . b``;
3. each facade keeps its latest ``y`` and the time it was last seen: one facade counts once, so
   its model error (the same at every look) is not taken for evidence;
4. the bias is the least-squares solution of ``n_f . b = y_f`` over the remembered facades,
   each weighed ``exp(-age / memory_s) / facade_sigma_m^2`` (a bias changes over tens of
   seconds: old facades fade), with a prior ``b ~ N(0, s^2 I)`` (a direction no facade
   constrains keeps the fix as it is): ``b = (I / s^2 + sum w_f n_f n_f^T)^-1 sum w_f y_f
   n_f``, its covariance the inverse. The prior is a mixture (the detection): a biased
   receiver (``s = prior_sigma_m``) with probability ``biased_share``, an unbiased one (``s =
   unbiased_sigma_m``) otherwise; each component's evidence weighs its posterior. The GIS
   model's own errors (a metre per building) then pass for a bias only when they are far
   larger than their mean over the facades seen, and a real bias of metres is taken whole.

The fix is corrected, ``fix - b``, and, with ``inflate``, weighed ``1 / (sigma_gps^2 +
tr(cov) / 2)``: a bias known only roughly is noise on the fix. The start-up's georeferencing
(:class:`slam_bridge.slam.initialization.TwoViewStart`), which fits the whole segment to its
fixes at every keyframe over its first ``refit_distance_m``, fits it to the corrected fixes
(:meth:`BuildingGpsBias.at`): without it the map would be put back on the biased track at
every keyframe, whatever the fusion does.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.errors import SlamError
from slam_bridge.slam.map import Map

logger = logging.getLogger(__name__)

__all__ = ["GpsBiasConfig", "BuildingGpsBias", "gaussian_posterior", "solve_bias"]


@dataclass
class GpsBiasConfig:
    """The GPS bias estimated from the building model (module docstring).

    Attributes:
        enabled: estimate the bias (when a building model is given) and correct the fixes.
        prior_sigma_m: spread per axis of a biased receiver's bias (the simulator's
            ``bias_std_m``).
        unbiased_sigma_m: spread per axis of an unbiased receiver's (its noise's mean over the
            facades' time; None: every receiver is biased, the bias always estimated).
        biased_share: prior probability that the receiver is biased.
        facade_sigma_m: error of one facade of the GIS model (its building's shift), metres.
        memory_s: a facade's evidence fades as ``exp(-age / memory_s)``, seconds.
        min_points: window points a facade needs to give an offset.
        max_offset_m: larger offsets are wrong associations, not a bias.
        inflate: lower the fix's weight by the uncertainty of its bias.
    """

    enabled: bool = True
    prior_sigma_m: float = 1.5
    unbiased_sigma_m: float | None = 0.3
    biased_share: float = 0.5
    facade_sigma_m: float = 1.2
    memory_s: float = 20.0
    min_points: int = 3
    max_offset_m: float = 4.0
    inflate: bool = True

    def __post_init__(self) -> None:
        for name in ("prior_sigma_m", "facade_sigma_m", "memory_s", "max_offset_m"):
            if not getattr(self, name) > 0:
                raise SlamError(f"gps_bias.{name}: expected > 0, got {getattr(self, name)}")
        if self.unbiased_sigma_m is not None and not 0 < self.unbiased_sigma_m:
            raise SlamError(f"gps_bias.unbiased_sigma_m: expected > 0, got {self.unbiased_sigma_m}")
        if not 0 < self.biased_share <= 1:
            raise SlamError(f"gps_bias.biased_share: expected in (0, 1], got {self.biased_share}")
        if self.min_points < 1:
            raise SlamError(f"gps_bias.min_points: expected >= 1, got {self.min_points}")


def gaussian_posterior(
    A: np.ndarray, g: np.ndarray, prior_sigma_m: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """The bias under the prior ``N(0, prior_sigma_m^2 I)``, given the facades' information.

    Args:
        A: ``(2, 2)`` the facades' information ``sum w_f n_f n_f^T``.
        g: ``(2,)`` ``sum w_f y_f n_f``.
        prior_sigma_m: the prior's spread per axis.

    Returns:
        ``(b (2,), cov (2, 2), log_evidence)``: the posterior mean and covariance, and the log
        marginal likelihood of the facades' offsets under this prior (up to a constant that
        is the same for every prior).
    """
    s2 = prior_sigma_m**2
    cov = np.linalg.inv(A + np.eye(2) / s2)
    b = cov @ g
    log_evidence = -0.5 * np.log(np.linalg.det(np.eye(2) + s2 * A)) + 0.5 * float(g @ b)
    return b, cov, float(log_evidence)


def solve_bias(
    normals: np.ndarray,
    y: np.ndarray,
    weights: np.ndarray,
    prior_sigma_m: float,
    unbiased_sigma_m: float | None = None,
    biased_share: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The bias from facade offsets (module docstring, step 4).

    Args:
        normals: ``(F, 2)`` horizontal unit normals of the facades.
        y: ``(F,)`` their measurements of ``n . b``, metres.
        weights: ``(F,)`` their weights, 1 / m^2.
        prior_sigma_m: the spread per axis of a biased receiver's bias.
        unbiased_sigma_m: the spread of an unbiased receiver's (None: every receiver is
            biased).
        biased_share: prior probability of a biased receiver (with ``unbiased_sigma_m``).

    Returns:
        ``(b (2,), cov (2, 2), p_biased)``: the posterior mean and covariance of the bias (of
        the two-component mixture), and the posterior probability that the receiver is biased.
    """
    A = np.einsum("f,fi,fj->ij", weights, normals, normals)
    g = np.einsum("f,f,fi->i", weights, y, normals)
    b1, cov1, log1 = gaussian_posterior(A, g, prior_sigma_m)
    if unbiased_sigma_m is None or biased_share >= 1.0:
        return b1, cov1, 1.0
    b0, cov0, log0 = gaussian_posterior(A, g, unbiased_sigma_m)
    # p(biased | offsets), from the two evidences (in a form that cannot overflow)
    p = 1.0 / (1.0 + (1.0 - biased_share) / biased_share * np.exp(np.clip(log0 - log1, -50, 50)))
    b = p * b1 + (1.0 - p) * b0
    cov = p * (cov1 + np.outer(b1, b1)) + (1.0 - p) * (cov0 + np.outer(b0, b0)) - np.outer(b, b)
    return b, cov, float(p)


@dataclass
class _Seen:
    """A facade's latest measurement: ``n . b = y`` at time ``t``."""

    normal: np.ndarray  # (2,)
    y: float
    t: float


@dataclass
class BuildingGpsBias:
    """The GPS bias from the facades of a bridge's building constraints (module docstring).

    Args:
        constraints: the bridge's building constraints (their current association and model).
        fixes: ``(timestamp, R_wc (3, 3)) -> (2,) | None``: the GPS fix of a camera's optical
            centre (:meth:`slam_bridge.slam.fusion.GpsConstraints.camera_fix_at`).
        config: the estimator's settings.

    Attributes:
        history: ``(keyframe, timestamp, b (2,), cov (2, 2), facades, p_biased)`` of every
            estimate.
    """

    constraints: BuildingConstraints
    fixes: Callable[[float, np.ndarray], np.ndarray | None]
    config: GpsBiasConfig = field(default_factory=GpsBiasConfig)
    history: list = field(default_factory=list)
    _seen: dict = field(default_factory=dict)  # facade row -> _Seen

    @property
    def inflate(self) -> bool:
        return self.config.inflate

    def estimate(self, slam_map: Map, problem, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(b (2,), cov (2, 2))`` for keyframe ``k``'s fix, after measuring the facades of
        ``problem``'s window (the k-BA's optimum ``X*``)."""
        cfg = self.config
        t = float(slam_map.timestamps[k])
        self._measure(slam_map, problem, t)
        for f in [f for f, s in self._seen.items() if t - s.t > 5.0 * cfg.memory_s]:
            del self._seen[f]  # weighs under 1 % of a new one: forgotten
        seen = list(self._seen.values())
        if seen:
            normals = np.stack([s.normal for s in seen])
            y = np.array([s.y for s in seen])
            ages = np.array([t - s.t for s in seen])
            w = np.exp(-np.maximum(ages, 0.0) / cfg.memory_s) / cfg.facade_sigma_m**2
            b, cov, p = solve_bias(
                normals, y, w, cfg.prior_sigma_m, cfg.unbiased_sigma_m, cfg.biased_share
            )
        else:
            b, cov, p = solve_bias(
                np.zeros((0, 2)), np.zeros(0), np.zeros(0), cfg.prior_sigma_m,
                cfg.unbiased_sigma_m, cfg.biased_share,
            )  # fmt: skip
        self.history.append((k, t, b, cov, len(seen), p))
        return b, cov

    def at(self, timestamps):
        """The bias of fixes at ``timestamps`` (a float: ``(2,)``; ``(N,)``: ``(N, 2)``): the
        estimate made ``memory_s`` after each (or the latest, if sooner): a locally constant
        bias is best known from the facades seen around its time, later ones included; 0
        before any estimate."""
        t = np.asarray(timestamps, dtype=np.float64)
        if not self.history:
            return np.zeros((*t.shape, 2))
        times = np.array([h[1] for h in self.history])
        bs = np.array([h[2] for h in self.history])
        i = np.searchsorted(times, t + self.config.memory_s, side="right") - 1
        return np.where((i >= 0)[..., None], bs[np.maximum(i, 0)], 0.0)

    def _fix_offset(self, slam_map: Map, problem) -> np.ndarray | None:
        """``(2,)`` the mean of ``fix - T`` over the window's cameras with a fix (step 1)."""
        st = problem.state
        gaps = []
        for cam, kf in enumerate(np.asarray(problem.camera_ids)):
            fix = self.fixes(float(slam_map.timestamps[kf]), st.R_wc[cam])
            if fix is not None:
                gaps.append(fix - st.t_wc[cam, :2])
        return np.mean(gaps, axis=0) if gaps else None

    def _measure(self, slam_map: Map, problem, t: float) -> None:
        """Each facade with enough points in the window: its latest ``y`` (steps 1-2)."""
        cfg = self.config
        rows, f, _ = self.constraints.window_points(problem)
        if rows.size == 0:
            return
        g = self._fix_offset(slam_map, problem)
        if g is None:  # a dropout over the whole window: nothing to compare with
            return
        model = self.constraints.facades
        offset = np.einsum("ij,ij->i", model.normal[f], problem.state.X_w[rows]) - model.d[f]
        order = np.argsort(f, kind="stable")
        groups, starts = np.unique(f[order], return_index=True)
        for facade_id, part in zip(groups, np.split(offset[order], starts[1:])):
            if part.size < cfg.min_points:
                continue
            median = float(np.median(part))
            if abs(median) > cfg.max_offset_m:
                continue
            n = model.normal[facade_id, :2]
            norm = float(np.linalg.norm(n))
            if norm < 0.5:  # not a vertical facade: no horizontal evidence
                continue
            # the plane's offset along its unit horizontal normal
            self._seen[int(facade_id)] = _Seen(n / norm, (median + float(n @ g)) / norm, t)
