"""Which map points may be constrained to which facade: three association methods.

All three give an :class:`Association`, a facade (row of :class:`~slam_bridge.bridge.facades.
Facades`, -1 for none) and a weight per map point, for the building constraint of the fusion
(eq. 4.2, :class:`slam_bridge.factors.building.BuildingFactor`). They differ in which points
they call building points and how they choose the facade:

* :func:`associate_raycast`, the baseline of chapter 2: a point is a building point when the ray
  from the camera centre through it hits the building model's mesh; its facade is the nearest
  one. A tree or a bus shelter in front of a facade passes, which is the failure the thesis
  shows.
* :func:`associate_dirichlet`, 2015 (§4.2.3): a point is a building point when the Dirichlet
  density of its mean probability vector exceeds the filter's threshold, ``D(P_Z) > t_D``, with
  the weight ``W_q = D(P_Z)``; its facade is the nearest one.
* :func:`associate_bayes`, 2016 (§4.3.3.4, eq. 4.14): a point labelled building by the vote of
  its observations is given the facade of highest posterior among those within ``radius_m``::

      P(p_Q = i | N_Q)  ∝  Beta(s_i; 10, 1) · softmax(-d)_i,   s_i = N_Q · l_i

  with ``N_Q`` the point's mean normal, ``l_i`` facade ``i``'s normal and ``d_i`` the point's
  distance to it; a facade facing away (``s_i < 0``) has probability 0. The weight is that
  posterior.

Every method leaves a point unassociated when no facade lies within ``radius_m`` of it (the
building model does not cover it) and when it is not triangulated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import softmax
from scipy.stats import beta as beta_distribution

from geoseg.errors import check_positive, check_shape
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError

__all__ = [
    "Association",
    "nearest_facades",
    "plane_posterior",
    "associate_raycast",
    "associate_dirichlet",
    "associate_bayes",
]

BETA_A, BETA_B = 10.0, 1.0  # eq. 4.14: the prior on the cosine between point and facade normals


@dataclass(frozen=True)
class Association:
    """Facade and weight per map point.

    Attributes:
        facade: ``(P,)`` int64 facade row, -1 where the point is not associated.
        weight: ``(P,)`` float64 weight of the building constraint, 0 where not associated.
        method: ``raycast``, ``dirichlet`` or ``bayes``.
    """

    facade: np.ndarray
    weight: np.ndarray
    method: str

    @property
    def associated(self) -> np.ndarray:
        """``(P,)`` bool."""
        return self.facade >= 0


def nearest_facades(
    facades: Facades, points: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The nearest facade rectangle of each point within ``radius_m``.

    Args:
        points: ``(N, 3)`` world points (NaN rows: none).

    Returns:
        ``(facade (N,) int64, -1 when none is that close; distance (N,) metres, inf then)``.
    """
    check_positive("radius_m", radius_m)
    points = np.asarray(points, dtype=np.float64)
    check_shape("points", points, (None, 3))
    facade = np.full(points.shape[0], -1, np.int64)
    dist = np.full(points.shape[0], np.inf)
    pt, fc, d = facades.near(points, radius_m)
    order = np.lexsort((fc, d, pt))  # per point, nearest first (ties: lower facade id)
    first = order[np.r_[True, pt[order][1:] != pt[order][:-1]]] if pt.size else order
    facade[pt[first]] = fc[first]
    dist[pt[first]] = d[first]
    return facade, dist


def plane_posterior(normal: np.ndarray, plane_normals: np.ndarray, distances: np.ndarray):
    """Eq. 4.14 for one point over its candidate facades.

    Args:
        normal: ``(3,)`` the point's unit normal ``N_Q``.
        plane_normals: ``(F, 3)`` the candidates' unit normals ``l_i``.
        distances: ``(F,)`` the point's distance to each, metres.

    Returns:
        ``(F,)`` posterior, summing to 1; all zeros when every candidate faces away.
    """
    s = np.asarray(plane_normals, dtype=np.float64) @ np.asarray(normal, dtype=np.float64)
    prior = np.where(s >= 0, beta_distribution.pdf(np.clip(s, 0.0, 1.0), BETA_A, BETA_B), 0.0)
    post = prior * softmax(-np.asarray(distances, dtype=np.float64))
    total = post.sum()
    return post / total if total > 0 else post


def associate_raycast(
    facades: Facades,
    mesh,
    points: np.ndarray,
    centres: np.ndarray,
    radius_m: float = 3.0,
) -> Association:
    """The ray-cast baseline (module docstring).

    Args:
        facades: the model's facades.
        mesh: the model's mesh (:class:`trimesh.Trimesh`, ``gis/buildings_model.ply``).
        points: ``(P, 3)`` map points (NaN rows: not triangulated).
        centres: ``(P, 3)`` the camera centre each point is seen from (its latest keyframe's).
        radius_m: farthest facade.
    """
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    points = np.asarray(points, dtype=np.float64)
    centres = np.asarray(centres, dtype=np.float64)
    check_shape("points", points, (None, 3))
    check_shape("centres", centres, points.shape)
    facade, _ = nearest_facades(facades, points, radius_m)
    ray = points - centres
    length = np.linalg.norm(ray, axis=1)
    cast = (facade >= 0) & np.isfinite(length) & (length > 0)
    hit = np.zeros(points.shape[0], bool)
    if cast.any():
        hit[cast] = RayMeshIntersector(mesh).intersects_any(
            centres[cast], ray[cast] / length[cast, None]
        )
    facade = np.where(hit, facade, -1)
    return Association(facade, hit.astype(np.float64), "raycast")


def associate_dirichlet(
    facades: Facades,
    points: np.ndarray,
    mean_probs: np.ndarray,
    dirichlet_filter,
    radius_m: float = 3.0,
) -> Association:
    """The 2015 rule (module docstring).

    Args:
        facades: the model's facades.
        points: ``(P, 3)`` map points (NaN rows: not triangulated).
        mean_probs: ``(P, K)`` each point's mean probability vector (NaN rows: no evidence).
        dirichlet_filter: a calibrated :class:`geoseg.dirichlet.DirichletFilter`.
        radius_m: farthest facade.
    """
    points = np.asarray(points, dtype=np.float64)
    mean_probs = np.asarray(mean_probs, dtype=np.float64)
    check_shape("mean_probs", mean_probs, (points.shape[0], dirichlet_filter.num_classes))
    facade, _ = nearest_facades(facades, points, radius_m)
    weight = np.zeros(points.shape[0])
    use = (facade >= 0) & np.isfinite(mean_probs).all(axis=1)
    if use.any():
        rule = dirichlet_filter.classify_points(mean_probs[use][:, None, :])
        idx = np.flatnonzero(use)
        weight[idx[rule.is_building]] = rule.weight[rule.is_building]
    facade = np.where(weight > 0, facade, -1)
    return Association(facade, weight, "dirichlet")


def associate_bayes(
    facades: Facades,
    points: np.ndarray,
    labels: np.ndarray,
    normals: np.ndarray,
    building_class: int,
    radius_m: float = 3.0,
) -> Association:
    """The 2016 rule, eq. 4.14 (module docstring).

    Args:
        facades: the model's facades.
        points: ``(P, 3)`` map points (NaN rows: not triangulated).
        labels: ``(P,)`` each point's voted class (-1: no evidence).
        normals: ``(P, 3)`` each point's mean world-frame normal (NaN rows: none).
        building_class: the label of building points.
        radius_m: the radius ``r`` of the candidate facades.
    """
    points = np.asarray(points, dtype=np.float64)
    check_shape("points", points, (None, 3))
    P = points.shape[0]
    labels = np.asarray(labels)
    normals = np.asarray(normals, dtype=np.float64)
    check_shape("labels", labels, (P,))
    check_shape("normals", normals, (P, 3))
    if P and not np.all(
        np.abs(np.linalg.norm(normals[np.isfinite(normals).all(1)], axis=1) - 1) < 1e-6
    ):
        raise SlamError("normals: expected unit vectors (or NaN rows)")
    facade = np.full(P, -1, np.int64)
    weight = np.zeros(P)
    use = (labels == building_class) & np.isfinite(points).all(1) & np.isfinite(normals).all(1)
    pt, fc, d = facades.near(np.where(use[:, None], points, np.nan), radius_m)
    if pt.size == 0:
        return Association(facade, weight, "bayes")
    # eq. 4.14 for every point at once: its candidates are a run of the sorted pairs
    starts = np.r_[0, np.flatnonzero(np.diff(pt)) + 1]
    counts = np.diff(np.r_[starts, pt.size])
    e = np.exp(-(d - np.repeat(np.minimum.reduceat(d, starts), counts)))
    soft = e / np.repeat(np.add.reduceat(e, starts), counts)
    cos = np.einsum("ki,ki->k", normals[pt], facades.normal[fc])
    prior = np.where(cos >= 0, beta_distribution.pdf(np.clip(cos, 0.0, 1.0), BETA_A, BETA_B), 0)
    post = prior * soft
    total = np.repeat(np.add.reduceat(post, starts), counts)
    post = np.divide(post, total, out=np.zeros_like(post), where=total > 0)
    order = np.lexsort((-post, pt))  # per point, the most probable facade first
    best = order[starts]
    win = post[best] > 0
    facade[pt[best[win]]] = fc[best[win]]
    weight[pt[best[win]]] = post[best[win]]
    return Association(facade, weight, "bayes")
