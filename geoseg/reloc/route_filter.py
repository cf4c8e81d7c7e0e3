"""Sequence localisation along a georeferenced image base: a discrete Bayes filter (HMM).

Single-image retrieval (:class:`geoseg.reloc.retrieval.RetrievalIndex`) ranks each query on its
own; a vehicle's queries come in order, a known distance apart, along a route the base was
recorded on, and a run of them is often unambiguous where one image is not (sequence-based place
recognition, SeqSLAM, in its probabilistic form, Hansen & Browning 2014; not in the thesis). The
state is the base image the vehicle is at along the base's route (ordered by timestamps, split
into segments at gaps); the motion model moves it the driven distance along its segment, with a
chance to leave the route; the observation is the appearance likelihood of the embedding
distance, times an optional GPS window or Gaussian. The model in full: ``docs/route_filter.md``.

:meth:`RouteFilter.filter` returns the causal posterior ``p(b_t | q_0..q_t)`` (what a vehicle
knows at query ``t``); :meth:`RouteFilter.smooth` the forward-backward posterior
``p(b_t | q_0..q_{T-1})`` of a recorded drive. The queries are assumed to drive the base route
in its recorded direction. Cost: ``O(T * M * w)`` with ``w`` the base images within the motion
band (a few); the ``(T, M)`` distance and posterior matrices are dense.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.special import ndtr

from geoseg.errors import GeosegError, check_finite, check_positive, check_shape

logger = logging.getLogger(__name__)

# The motion band reaches this many sigmas (at least one base spacing) around the step.
_BAND_SIGMAS = 4.0
# Floor of a log-likelihood term (a probability of exp(-1e300) is 0 for every purpose).
_LOG_FLOOR = 1e300


@dataclass
class RouteFilterConfig:
    """Settings of :class:`RouteFilter` (defaults chosen on validation city 13,
    ``bench/accuracy_reloc.py``).

    Attributes:
        appearance_scale: ``tau`` of the appearance likelihood ``exp(-d / tau)``, in the
            embedding's distance units (> 0; smaller trusts appearance more); None:
            ``appearance_scale_rel`` times the median of the drive's distances.
        appearance_scale_rel: that share (> 0). 0.29: ``tau = 0.4`` for the shipped embedding
            head, whose query-base distances have a median of 1.38 on validation city 13.
        step_sigma_m: absolute odometry error per step, metres (> 0).
        step_sigma_rel: relative odometry error per step (>= 0).
        off_route: per-step probability of a jump to any base image (in ``(0, 1)``).
        gap_m: consecutive base images farther apart than this start a new route segment
            (None: 4 times the median spacing).
    """

    appearance_scale: float | None = None
    appearance_scale_rel: float = 0.29
    step_sigma_m: float = 2.0
    step_sigma_rel: float = 0.2
    off_route: float = 1e-3
    gap_m: float | None = None

    def __post_init__(self) -> None:
        if self.appearance_scale is not None:
            check_positive("appearance_scale", self.appearance_scale)
        check_positive("appearance_scale_rel", self.appearance_scale_rel)
        check_positive("step_sigma_m", self.step_sigma_m)
        check_positive("step_sigma_rel", self.step_sigma_rel, strict=False)
        if not 0.0 < self.off_route < 1.0:
            raise GeosegError(f"off_route: expected in (0, 1), got {self.off_route}")
        if self.gap_m is not None:
            check_positive("gap_m", self.gap_m)


@dataclass
class RouteFilterResult:
    """Posterior over base images per query.

    Attributes:
        posterior: ``(T, M)`` probabilities, each row sums to 1.
        ranked: ``(T, M)`` base indices per query, most probable first.
        empty_windows: queries whose GPS window held no base image (their observation was the
            appearance alone).
    """

    posterior: np.ndarray
    ranked: np.ndarray
    empty_windows: int = 0

    def top(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(indices (T, k), probabilities (T, k))`` of the ``k`` most probable base images."""
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise GeosegError(f"k: expected an int >= 1, got {k!r}")
        idx = self.ranked[:, :k]
        return idx, np.take_along_axis(self.posterior, idx, axis=1)


class RouteFilter:
    """HMM over the base images of a route (module docstring).

    Args:
        positions: ``(M, 2)`` or ``(M, 3)`` base camera positions in the world frame, metres
            (the horizontal part is used).
        timestamps: ``(M,)`` base timestamps giving the route order (None: the given order).
        config: :class:`RouteFilterConfig`.

    Attributes:
        order: ``(M,)`` base indices in route order.
        arc_length: ``(M,)`` metres along the route, per base image (original indexing).
        segment: ``(M,)`` route segment of each base image.
        spacing_m: median distance between consecutive base images of a segment.
    """

    def __init__(
        self,
        positions: Any,
        *,
        timestamps: Any = None,
        config: RouteFilterConfig | None = None,
    ) -> None:
        self.config = config or RouteFilterConfig()
        pos = np.asarray(positions, dtype=np.float64)
        check_shape("positions", pos, (None, None))
        m = pos.shape[0]
        if m == 0:
            raise GeosegError("positions: the base is empty")
        if pos.shape[1] not in (2, 3):
            raise GeosegError(f"positions: expected shape ({m}, 2) or ({m}, 3), got {pos.shape}")
        check_finite("positions", pos)
        if timestamps is None:
            order = np.arange(m)
        else:
            ts = np.asarray(timestamps, dtype=np.float64)
            check_shape("timestamps", ts, (m,))
            check_finite("timestamps", ts)
            order = np.argsort(ts, kind="stable")
        xy = pos[order, :2]
        hops = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        moving = hops[hops > 1e-9]
        self.spacing_m = float(np.median(moving)) if moving.size else 1.0
        gap = self.config.gap_m if self.config.gap_m is not None else 4.0 * self.spacing_m
        breaks = hops > gap
        seg_sorted = np.concatenate([[0], np.cumsum(breaks)])
        # a segment break does not advance the arc length: segments never mix (see _motion)
        s_sorted = np.concatenate([[0.0], np.cumsum(np.where(breaks, 0.0, hops))])
        self.order = order
        self.arc_length = np.empty(m)
        self.arc_length[order] = s_sorted
        self.segment = np.empty(m, dtype=np.int64)
        self.segment[order] = seg_sorted
        self._s = s_sorted
        self._xy = xy
        starts = np.flatnonzero(np.r_[True, breaks])
        self._seg_lo = starts[seg_sorted]  # per sorted index: first index of its segment
        self._seg_hi = np.r_[starts[1:], m][seg_sorted]  # one past its last
        logger.debug(
            "route filter: %d base images, %d segments, spacing %.2f m",
            m,
            int(seg_sorted[-1]) + 1,
            self.spacing_m,
        )

    def __len__(self) -> int:
        return int(self.order.size)

    # ------------------------------------------------------------------ model
    def _motion(self, step_m: float) -> tuple[sp.csr_matrix, np.ndarray]:
        """One step of the motion model in route order.

        Returns:
            ``(K (M, M) sub-stochastic CSR, leave (M,))``: ``K[b, b']`` the probability of
            moving from ``b`` to ``b'`` along the segment, ``leave[b]`` that of driving past
            either end of it (half a spacing beyond its last image), ``K.sum(1) + leave = 1``.
        """
        cfg = self.config
        m = len(self)
        sigma = cfg.step_sigma_m + cfg.step_sigma_rel * abs(step_m)
        half = max(_BAND_SIGMAS * sigma, 1.5 * self.spacing_m)
        target = self._s + step_m
        s_lo, s_hi = self._s[self._seg_lo], self._s[self._seg_hi - 1]
        pad = 0.5 * self.spacing_m
        leave = ndtr((target - s_hi - pad) / sigma) + ndtr((s_lo - pad - target) / sigma)
        lo = np.maximum(np.searchsorted(self._s, target - half, side="left"), self._seg_lo)
        hi = np.minimum(np.searchsorted(self._s, target + half, side="right"), self._seg_hi)
        counts = np.maximum(hi - lo, 0)
        rows = np.repeat(np.arange(m), counts)
        cols = np.repeat(lo - np.cumsum(np.r_[0, counts[:-1]]), counts) + np.arange(rows.size)
        w = np.exp(-0.5 * np.square((self._s[cols] - target[rows]) / sigma))
        row_sum = np.bincount(rows, weights=w, minlength=m)
        empty = row_sum <= 1e-300
        leave = np.where(empty, 1.0, np.clip(leave, 0.0, 1.0))
        w = w * ((1.0 - leave) / np.where(empty, 1.0, row_sum))[rows]
        return sp.csr_matrix((w, (rows, cols)), shape=(m, m)), leave

    def _steps(self, steps_m: Any, n: int) -> np.ndarray:
        if steps_m is None:
            return np.full(max(n - 1, 0), self.spacing_m)
        steps = np.asarray(steps_m, dtype=np.float64)
        check_shape("steps_m", steps, (max(n - 1, 0),))
        check_finite("steps_m", steps)
        if (steps < 0).any():
            raise GeosegError(
                "steps_m: expected distances >= 0 (the drive's direction is the base's)"
            )
        return steps

    def likelihoods(
        self,
        distances: Any,
        *,
        gps: Any = None,
        radius_m: float | None = None,
        gps_sigma_m: float | None = None,
    ) -> tuple[np.ndarray, int]:
        """Observation likelihoods in route order, each row scaled to a maximum of 1.

        Args:
            distances: ``(T, M)`` embedding distances query -> base image (original indexing,
                e.g. :meth:`geoseg.reloc.retrieval.RetrievalIndex.distances`).
            gps: ``(T, 2)`` or ``(T, 3)`` query fixes in the world frame, metres.
            radius_m: hard GPS window (needs ``gps`` and base positions).
            gps_sigma_m: Gaussian GPS likelihood's standard deviation per axis (needs ``gps``).

        Returns:
            ``((T, M) likelihoods in route order, number of queries with an empty window)``.
        """
        d = np.asarray(distances, dtype=np.float64)
        check_shape("distances", d, (None, len(self)))
        check_finite("distances", d)
        if (d < 0).any():
            raise GeosegError("distances: expected embedding distances >= 0")
        d = d[:, self.order]
        # Log-likelihoods, each term floored at -_LOG_FLOOR (not -inf): two terms that both
        # underflow (a tiny tau and a tiny GPS sigma) still sum to a finite, ordered value.
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            log_l = -(d - d.min(axis=1, keepdims=True)) / self.appearance_scale(d)
        log_l = np.maximum(np.nan_to_num(log_l, nan=-_LOG_FLOOR), -_LOG_FLOOR)
        empty = 0
        if radius_m is not None or gps_sigma_m is not None:
            if gps is None:
                raise GeosegError("gps: required with radius_m or gps_sigma_m")
            g = np.asarray(gps, dtype=np.float64)
            check_shape("gps", g, (d.shape[0], None))
            if g.shape[1] not in (2, 3):
                raise GeosegError(
                    f"gps: expected shape ({d.shape[0]}, 2) or (.., 3), got {g.shape}"
                )
            check_finite("gps", g)
            with np.errstate(over="ignore"):
                r2 = np.sum(np.square(g[:, None, :2] - self._xy[None]), axis=2)
            if gps_sigma_m is not None:
                check_positive("gps_sigma_m", gps_sigma_m)
                # relative to the nearest base image, so the nearest keeps a finite term however
                # small sigma is (sigma -> 0: the posterior goes to the nearest base image)
                rel = r2 - r2.min(axis=1, keepdims=True)
                with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
                    gps_term = np.where(rel > 0, rel / (2.0 * np.square(float(gps_sigma_m))), 0.0)
                log_l = log_l - np.minimum(np.nan_to_num(gps_term, nan=_LOG_FLOOR), _LOG_FLOOR)
            if radius_m is not None:
                check_positive("radius_m", radius_m)
                outside = r2 > np.square(float(radius_m))
                all_out = outside.all(axis=1)
                empty = int(all_out.sum())
                if empty:
                    logger.warning(
                        "%d queries have no base image within %.1f m of their GPS fix: "
                        "appearance alone for them",
                        empty,
                        radius_m,
                    )
                log_l = np.where(outside & ~all_out[:, None], -np.inf, log_l)
        log_l -= log_l.max(axis=1, keepdims=True)
        return np.exp(log_l), empty

    def appearance_scale(self, distances: np.ndarray) -> float:
        """``tau`` for a drive's ``(T, M)`` distances (:class:`RouteFilterConfig`)."""
        cfg = self.config
        if cfg.appearance_scale is not None:
            return float(cfg.appearance_scale)
        top = float(distances.max()) if distances.size else 0.0
        if not top > 0:  # every query duplicates every base image: appearance says nothing
            return 1.0
        # the median of distances / max, times max: no overflow for distances near 1e308
        return cfg.appearance_scale_rel * float(np.median(distances / top)) * top

    # ------------------------------------------------------------------ inference
    def _predict(self, alpha: np.ndarray, motion: tuple) -> np.ndarray:
        """``T^T alpha``: one motion step (:meth:`_motion`) of a distribution in route order."""
        K, leave = motion
        eps = self.config.off_route
        jump = eps * alpha.sum() + (1.0 - eps) * (leave @ alpha)
        return (1.0 - eps) * (K.T @ alpha) + jump / alpha.size

    def _back(self, beta: np.ndarray, motion: tuple) -> np.ndarray:
        """``T beta``: the backward message through one motion step (:meth:`_motion`)."""
        K, leave = motion
        eps = self.config.off_route
        return (1.0 - eps) * (K @ beta) + (eps + (1.0 - eps) * leave) * beta.mean()

    def _forward(self, lik: np.ndarray, motions: list) -> np.ndarray:
        n, m = lik.shape
        alpha = np.empty((n, m))
        prior = np.full(m, 1.0 / m)
        for t in range(n):
            if t:
                prior = self._predict(alpha[t - 1], motions[t - 1])
            a = prior * lik[t]
            total = a.sum()
            if not total > 0:  # the observation contradicts every reachable state
                a = lik[t] / lik[t].sum()
            else:
                a /= total
            alpha[t] = a
        return alpha

    def _result(self, post_sorted: np.ndarray, empty: int) -> RouteFilterResult:
        post = np.empty_like(post_sorted)
        post[:, self.order] = post_sorted
        total = post.sum(axis=1, keepdims=True)
        if not (np.isfinite(total).all() and (total > 0).all()):  # never a silent NaN posterior
            raise GeosegError(
                "route filter: the posterior underflowed for some query (inputs far outside "
                "the model's range: check distances, steps_m and the GPS sigmas)"
            )
        post /= total
        ranked = np.argsort(-post, axis=1, kind="stable").astype(np.int64)
        return RouteFilterResult(posterior=post, ranked=ranked, empty_windows=empty)

    def filter(
        self,
        distances: Any,
        steps_m: Any = None,
        *,
        gps: Any = None,
        radius_m: float | None = None,
        gps_sigma_m: float | None = None,
    ) -> RouteFilterResult:
        """Causal posterior ``p(b_t | q_0..q_t)`` of each query of a drive.

        Args:
            distances: ``(T, M)`` embedding distances query -> base image, queries in driving
                order.
            steps_m: ``(T - 1,)`` distances driven between consecutive queries, metres
                (odometry); None assumes one base spacing per query.
            gps, radius_m, gps_sigma_m: optional GPS evidence (:meth:`likelihoods`).

        Returns:
            A :class:`RouteFilterResult` (original base indexing).
        """
        return self._run(distances, steps_m, (gps, radius_m, gps_sigma_m), smooth=False)

    def smooth(
        self,
        distances: Any,
        steps_m: Any = None,
        *,
        gps: Any = None,
        radius_m: float | None = None,
        gps_sigma_m: float | None = None,
    ) -> RouteFilterResult:
        """Forward-backward posterior ``p(b_t | q_0..q_{T-1})`` of a recorded drive (same
        arguments as :meth:`filter`)."""
        return self._run(distances, steps_m, (gps, radius_m, gps_sigma_m), smooth=True)

    def _run(
        self, distances: Any, steps_m: Any, gps_args: tuple, *, smooth: bool
    ) -> RouteFilterResult:
        gps, radius_m, gps_sigma_m = gps_args
        lik, empty = self.likelihoods(
            distances, gps=gps, radius_m=radius_m, gps_sigma_m=gps_sigma_m
        )
        if lik.shape[0] == 0:
            raise GeosegError("distances: no queries")
        # one motion model per step, shared by the forward and backward passes
        motions = [self._motion(float(s)) for s in self._steps(steps_m, lik.shape[0])]
        alpha = self._forward(lik, motions)
        if not smooth:
            return self._result(alpha, empty)
        beta = np.ones_like(alpha)
        for t in range(lik.shape[0] - 2, -1, -1):
            b = self._back(lik[t + 1] * beta[t + 1], motions[t])
            beta[t] = b / b.max() if b.max() > 0 else 1.0
        return self._result(alpha * beta, empty)
