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
sampled from the maps as given: pass the ``smooth`` of the Dirichlet filter that will score them
(:meth:`geoseg.dirichlet.DirichletFilter.smooth`, a 5x5 mean for the shipped filter) so that
the points see the vectors the filter was calibrated on.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from slam_bridge.errors import SlamError
from slam_bridge.slam.map import Map

__all__ = ["PointEvidence"]

PROB_SUM, VOTES, SAMPLES = "bridge.prob_sum", "bridge.votes", "bridge.samples"
NORMAL_SUM, NORMAL_SAMPLES = "bridge.normal_sum", "bridge.normal_samples"
SUM_TOL = 1e-3  # a probability vector must sum to 1 within this


class PointEvidence:
    """Accumulates network outputs on a map's points (module docstring).

    Args:
        slam_map: the map; the attributes are registered on it.
        num_classes: ``K``, the length of the probability vectors.
        smooth: applied to each ``(H, W, K)`` probability map before sampling (None: as given).
    """

    def __init__(
        self,
        slam_map: Map,
        num_classes: int,
        smooth: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        if not isinstance(num_classes, int) or num_classes < 2:
            raise SlamError(f"num_classes: expected an int >= 2, got {num_classes!r}")
        self.map = slam_map
        self.num_classes = num_classes
        self.smooth = smooth
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
            probs: ``(H, W, K)`` class probabilities at the image size of the map.
            normals: ``(H, W, 3)`` unit normals in the camera frame (OpenCV axes), zero rows
                where the network gives none; None: no normals (the 2015 network).

        Returns:
            The number of observations sampled.

        Raises:
            SlamError: ``k`` added already or not a keyframe; maps of the wrong size or class
                count, non-finite values, probability vectors that do not sum to 1.
        """
        m = self.map
        if not 0 <= k < m.num_keyframes:
            raise SlamError(f"keyframe {k}: the map has {m.num_keyframes} keyframes")
        if k in self.added:
            raise SlamError(f"keyframe {k}: its network outputs were added already")
        W, H = m.image_size
        probs = np.asarray(probs, dtype=np.float64)
        if probs.shape != (H, W, self.num_classes):
            raise SlamError(
                f"keyframe {k}: probs of shape {probs.shape}, expected (H, W, K) = "
                f"{(H, W, self.num_classes)} (the map's image size, the class count)"
            )
        if not np.isfinite(probs).all():
            raise SlamError(f"keyframe {k}: the probability map holds NaN or infinite values")
        if self.smooth is not None:
            probs = np.asarray(self.smooth(probs), dtype=np.float64)
        obs = m.keyframe_observations(k)
        obs = obs[m.obs_active[obs]]
        cols = np.clip(np.rint(m.obs_uv[obs, 0]).astype(np.int64), 0, W - 1)
        rows = np.clip(np.rint(m.obs_uv[obs, 1]).astype(np.int64), 0, H - 1)
        p = probs[rows, cols]
        if np.any(np.abs(p.sum(axis=1) - 1.0) > SUM_TOL) or np.any(p < 0):
            raise SlamError(f"keyframe {k}: probability vectors must be >= 0 and sum to 1")
        pts = m.obs_point[obs]
        np.add.at(m.attribute(PROB_SUM), pts, p)
        np.add.at(m.attribute(VOTES), (pts, p.argmax(axis=1)), 1)
        np.add.at(m.attribute(SAMPLES), pts, 1)
        if normals is not None:
            normals = np.asarray(normals, dtype=np.float64)
            if normals.shape != (H, W, 3):
                raise SlamError(
                    f"keyframe {k}: normals of shape {normals.shape}, expected {(H, W, 3)}"
                )
            if not np.isfinite(normals).all():
                raise SlamError(f"keyframe {k}: the normal map holds NaN or infinite values")
            n_c = normals[rows, cols]
            norm = np.linalg.norm(n_c, axis=1)
            ok = norm > 0.5  # zero rows: no normal there
            n_w = (n_c[ok] / norm[ok, None]) @ m.R_wc[k].T
            np.add.at(m.attribute(NORMAL_SUM), pts[ok], n_w)
            np.add.at(m.attribute(NORMAL_SAMPLES), pts[ok], 1)
        self.added.add(k)
        return int(obs.size)

    @property
    def samples(self) -> np.ndarray:
        """``(P,)`` observations whose probabilities each point holds."""
        return self.map.attribute(SAMPLES)

    def mean_probs(self) -> np.ndarray:
        """``(P, K)`` mean probability vector ``P_Z`` of each point (NaN rows: no evidence)."""
        n = self.samples
        out = np.full((n.size, self.num_classes), np.nan)
        seen = n > 0
        out[seen] = self.map.attribute(PROB_SUM)[seen] / n[seen, None]
        return out

    def labels(self) -> np.ndarray:
        """``(P,)`` majority vote of each point's observations (-1: no evidence; a tie goes to
        the lower class id)."""
        votes = self.map.attribute(VOTES)
        return np.where(self.samples > 0, votes.argmax(axis=1), -1)

    def normals(self) -> np.ndarray:
        """``(P, 3)`` normalised mean of each point's world-frame normals (NaN rows: none, or
        observed normals that cancel out)."""
        s = self.map.attribute(NORMAL_SUM)
        norm = np.linalg.norm(s, axis=1)
        out = np.full(s.shape, np.nan)
        ok = (self.map.attribute(NORMAL_SAMPLES) > 0) & (norm > 1e-6)
        out[ok] = s[ok] / norm[ok, None]
        return out
