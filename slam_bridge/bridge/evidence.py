"""Network evidence per map point: the 2D -> 3D step of the bridge (thesis §4.2.3, §4.3.3.2).

Each keyframe's network outputs, a class-probability map and (for the joint network) a
camera-frame normal map, are sampled at the pixels of the keyframe's observations and added to
the observed points' running sums, kept as per-point attributes of the
:class:`~slam_bridge.slam.map.Map`:

* ``bridge.prob_sum`` ``(P, K)``: the sum of the probability vectors; their mean is the
  ``P_Z`` of eq. 4.9 that the Dirichlet rule scores;
* ``bridge.votes`` ``(P, K)``: one vote per observation for its pixel's most probable class
  (the point's label is the majority);
* ``bridge.normal_sum`` ``(P, 3)``: the sum of the observed unit normals rotated into the world
  frame with the keyframe's pose when it is added (the later fusion turns a keyframe by a
  fraction of a degree); the point's normal is the normalised sum;
* ``bridge.samples`` / ``bridge.normal_samples`` ``(P,)``: how many vectors each sum holds.

Points gain evidence as they are re-observed; each keyframe is added once. Probabilities are
sampled from the maps as given: pass the ``smooth_at`` of the Dirichlet filter that will score
them (:meth:`geoseg.dirichlet.DirichletFilter.smooth_at`, 5x5 means for the shipped filter) so
that the points see the vectors the filter was calibrated on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np

from geoseg.errors import GeosegError
from slam_bridge.errors import SlamError
from slam_bridge.slam.map import Map

__all__ = ["OutputSamples", "PixelSampler", "PointEvidence", "sample_outputs"]

PROB_SUM, VOTES, SAMPLES = "bridge.prob_sum", "bridge.votes", "bridge.samples"
NORMAL_SUM, NORMAL_SAMPLES = "bridge.normal_sum", "bridge.normal_samples"
SUM_TOL = 1e-3  # a probability vector must sum to 1 within this
#: ``(probs (h, w, K), rows (N,), cols (N,)) -> (N, K)``: the vectors a map gives at some pixels
PixelSampler: TypeAlias = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class OutputSamples:
    """Network outputs at ``N`` observation pixels of one keyframe.

    Attributes:
        probs: ``(N, K)`` probability vectors.
        normals_w: ``(N, 3)`` unit normals in the world frame (rows without a normal: 0), or
            None without a normal map.
        has_normal: ``(N,)`` bool, the network gave a normal there.
    """

    probs: np.ndarray
    normals_w: np.ndarray | None
    has_normal: np.ndarray


def sample_outputs(
    probs: np.ndarray,
    normals: np.ndarray | None,
    uv: np.ndarray,
    R_wc: np.ndarray,
    image_size: tuple[int, int],
    num_classes: int,
    smooth_at: PixelSampler | None = None,
) -> OutputSamples:
    """Sample one keyframe's network maps at its observation pixels (nearest map pixel).

    Args:
        probs: ``(h, w, K)`` class probabilities; ``(w, h)`` is the image size or a scaling of
            it (pixel ``u`` of the image is ``(u + 0.5) w / W - 0.5`` of the map).
        normals: ``(h, w, 3)`` camera-frame unit normals (zero rows: none), or None.
        uv: ``(N, 2)`` observation pixels of the image.
        R_wc: ``(3, 3)`` the keyframe's rotation, to turn normals into the world frame (not
            finite: a keyframe the SLAM could not place, whose normals are left out).
        image_size: ``(W, H)`` of the image.
        num_classes: ``K``.
        smooth_at: the vectors at the sampled pixels (e.g. the box means of
            :meth:`geoseg.dirichlet.DirichletFilter.smooth_at`; None: the pixels' own).

    Raises:
        SlamError: maps of another aspect ratio or class count, normals of another size,
            non-finite values, probability vectors that are negative or do not sum to 1.
    """
    W, H = image_size
    probs = np.asarray(probs)
    if probs.ndim != 3 or probs.shape[2] != num_classes:
        raise SlamError(f"probs: expected (h, w, {num_classes}) maps, got shape {probs.shape}")
    h, w = probs.shape[:2]
    if abs(W * h / H - w) > 1.0:  # the same aspect ratio, to a pixel of rounding
        raise SlamError(f"probs: {w}x{h} maps for {W}x{H} images (not the same aspect ratio)")
    if not np.isfinite(probs).all():
        raise SlamError("probs: the probability map holds NaN or infinite values")
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    cols = np.clip(np.rint((uv[:, 0] + 0.5) * w / W - 0.5).astype(np.int64), 0, w - 1)
    rows = np.clip(np.rint((uv[:, 1] + 0.5) * h / H - 0.5).astype(np.int64), 0, h - 1)
    try:
        sampled = probs[rows, cols] if smooth_at is None else smooth_at(probs, rows, cols)
    except GeosegError as exc:  # the sampler's own checks (a filter's): this module's error
        raise SlamError(f"probs: {exc}") from exc
    p = np.asarray(sampled, dtype=np.float64)
    if np.any(np.abs(p.sum(axis=1) - 1.0) > SUM_TOL) or np.any(p < 0):
        raise SlamError("probs: probability vectors must be >= 0 and sum to 1")
    R_wc = np.asarray(R_wc, dtype=np.float64)
    if normals is None or not np.isfinite(R_wc).all():  # a keyframe the SLAM could not place
        return OutputSamples(p, None, np.zeros(p.shape[0], bool))
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != (h, w, 3):
        raise SlamError(f"normals of shape {normals.shape}, expected {(h, w, 3)} like probs")
    if not np.isfinite(normals).all():
        raise SlamError("normals: the normal map holds NaN or infinite values")
    n_c = normals[rows, cols]
    norm = np.linalg.norm(n_c, axis=1)
    ok = norm > 0.5  # zero rows: no normal there
    n_w = np.zeros_like(n_c)
    n_w[ok] = (n_c[ok] / norm[ok, None]) @ R_wc.T
    return OutputSamples(p, n_w, ok)


class PointEvidence:
    """Accumulates network outputs on a map's points (module docstring).

    Args:
        slam_map: the map; the attributes are registered on it.
        num_classes: ``K``, the length of the probability vectors.
        smooth_at: the vectors a probability map gives at the sampled pixels (None: the
            pixels' own; :func:`sample_outputs`).
    """

    def __init__(
        self,
        slam_map: Map,
        num_classes: int,
        smooth_at: PixelSampler | None = None,
    ) -> None:
        if not isinstance(num_classes, int) or num_classes < 2:
            raise SlamError(f"num_classes: expected an int >= 2, got {num_classes!r}")
        self.map = slam_map
        self.num_classes = num_classes
        self.smooth_at = smooth_at
        slam_map.add_attribute(PROB_SUM, (num_classes,), np.float64, 0.0)
        slam_map.add_attribute(VOTES, (num_classes,), np.int64, 0)
        slam_map.add_attribute(SAMPLES, (), np.int64, 0)
        slam_map.add_attribute(NORMAL_SUM, (3,), np.float64, 0.0)
        slam_map.add_attribute(NORMAL_SAMPLES, (), np.int64, 0)
        self.added: set[int] = set()

    def add_keyframe(self, k: int, probs: np.ndarray, normals: np.ndarray | None = None) -> int:
        """Add keyframe ``k``'s network outputs to the points it observes (active observations).

        Args:
            k: the keyframe.
            probs: ``(h, w, K)`` class probabilities, at the map's image size or a scaled copy
                of it (a network run on a downsized image).
            normals: ``(h, w, 3)`` unit normals in the camera frame (OpenCV axes), zero rows
                where the network gives none; None: no normals (the 2015 network).

        Returns:
            The number of observations sampled.

        Raises:
            SlamError: ``k`` added already or not a keyframe, and the errors of
                :func:`sample_outputs`.
        """
        m = self.map
        if not 0 <= k < m.num_keyframes:
            raise SlamError(f"keyframe {k}: the map has {m.num_keyframes} keyframes")
        obs = m.keyframe_observations(k)
        obs = obs[m.obs_active[obs]]
        samples = sample_outputs(
            probs, normals, m.obs_uv[obs], m.R_wc[k], m.image_size, self.num_classes,
            self.smooth_at,
        )  # fmt: skip
        self.add_samples(k, m.obs_point[obs], samples)
        return int(obs.size)

    def add_samples(self, k: int, points: np.ndarray, samples: OutputSamples) -> None:
        """Add samples taken from keyframe ``k`` (:func:`sample_outputs`) to ``points`` ``(N,)``.

        Raises:
            SlamError: ``k`` added already; samples and points of different lengths.
        """
        if k in self.added:
            raise SlamError(f"keyframe {k}: its network outputs were added already")
        points = np.asarray(points, dtype=np.int64)
        if samples.probs.shape != (points.size, self.num_classes):
            raise SlamError(f"keyframe {k}: {samples.probs.shape} samples for {points.size} points")
        m = self.map
        np.add.at(m.attribute(PROB_SUM), points, samples.probs)
        np.add.at(m.attribute(VOTES), (points, samples.probs.argmax(axis=1)), 1)
        np.add.at(m.attribute(SAMPLES), points, 1)
        if samples.normals_w is not None:
            ok = samples.has_normal
            np.add.at(m.attribute(NORMAL_SUM), points[ok], samples.normals_w[ok])
            np.add.at(m.attribute(NORMAL_SAMPLES), points[ok], 1)
        self.added.add(k)

    @property
    def samples(self) -> np.ndarray:
        """``(P,)`` observations whose probabilities each point holds."""
        return self.map.attribute(SAMPLES)

    def mean_probs(self, points: np.ndarray | None = None) -> np.ndarray:
        """``(P, K)`` mean probability vector ``P_Z`` of each point (NaN rows: no evidence);
        ``(N, K)`` of ``points`` ``(N,)`` only, when given."""
        sel = slice(None) if points is None else points
        n = self.samples[sel]
        out = np.full((n.size, self.num_classes), np.nan)
        seen = n > 0
        out[seen] = self.map.attribute(PROB_SUM)[sel][seen] / n[seen, None]
        return out

    def labels(self, points: np.ndarray | None = None) -> np.ndarray:
        """``(P,)`` majority vote of each point's observations (-1: no evidence; a tie goes to
        the lower class id); ``(N,)`` of ``points`` only, when given."""
        sel = slice(None) if points is None else points
        votes = self.map.attribute(VOTES)[sel]
        return np.where(self.samples[sel] > 0, votes.argmax(axis=1), -1)

    def normals(self, points: np.ndarray | None = None) -> np.ndarray:
        """``(P, 3)`` normalised mean of each point's world-frame normals (NaN rows: none, or
        observed normals that cancel out); ``(N, 3)`` of ``points`` only, when given."""
        sel = slice(None) if points is None else points
        s = self.map.attribute(NORMAL_SUM)[sel]
        norm = np.linalg.norm(s, axis=1)
        out = np.full(s.shape, np.nan)
        ok = (self.map.attribute(NORMAL_SAMPLES)[sel] > 0) & (norm > 1e-6)
        out[ok] = s[ok] / norm[ok, None]
        return out
