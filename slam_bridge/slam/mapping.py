"""Mapping: triangulating new points, gating bad observations, culling degenerate points.

* :func:`triangulate_new`: the untriangulated points a keyframe sees are triangulated from all
  their active observations (DLT + Gauss-Newton, :func:`slam_bridge.geometry.multiview.triangulate`,
  parallax >= ``min_parallax_deg``); a point whose worst observation errs by more than the
  outlier gate loses that observation and waits for the next keyframe.
* :func:`gate_window`: after the fusion, the fusion window's observations erring by more than
  ``window_gate_px`` are deactivated (gross outliers that slipped through), then the window's
  points whose views' rays now meet at less than ``min_parallax_deg``, or that lie behind a
  view, are untriangulated (:func:`cull_degenerate_points`; triangulated anew when seen again).
  In a sharp turn the optimisation can slide points seen from close viewpoints far along their
  rays: the reprojection gate cannot see it (they still reproject well), the next PnP does.
* :func:`refine_points`: after the last keyframe, the points that left a hybrid window (only
  carried rigidly since) are re-triangulated with the final poses, so that the returned map
  matches the returned trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geoseg.errors import check_positive
from slam_bridge.geometry.multiview import ray_parallax_deg, triangulate
from slam_bridge.slam.map import Map
from slam_bridge.slam.tracking import reprojection_errors

__all__ = [
    "MappingConfig",
    "triangulate_new",
    "gate_window",
    "cull_degenerate_points",
    "refine_points",
]


@dataclass
class MappingConfig:
    """Mapping settings (module docstring).

    Attributes:
        min_parallax_deg: triangulation parallax threshold (also the culling threshold).
        window_gate_px: observations of the fusion window erring more after the fusion are
            deactivated.
    """

    min_parallax_deg: float = 1.0
    window_gate_px: float = 8.0

    def __post_init__(self) -> None:
        check_positive("min_parallax_deg", self.min_parallax_deg, strict=False)
        check_positive("window_gate_px", self.window_gate_px)


def triangulate_new(
    slam_map: Map, k: int, cfg: MappingConfig, outlier_gate_px: float, first_observation: int = 0
) -> int:
    """Triangulate the untriangulated points seen by keyframe ``k`` (map updated in place).

    Args:
        slam_map: the map.
        k: the keyframe.
        cfg: mapping settings.
        outlier_gate_px: a new point whose worst observation errs more loses that observation.
        first_observation: observations before this index are ignored (a new segment's start).

    Returns:
        The number of points triangulated.
    """
    m = slam_map
    pt = m.obs_point
    starts = m.starts
    sl = np.arange(starts[k], starts[k + 1])
    cand = np.unique(pt[sl][m.obs_active[sl] & ~m.triangulated[pt[sl]]])
    if cand.size == 0:
        return 0
    upto = np.arange(first_observation, starts[k + 1])
    o = upto[m.obs_active[upto] & np.isin(pt[upto], cand)]
    counts = np.bincount(pt[o], minlength=m.num_points)
    o = o[counts[pt[o]] >= 2]
    if o.size == 0:
        return 0
    pts_u, local = np.unique(pt[o], return_inverse=True)
    kf = m.obs_keyframe[o]
    res = triangulate(
        m.K, m.R_wc, m.t_wc, kf, local, m.obs_uv[o], num_points=pts_u.size,
        min_parallax_deg=cfg.min_parallax_deg,
    )  # fmt: skip
    Xo = np.where(res.valid[:, None], res.X_w, 0.0)[local]
    err = reprojection_errors(m.K, m.R_wc[kf], m.t_wc[kf], Xo, m.obs_uv[o])
    worst = np.zeros(pts_u.size)
    np.maximum.at(worst, local, err)
    good = res.valid & (worst <= outlier_gate_px)
    # a valid point with one bad observation: drop its worst observation, retry later
    bad_pt = res.valid & ~good
    if np.any(bad_pt):
        is_worst = bad_pt[local] & (err >= worst[local]) & (err > outlier_gate_px)
        m.obs_active[o[is_worst]] = False
    m.X_w[pts_u[good]] = res.X_w[good]
    m.triangulated[pts_u[good]] = True
    return int(good.sum())


def gate_window(
    slam_map: Map, observations: np.ndarray, k: int, cfg: MappingConfig, first_observation: int = 0
) -> tuple[int, int]:
    """Deactivate the fusion window's bad observations, then cull its degenerate points.

    Args:
        slam_map: the map (poses and points after the fusion).
        observations: ``(M,)`` map indices of the fusion window's reprojection rows.
        k: the newest keyframe.
        cfg: mapping settings.
        first_observation: observations before this index are ignored (a new segment's start).

    Returns:
        ``(observations deactivated, points untriangulated)``.
    """
    m, o = slam_map, observations
    kf = m.obs_keyframe[o]
    err = reprojection_errors(m.K, m.R_wc[kf], m.t_wc[kf], m.X_w[m.obs_point[o]], m.obs_uv[o])
    bad = o[err > cfg.window_gate_px]
    m.obs_active[bad] = False
    # every active view of the window's points, older ones included
    in_window = np.zeros(m.num_points, dtype=bool)
    in_window[m.obs_point[o]] = True
    span = np.arange(first_observation, m.starts[k + 1])
    ok = span[m.obs_active[span] & in_window[m.obs_point[span]]]
    culled = cull_degenerate_points(
        m.obs_point[ok], m.R_wc[m.obs_keyframe[ok]], m.t_wc[m.obs_keyframe[ok]], m.X_w,
        m.triangulated, cfg.min_parallax_deg,
    )  # fmt: skip
    return int(bad.size), culled


def cull_degenerate_points(
    points: np.ndarray,
    R_obs: np.ndarray,
    t_obs: np.ndarray,
    X_w: np.ndarray,
    tri_ok: np.ndarray,
    min_parallax_deg: float,
) -> int:
    """Untriangulate the points whose geometry the optimisation has made degenerate.

    A point whose observers' rays now meet at less than ``min_parallax_deg``, or that lies
    behind one of them, is marked untriangulated (module docstring).

    Args:
        points: ``(M,)`` point id of each active observation of the points to check (all their
            views, not only the window's: old views carry the parallax).
        R_obs: ``(M, 3, 3)`` rotation of its keyframe.
        t_obs: ``(M, 3)`` optical centre of its keyframe.
        X_w: ``(P, 3)`` the map.
        tri_ok: ``(P,)`` triangulated flags (updated in place).
        min_parallax_deg: parallax threshold, degrees.

    Returns:
        The number of points untriangulated.
    """
    if points.size == 0:
        return 0
    uniq, local = np.unique(points, return_inverse=True)
    X_obs = X_w[points]
    parallax = ray_parallax_deg(t_obs, X_obs, local, uniq.size)
    depth = np.einsum("mi,mi->m", X_obs - t_obs, R_obs[:, :, 2])  # camera z axis in the world
    behind = np.zeros(uniq.size, dtype=bool)
    np.logical_or.at(behind, local, ~(depth > 0))
    views = np.bincount(local, minlength=uniq.size)
    # a point with a single active view left has nothing to measure parallax with: kept
    cull = tri_ok[uniq] & (behind | ((views >= 2) & (parallax < min_parallax_deg)))
    tri_ok[uniq[cull]] = False
    return int(cull.sum())


def refine_points(
    slam_map: Map,
    points: np.ndarray,
    first_observation: int = 0,
    end_observation: int | None = None,
) -> int:
    """Re-triangulate ``points`` from their active observations with the current poses.

    A point takes its refit (DLT + Gauss-Newton) only when that lowers its worst reprojection
    error (module docstring).

    Args:
        slam_map: the map (updated in place).
        points: ``(M,)`` point ids.
        first_observation: observations before this index are ignored (one segment's refit).
        end_observation: observations from this index on are ignored (default: none).

    Returns:
        The number of points updated.
    """
    m = slam_map
    if points.size == 0:
        return 0
    end = m.num_observations if end_observation is None else end_observation
    o = np.arange(first_observation, end)
    o = o[m.obs_active[o] & np.isin(m.obs_point[o], points)]
    if o.size == 0:
        return 0
    pts_u, local = np.unique(m.obs_point[o], return_inverse=True)
    kf = m.obs_keyframe[o]
    res = triangulate(
        m.K, m.R_wc, m.t_wc, kf, local, m.obs_uv[o], num_points=pts_u.size, min_parallax_deg=0.0
    )

    def worst_error(X: np.ndarray) -> np.ndarray:
        err = reprojection_errors(m.K, m.R_wc[kf], m.t_wc[kf], np.nan_to_num(X[local]), m.obs_uv[o])
        worst = np.zeros(pts_u.size)
        np.maximum.at(worst, local, err)
        return worst

    better = res.valid & (worst_error(res.X_w) < worst_error(m.X_w[pts_u]))
    m.X_w[pts_u[better]] = res.X_w[better]
    return int(better.sum())
