"""Dirichlet false-positive filter for building pixels (thesis §4.2.2-4.2.3, eqs. 4.3-4.9).

The network's per-pixel softmax vectors of *true* building pixels are modelled by a Dirichlet
distribution ``D(alpha)``; a pixel whose argmax is "building" but whose density is low is a false
positive and is dropped (fig. 4.7). :class:`DirichletFilter` fits ``alpha`` by L-BFGS-B on
sufficient statistics (eqs. 4.4-4.8; :meth:`DirichletFilter.fit_statistics` from statistics
accumulated over many images), clips probabilities at ``eps`` (:data:`DEFAULT_EPS`, part of the
saved model) before any logarithm, stores the threshold ``t_D`` as a log-density and applies the
3D rule of eq. 4.9 to map points (:meth:`DirichletFilter.classify_points`).
:class:`MaxProbabilityFilter` is the baseline with the same API. Both may score the mean vector
over a ``window x window`` box (our addition; ``window = 1`` is the thesis's filter). The fit's
details, the choice of ``eps`` (measured) and the reason for the window: ``docs/networks.md``
("The Dirichlet false-positive filter").
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from scipy.ndimage import uniform_filter
from scipy.optimize import minimize
from scipy.special import digamma, gammaln, logsumexp

from geoseg.atomic import atomic_write
from geoseg.classes import BUILDING, NUM_CLASSES
from geoseg.errors import GeosegError, check_positive
from geoseg.integrity import DIGEST_KEY, seal, verify_payload

logger = logging.getLogger(__name__)

FORMAT_NAME = "geoseg.score_filter"
FORMAT_VERSION = 1
DEFAULT_EPS = 1e-30
ALPHA_MIN = 1e-6
SUM_TOL = 1e-3
_CHUNK = 1 << 18
_N_CALIBRATION_QUANTILES = 101


# ----------------------------------------------------------------------------- input checks


def _as_probs(name: str, probs: Any, k: int | None, sum_tol: float = SUM_TOL) -> np.ndarray:
    """Validate ``probs`` as a ``(..., K)`` array of probability vectors; return float64 view."""
    if hasattr(probs, "detach"):
        probs = probs.detach().cpu().numpy()
    arr = np.asarray(probs)
    if arr.ndim < 1:
        raise GeosegError(f"{name}: expected an array of shape (..., K), got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise GeosegError(f"{name}: expected floating-point probabilities, got dtype {arr.dtype}")
    if k is not None and arr.shape[-1] != k:
        raise GeosegError(f"{name}: expected K = {k} classes in the last axis, got {arr.shape}")
    if arr.shape[-1] < 2:
        raise GeosegError(f"{name}: expected at least 2 classes in the last axis, got {arr.shape}")
    arr = arr.astype(np.float64, copy=False)
    if not np.isfinite(arr).all():
        raise GeosegError(f"{name}: contains NaN or infinite values")
    if (arr < 0).any():
        raise GeosegError(f"{name}: probabilities must be >= 0, got min {arr.min():.3g}")
    if arr.size:
        dev = np.abs(arr.sum(axis=-1) - 1.0).max()
        if dev > sum_tol:
            raise GeosegError(
                f"{name}: each probability vector must sum to 1 (tolerance {sum_tol}), "
                f"got a deviation of {dev:.3g}"
            )
    return arr


def _log_clipped(p: np.ndarray, eps: float) -> np.ndarray:
    """``ln`` of ``p`` clipped to ``[eps, 1]`` and renormalised. ``(..., K) -> (..., K)``."""
    q = np.clip(p, eps, 1.0)
    q /= q.sum(axis=-1, keepdims=True)
    return np.log(q)


def _tempered_log(p: np.ndarray, eps: float, temperature: float) -> np.ndarray:
    """``ln softmax(ln p / T)`` of clipped ``p``: the log-probabilities the network would give
    with its logits divided by ``T``. ``(..., K) -> (..., K)``."""
    log_p = _log_clipped(p, eps)
    if temperature == 1.0:
        return log_p
    log_p /= temperature
    return log_p - logsumexp(log_p, axis=-1, keepdims=True)


def temper(probs: Any, temperature: float, *, eps: float = DEFAULT_EPS) -> np.ndarray:
    """Soften (``T > 1``) or sharpen (``T < 1``) probability vectors: ``softmax(ln p / T)``,
    which equals the softmax of the network's logits divided by ``T``; clipped to ``eps``.
    ``(..., K) -> (..., K)`` float64, same argmax."""
    check_positive("temperature", temperature)
    arr = _as_probs("probs", probs, None)
    return np.exp(_tempered_log(arr, eps, float(temperature)))


def sufficient_statistics(
    probs: Any, *, eps: float = DEFAULT_EPS, temperature: float = 1.0
) -> tuple[np.ndarray, int]:
    """The statistics of eq. 4.6: ``ln t_i = sum_q ln q_i`` and the sample count ``m``.

    Args:
        probs: ``(N, K)`` probability vectors (rows sum to 1).
        eps: clip floor before the logarithm (see the module docstring).
        temperature: the statistics are those of :func:`temper`-ed vectors (1: unchanged).

    Returns:
        ``(log_t (K,), m)``.
    """
    check_positive("temperature", temperature)
    arr = _as_probs("probs", probs, None)
    if arr.ndim != 2 or arr.shape[0] == 0:
        raise GeosegError(f"probs: expected a non-empty (N, K) array, got shape {arr.shape}")
    log_t = np.zeros(arr.shape[1], dtype=np.float64)
    for start in range(0, arr.shape[0], _CHUNK):
        log_t += _tempered_log(arr[start : start + _CHUNK], eps, float(temperature)).sum(axis=0)
    return log_t, int(arr.shape[0])


# ----------------------------------------------------------------------------- cost (4.7-4.8)


def dirichlet_cost(alpha: np.ndarray, log_t: np.ndarray, m: float, lam: float = 1.0) -> float:
    """Eq. 4.7: ``m ln B(alpha) + sum (1 - alpha_i) ln t_i + lam sum exp(-alpha_i)``.

    Args:
        alpha: ``(K,)`` positive concentration parameters.
        log_t: ``(K,)`` sums over the samples of ``ln x_i``.
        m: number of samples.
        lam: weight of the exponential barrier.
    """
    alpha = np.asarray(alpha, dtype=np.float64)
    log_beta = gammaln(alpha).sum() - gammaln(alpha.sum())
    return float(m * log_beta + ((1.0 - alpha) * log_t).sum() + lam * np.exp(-alpha).sum())


def dirichlet_cost_grad(
    alpha: np.ndarray, log_t: np.ndarray, m: float, lam: float = 1.0
) -> np.ndarray:
    """Eq. 4.8: ``m (psi(alpha_l) - psi(sum alpha)) - ln t_l - lam exp(-alpha_l)``. ``(K,)``."""
    alpha = np.asarray(alpha, dtype=np.float64)
    return m * (digamma(alpha) - digamma(alpha.sum())) - log_t - lam * np.exp(-alpha)


def dirichlet_log_density(
    alpha: np.ndarray, probs: Any, *, eps: float = DEFAULT_EPS, temperature: float = 1.0
) -> np.ndarray:
    """Log of the Dirichlet density (thesis eq. 1.70) of each probability vector.

    Args:
        alpha: ``(K,)`` concentration parameters.
        probs: ``(..., K)`` probability vectors.
        eps: clip floor before the logarithm.
        temperature: the density of the :func:`temper`-ed vectors (1: of ``probs`` itself).

    Returns:
        ``(...)`` log-densities, float64.
    """
    alpha = np.asarray(alpha, dtype=np.float64)
    arr = _as_probs("probs", probs, alpha.shape[0])
    log_norm = gammaln(alpha.sum()) - gammaln(alpha).sum()
    return log_norm + _tempered_log(arr, eps, float(temperature)) @ (alpha - 1.0)


def _moments_init(probs_mean: np.ndarray, probs_sq: np.ndarray) -> np.ndarray:
    """Method-of-moments start: ``alpha = mean * s`` with ``s`` from the first component variance."""
    var = max(float(probs_sq[0] - probs_mean[0] ** 2), 1e-12)
    s = probs_mean[0] * (1.0 - probs_mean[0]) / var - 1.0
    s = float(np.clip(s, 0.1, 1e4))
    return np.maximum(probs_mean * s, 0.05)


# ----------------------------------------------------------------------------- filters


@dataclass(frozen=True)
class PointClassification:
    """The 3D rule of §4.2.3 for ``N`` map points.

    Attributes:
        is_building: ``(N,)`` bool, ``score(P_Z) > threshold``.
        score: ``(N,)`` float64 score of the mean distribution (log-density for the Dirichlet
            filter, building probability for the baseline).
        weight: ``(N,)`` float64 ``W_q``: the density ``D(P_Z)`` itself for the Dirichlet
            filter (thesis, unnormalised, capped at the largest float64), the building
            probability for the baseline.
        normalized_weight: ``(N,)`` float64 in ``[0, 1]``, the fraction of the held-out
            true-building calibration scores below ``score`` (NaN before calibration).
        mean_probs: ``(N, K)`` the mean distributions ``P_Z`` (eq. 4.9).
    """

    is_building: np.ndarray
    score: np.ndarray
    weight: np.ndarray
    normalized_weight: np.ndarray
    mean_probs: np.ndarray


class _ScoreFilter:
    """Shared logic: a per-vector score, a threshold, keep masks, the 3D rule and JSON I/O."""

    kind: ClassVar[str] = ""

    def __init__(
        self, *, num_classes: int = NUM_CLASSES, building_class: int = BUILDING, window: int = 1
    ) -> None:
        if not isinstance(num_classes, int) or num_classes < 2:
            raise GeosegError(f"num_classes: expected an int >= 2, got {num_classes!r}")
        if not isinstance(building_class, int) or not 0 <= building_class < num_classes:
            raise GeosegError(
                f"building_class: expected an int in [0, {num_classes}), got {building_class!r}"
            )
        if isinstance(window, bool) or not isinstance(window, int) or window < 1 or window % 2 == 0:
            raise GeosegError(f"window: expected an odd int >= 1, got {window!r}")
        self.num_classes = num_classes
        self.building_class = building_class
        self.window = window
        self.threshold: float | None = None
        self.calibration: np.ndarray | None = None  # sorted quantiles of held-out scores

    # -- to override
    def score(self, probs: Any) -> np.ndarray:
        """Score of each probability vector, ``(..., K) -> (...)``; higher = more building."""
        raise NotImplementedError

    def _weight(self, score: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _params(self) -> dict[str, Any]:
        return {}

    @classmethod
    def _from_params(cls, params: dict[str, Any], common: dict[str, Any]) -> _ScoreFilter:
        raise NotImplementedError

    # -- shared
    def smooth(self, probs: Any) -> np.ndarray:
        """Mean probability vector over the ``window x window`` box around each pixel (the
        image border repeats its edge pixels); the input itself when ``window`` is 1.

        Args:
            probs: ``(..., H, W, K)`` probability maps.

        Returns:
            ``(..., H, W, K)`` float64 probability maps (each vector still sums to 1).
        """
        arr = _as_probs("probs", probs, self.num_classes)
        if arr.ndim < 3:
            raise GeosegError(f"probs: expected maps of shape (..., H, W, K), got {arr.shape}")
        if self.window == 1:
            return arr
        size = (1,) * (arr.ndim - 3) + (self.window, self.window, 1)
        # the running sums leave ~1e-16 negatives where a probability is 0
        return np.maximum(uniform_filter(arr, size=size, mode="nearest"), 0.0)

    def smooth_at(self, probs: Any, rows: Any, cols: Any) -> np.ndarray:
        """:meth:`smooth`'s vectors at a few pixels only: the same box means (edge pixels
        repeat), without smoothing the whole map (the bridge samples a few hundred pixels of
        each keyframe's map).

        Args:
            probs: ``(H, W, K)`` probability map.
            rows: ``(N,)`` pixel rows in ``[0, H)``.
            cols: ``(N,)`` pixel columns in ``[0, W)``.

        Returns:
            ``(N, K)`` float64 probability vectors.
        """
        arr = np.asarray(probs.detach().cpu().numpy() if hasattr(probs, "detach") else probs)
        if arr.ndim != 3:
            raise GeosegError(f"probs: expected a map of shape (H, W, K), got {arr.shape}")
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        cols = np.asarray(cols, dtype=np.int64).reshape(-1)
        H, W = arr.shape[:2]
        if rows.shape != cols.shape:
            raise GeosegError(f"rows {rows.shape} and cols {cols.shape} differ")
        if rows.size and (rows.min() < 0 or rows.max() >= H or cols.min() < 0 or cols.max() >= W):
            raise GeosegError(f"rows/cols: pixels outside the {W}x{H} map")
        offsets = np.arange(self.window) - self.window // 2
        rr = np.clip(rows[:, None] + offsets, 0, H - 1)  # (N, window): clipping repeats edges
        cc = np.clip(cols[:, None] + offsets, 0, W - 1)
        boxes = _as_probs("probs", arr[rr[:, :, None], cc[:, None, :]], self.num_classes)
        return np.maximum(boxes.mean(axis=(1, 2)), 0.0)

    def threshold_for_false_rejection(self, probs_true_building: Any, rate: float) -> float:
        """Pick and store the threshold that rejects a fraction ``rate`` of true building pixels.

        The threshold is the ``rate`` quantile of the held-out scores: exactly
        ``ceil(rate * N)`` of the ``N`` given vectors score ``<= threshold`` (rejected, since
        :meth:`filter` keeps ``score > threshold``). Also stores 101 quantiles of these scores,
        used by the normalised weight of :meth:`classify_points`.

        Args:
            probs_true_building: ``(N, K)`` softmax vectors of held-out pixels whose ground truth
                is building (pass only those whose argmax is building to calibrate the extra
                rejections the filter adds on top of the argmax), taken from :meth:`smooth`'s
                maps when ``window > 1``.
            rate: target false-rejection rate in ``[0, 1)``.

        Returns:
            The threshold (in score units: log-density for the Dirichlet filter).
        """
        if not isinstance(rate, int | float) or not 0.0 <= rate < 1.0:
            raise GeosegError(f"rate: expected a number in [0, 1), got {rate!r}")
        arr = _as_probs("probs_true_building", probs_true_building, self.num_classes)
        if arr.ndim != 2 or arr.shape[0] == 0:
            raise GeosegError(
                f"probs_true_building: expected a non-empty (N, K) array, got shape {arr.shape}"
            )
        scores = np.sort(self.score(arr))
        n = scores.shape[0]
        n_reject = int(np.ceil(rate * n - 1e-9))
        if n_reject == 0:
            thr = float(np.nextafter(scores[0], -np.inf))
        else:
            thr = float(scores[n_reject - 1])
        self.threshold = thr
        self.calibration = np.quantile(scores, np.linspace(0.0, 1.0, _N_CALIBRATION_QUANTILES))
        logger.info("%s threshold %.6g for false-rejection rate %.3f", self.kind, thr, rate)
        return thr

    def _require_threshold(self, threshold: float | None) -> float:
        thr = self.threshold if threshold is None else threshold
        if thr is None:
            raise GeosegError(
                "threshold: not set; call threshold_for_false_rejection() or pass threshold="
            )
        if (
            isinstance(thr, bool)
            or not isinstance(thr, int | float | np.number)
            or not np.isfinite(thr)
        ):
            raise GeosegError(f"threshold: expected a finite number, got {thr!r}")
        return float(thr)

    def filter(
        self, probs: Any, labels: Any = None, *, threshold: float | None = None
    ) -> np.ndarray:
        """Keep mask of building pixels whose score exceeds the threshold.

        Args:
            probs: an ``(H, W, K)`` probability map (scored through :meth:`smooth`) or
                ``(N, K)`` vectors, scored as given: with ``window > 1`` pass vectors taken
                from :meth:`smooth`'s maps.
            labels: ``(H, W)`` or ``(N,)`` integer labels; the argmax of ``probs`` (before
                smoothing) when None.
            threshold: overrides the stored threshold.

        Returns:
            ``(H, W)`` or ``(N,)`` bool: label is building and score > threshold.
        """
        thr = self._require_threshold(threshold)
        arr = _as_probs("probs", probs, self.num_classes)
        if arr.ndim not in (2, 3):
            raise GeosegError(f"probs: expected shape (H, W, K) or (N, K), got {arr.shape}")
        if labels is None:
            lab = arr.argmax(axis=-1)
        else:
            lab = np.asarray(labels.detach().cpu() if hasattr(labels, "detach") else labels)
            if lab.shape != arr.shape[:-1]:
                raise GeosegError(f"labels: expected shape {arr.shape[:-1]}, got {lab.shape}")
            if not np.issubdtype(lab.dtype, np.integer):
                raise GeosegError(f"labels: expected integer class ids, got dtype {lab.dtype}")
        keep = lab == self.building_class
        out = np.zeros(lab.shape, dtype=bool)
        if keep.any():
            scored = self.smooth(arr) if arr.ndim == 3 else arr
            out[keep] = self.score(scored[keep]) > thr
        return out

    def classify_points(
        self, point_probs: Any, *, threshold: float | None = None
    ) -> PointClassification:
        """The 3D rule of §4.2.3 (eq. 4.9) for map points seen in several keyframes.

        Args:
            point_probs: ``(N, V, K)`` distributions of ``N`` points in ``V`` observations each,
                or a sequence of ``N`` arrays ``(V_n, K)`` (ragged observation counts).
            threshold: overrides the stored threshold ``t_D``.

        Returns:
            :class:`PointClassification` (flag, score, ``W_q``, normalised weight, ``P_Z``).
        """
        thr = self._require_threshold(threshold)
        if isinstance(point_probs, list | tuple):
            if len(point_probs) == 0:
                raise GeosegError("point_probs: expected at least one point, got none")
            means = []
            for i, p in enumerate(point_probs):
                a = _as_probs(f"point_probs[{i}]", p, self.num_classes)
                if a.ndim != 2 or a.shape[0] == 0:
                    raise GeosegError(
                        f"point_probs[{i}]: expected a non-empty (V, K) array, got {a.shape}"
                    )
                means.append(a.mean(axis=0))
            mean_probs = np.stack(means)
        else:
            a = _as_probs("point_probs", point_probs, self.num_classes)
            if a.ndim != 3 or a.shape[1] == 0:
                raise GeosegError(f"point_probs: expected shape (N, V, K), got {a.shape}")
            mean_probs = a.mean(axis=1)
        score = self.score(mean_probs)
        if self.calibration is None:
            norm = np.full(score.shape, np.nan)
        else:
            qs = np.linspace(0.0, 1.0, self.calibration.shape[0])
            norm = np.interp(score, self.calibration, qs, left=0.0, right=1.0)
        return PointClassification(
            is_building=score > thr,
            score=score,
            weight=self._weight(score),
            normalized_weight=norm,
            mean_probs=mean_probs,
        )

    # -- persistence
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (format name, version, kind, parameters, threshold)."""
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "kind": self.kind,
            "num_classes": self.num_classes,
            "building_class": self.building_class,
            "window": self.window,
            "threshold": self.threshold,
            "calibration": None if self.calibration is None else self.calibration.tolist(),
            **self._params(),
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write the filter as JSON (atomically: temp file + rename), with the SHA-256 of its
        content (key ``"sha256"``, checked by :func:`load_filter`). Returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, json.dumps(seal(self.to_dict()), indent=2))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> _ScoreFilter:
        """Read a filter written by :meth:`save`; raises GeosegError naming the file."""
        obj = load_filter(path)
        if cls.kind and obj.kind != cls.kind:
            raise GeosegError(f"{path}: holds a {obj.kind!r} filter, expected {cls.kind!r}")
        return obj


class DirichletFilter(_ScoreFilter):
    """Dirichlet model of true-building softmax vectors (eqs. 4.3-4.9).

    Args:
        num_classes: ``K``.
        building_class: the class id the filter acts on.
        window: odd side of the box the probability maps are averaged over before scoring
            (:meth:`smooth`); 1 = per pixel, as in the thesis.
        lam: barrier weight ``lambda`` of eq. 4.7.
        eps: probability clip floor before logarithms.
        temperature: ``T``; the filter models the tempered vectors ``softmax(ln p / T)``
            (:func:`temper`) in fit and scoring alike. 1 is the thesis. An over-confident
            network puts nearly all true-building vectors at the simplex corner (fitted
            ``alpha_i`` ~0.1), where a false positive's density differs from a true pixel's
            mostly through the building probability; ``T > 1`` spreads the vectors so the
            secondary classes weigh in (the naive CNN: T = 5, see configs/dirichlet.yaml).

    Attributes:
        alpha: ``(K,)`` fitted concentration parameters (None before :meth:`fit`).
        threshold: log-density threshold ``ln t_D`` (None before calibration).
    """

    kind: ClassVar[str] = "dirichlet"

    def __init__(
        self,
        *,
        num_classes: int = NUM_CLASSES,
        building_class: int = BUILDING,
        window: int = 1,
        lam: float = 1.0,
        eps: float = DEFAULT_EPS,
        temperature: float = 1.0,
        alpha: Any = None,
    ) -> None:
        super().__init__(num_classes=num_classes, building_class=building_class, window=window)
        check_positive("lam", lam, strict=False)
        check_positive("eps", eps)
        check_positive("temperature", temperature)
        if eps >= 1.0 / num_classes:
            raise GeosegError(f"eps: expected < 1/K = {1.0 / num_classes:.3g}, got {eps}")
        self.lam = float(lam)
        self.eps = float(eps)
        self.temperature = float(temperature)
        self.alpha: np.ndarray | None = None
        if alpha is not None:
            a = np.asarray(alpha, dtype=np.float64)
            if a.shape != (num_classes,) or not np.isfinite(a).all() or (a <= 0).any():
                raise GeosegError(f"alpha: expected {num_classes} finite values > 0, got {a}")
            self.alpha = a

    def fit(self, probs: Any, *, max_iter: int = 500) -> DirichletFilter:
        """Fit ``alpha`` by L-BFGS-B on eq. 4.7 with the analytic gradient of eq. 4.8.

        Args:
            probs: ``(N, K)`` softmax vectors of true building pixels (``D_build``, eq. 4.3),
                taken from :meth:`smooth`'s maps when ``window > 1``.
            max_iter: L-BFGS-B iteration cap.

        Returns:
            self.
        """
        arr = _as_probs("probs", probs, self.num_classes)
        if arr.ndim != 2 or arr.shape[0] < 2:
            raise GeosegError(f"probs: expected an (N >= 2, K) array, got shape {arr.shape}")
        t0 = time.perf_counter()
        # one chunked pass over the samples: ln t (eq. 4.6) and the moments of the start point
        m = arr.shape[0]
        log_t = np.zeros(self.num_classes)
        mean = np.zeros(self.num_classes)
        sq = np.zeros(self.num_classes)
        for start in range(0, m, _CHUNK):
            log_chunk = _tempered_log(arr[start : start + _CHUNK], self.eps, self.temperature)
            chunk = np.exp(log_chunk)
            log_t += log_chunk.sum(axis=0)
            mean += chunk.sum(axis=0)
            sq += np.square(chunk).sum(axis=0)
        self._optimise(log_t, m, _moments_init(mean / m, sq / m), max_iter)
        logger.info("Dirichlet fit on %d vectors in %.3f s", m, time.perf_counter() - t0)
        return self

    def fit_statistics(self, log_t: Any, m: int, *, max_iter: int = 500) -> DirichletFilter:
        """Fit ``alpha`` from accumulated statistics (streaming over many images).

        Args:
            log_t: ``(K,)`` ``sum_q ln q_i`` over the samples, with the same clip floor ``eps``
                and temperature (see :func:`sufficient_statistics`; sums of several calls add
                up).
            m: number of samples behind ``log_t``.
            max_iter: L-BFGS-B iteration cap.

        Returns:
            self.
        """
        lt = np.asarray(log_t, dtype=np.float64)
        if lt.shape != (self.num_classes,) or not np.isfinite(lt).all() or (lt > 0).any():
            raise GeosegError(
                f"log_t: expected {self.num_classes} finite values <= 0, got {np.array2string(lt)}"
            )
        if isinstance(m, bool) or not isinstance(m, int | np.integer) or m < 2:
            raise GeosegError(f"m: expected an int >= 2, got {m!r}")
        # start: the mean distribution implied by the geometric means, concentration 1 per class
        g = np.exp(lt / m)
        self._optimise(lt, int(m), np.maximum(g / g.sum() * self.num_classes, 0.05), max_iter)
        return self

    def _optimise(self, log_t: np.ndarray, m: int, alpha0: np.ndarray, max_iter: int) -> None:
        mean_log = log_t / m
        lam_m = self.lam / m

        def fun(a: np.ndarray) -> tuple[float, np.ndarray]:
            return (
                dirichlet_cost(a, mean_log, 1.0, lam_m),
                dirichlet_cost_grad(a, mean_log, 1.0, lam_m),
            )

        res = minimize(
            fun,
            alpha0,
            jac=True,
            method="L-BFGS-B",
            bounds=[(ALPHA_MIN, None)] * self.num_classes,
            options={"maxiter": max_iter, "ftol": 1e-15, "gtol": 1e-10},
        )
        if not np.isfinite(res.x).all():
            raise GeosegError(f"probs: the Dirichlet fit diverged ({res.message})")
        if not res.success:
            logger.warning("Dirichlet fit did not fully converge: %s", res.message)
        self.alpha = np.asarray(res.x, dtype=np.float64)
        logger.debug(
            "L-BFGS-B: %d iterations, alpha=%s", res.nit, np.array2string(self.alpha, precision=4)
        )

    def _require_alpha(self) -> np.ndarray:
        if self.alpha is None:
            raise GeosegError("alpha: the filter is not fitted; call fit() or load()")
        return self.alpha

    def log_density(self, probs: Any) -> np.ndarray:
        """Log Dirichlet density of each vector. ``(..., K)`` -> ``(...)``, float64."""
        return dirichlet_log_density(
            self._require_alpha(), probs, eps=self.eps, temperature=self.temperature
        )

    def score(self, probs: Any) -> np.ndarray:
        """The log-density (same as :meth:`log_density`)."""
        return self.log_density(probs)

    def _weight(self, score: np.ndarray) -> np.ndarray:
        # W_q = D(P_Z) as in the thesis; capped so that it stays finite.
        return np.exp(np.minimum(score, np.log(np.finfo(np.float64).max)))

    def _params(self) -> dict[str, Any]:
        return {
            "alpha": None if self.alpha is None else self.alpha.tolist(),
            "lam": self.lam,
            "eps": self.eps,
            "temperature": self.temperature,
        }

    @classmethod
    def _from_params(cls, params: dict[str, Any], common: dict[str, Any]) -> DirichletFilter:
        return cls(
            lam=_field(params, "lam", "number", default=1.0),
            eps=_field(params, "eps", "number", default=DEFAULT_EPS),
            temperature=_field(params, "temperature", "number", default=1.0),
            alpha=_field(params, "alpha", "numbers", default=None, k=common["num_classes"]),
            **common,
        )


class MaxProbabilityFilter(_ScoreFilter):
    """Baseline: keep building pixels whose building probability exceeds a threshold.

    Same API as :class:`DirichletFilter` (``num_classes``, ``building_class``, ``window``); its
    score and weight are the building probability.
    """

    kind: ClassVar[str] = "max_probability"

    def fit(self, probs: Any | None = None) -> MaxProbabilityFilter:
        """No parameters to learn; validates ``probs`` (``(N, K)``) when given. Returns self."""
        if probs is not None:
            _as_probs("probs", probs, self.num_classes)
        return self

    def score(self, probs: Any) -> np.ndarray:
        """Building probability. ``(..., K)`` -> ``(...)``, float64."""
        return _as_probs("probs", probs, self.num_classes)[..., self.building_class]

    def _weight(self, score: np.ndarray) -> np.ndarray:
        return score.copy()

    @classmethod
    def _from_params(cls, params: dict[str, Any], common: dict[str, Any]) -> MaxProbabilityFilter:
        return cls(**common)


_KINDS: dict[str, type[_ScoreFilter]] = {
    DirichletFilter.kind: DirichletFilter,
    MaxProbabilityFilter.kind: MaxProbabilityFilter,
}


def _field(data: dict[str, Any], key: str, kind: str, *, default: Any = ..., k: int = 0) -> Any:
    """One field of a filter file, type-checked: ``int`` (a JSON integer, not ``true`` nor
    ``8.9`` nor ``"8"``), ``number`` (a finite JSON number), ``numbers`` (a list of finite
    numbers; ``k > 0``: exactly ``k``), or None where ``default`` is None.

    Raises:
        GeosegError: naming the key, the expected type and what came.
    """
    if key not in data:
        if default is ...:
            raise GeosegError(f"{key}: missing")
        return default
    value = data[key]
    if value is None and default is None:
        return None

    def number(v: Any) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)

    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise GeosegError(f"{key}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if kind == "number":
        if not number(value):
            raise GeosegError(
                f"{key}: expected a finite number, got {type(value).__name__} {value!r}"
            )
        return float(value)
    if not isinstance(value, list) or not all(number(v) for v in value):
        shown = repr(value)[:80]
        raise GeosegError(f"{key}: expected a list of finite numbers, got {shown}")
    if k and len(value) != k:
        raise GeosegError(f"{key}: expected {k} numbers, got {len(value)}")
    return [float(v) for v in value]


_COMMON_KEYS = {"format", "version", "kind", "num_classes", "building_class", "window"}
_COMMON_KEYS |= {"threshold", "calibration", DIGEST_KEY}
_PARAM_KEYS = {"dirichlet": {"alpha", "lam", "eps", "temperature"}, "max_probability": set()}


def load_filter(path: str | os.PathLike) -> DirichletFilter | MaxProbabilityFilter:
    """Read any filter written by ``save``; raises GeosegError naming the file and the problem.

    Every field is checked for its type and finiteness (a NaN threshold would reject every
    pixel, a NaN calibration give NaN weights), then the file's SHA-256 (embedded, else the
    model card's, :mod:`geoseg.integrity`).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise GeosegError(f"{path}: no such filter file") from exc
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GeosegError(f"{path}: not a readable JSON filter file ({exc})") from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT_NAME:
        raise GeosegError(f"{path}: not a geoseg filter file (format != {FORMAT_NAME!r})")
    if data.get("version") != FORMAT_VERSION or isinstance(data.get("version"), bool):
        raise GeosegError(
            f"{path}: unsupported filter format version {data.get('version')!r} "
            f"(this geoseg reads version {FORMAT_VERSION})"
        )
    kind = data.get("kind")
    cls = _KINDS.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise GeosegError(f"{path}: unknown filter kind {data.get('kind')!r}")
    unknown = sorted(set(data) - _COMMON_KEYS - _PARAM_KEYS[kind])
    if unknown:
        raise GeosegError(f"{path}: unknown key(s) {unknown} for a {kind} filter")
    try:
        common = {
            "num_classes": _field(data, "num_classes", "int"),
            "building_class": _field(data, "building_class", "int"),
            "window": _field(data, "window", "int", default=1),
        }
        obj = cls._from_params(data, common)
        obj.threshold = _field(data, "threshold", "number", default=None)
        cal = _field(data, "calibration", "numbers", default=None)
        if cal is not None and (len(cal) < 2 or np.any(np.diff(cal) < 0)):
            raise GeosegError("calibration: expected >= 2 non-decreasing quantiles")
        obj.calibration = None if cal is None else np.asarray(cal, dtype=np.float64)
    except GeosegError as exc:
        raise GeosegError(f"{path}: {exc}") from exc
    verify_payload(data, path)
    return obj  # type: ignore[return-value]
