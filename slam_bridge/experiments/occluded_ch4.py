"""The geometric baseline behind occluders: why it holds in the chapter-4 city, and a city
where it should not (thesis §4.2.4.2, figure 4.13).

The ray-cast baseline (:func:`slam_bridge.bridge.association.associate_raycast`) calls a map
point a building point when the ray from the camera through it hits the building model. The
ray does not stop at the point: a tree or a parked van in front of a facade passes the test,
since its ray goes on to the facade behind it. What keeps such a point off the facade is the
association's gate, ``radius_m``: a point farther than that from every facade is left alone.
In the thesis's figure 4.13 the occluders (dense trees, bus shelters, parked vans) stand close
in front of the facades, inside any such gate, and the baseline drifts.

This module gives the experiment what it needs to tell the two cases apart:

* :func:`point_classes`: each map point's true class, the majority of its observations' rendered
  labels (saved by :func:`slam_bridge.experiments.buildings_ch4.run_one` as ``true_class``);
* :func:`false_associations`: the associated points that do not lie on their facade, by class
  and by their true distance to the nearest facade, and the distances of every non-building
  point (where the occluders stand relative to the facades);
* :func:`occluded_config`: the chapter-4 experiment on a ``facade_occluded`` city
  (:data:`geoseg.synth.world_config.FACADE_OCCLUDED_LAYOUT`: narrow sidewalks, facades on the
  sidewalk's edge, trees, shelters and panels within a metre or two of them).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from geoseg.classes import CLASS_NAMES, NUM_CLASSES, OBJECT, VEGETATION, VEHICLE
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError

__all__ = [
    "DISTANCE_BINS_M",
    "OCCLUDER_CLASSES",
    "point_classes",
    "facade_distances",
    "occluder_gaps",
    "false_associations",
    "occluded_config",
]

#: the bins (metres, true distance to the nearest facade) of the false associations' table
DISTANCE_BINS_M = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 5.0, np.inf)
#: the classes of the occluders (trees, vehicles, shelters, panels and poles)
OCCLUDER_CLASSES = (VEGETATION, VEHICLE, OBJECT)


def point_classes(folder: str | Path, slam_map, timestamps: np.ndarray) -> np.ndarray:
    """Each map point's true class: the majority of the rendered labels at its observations.

    Args:
        folder: a ``geoseg render`` output (``labels/<frame>.png``).
        slam_map: the run's :class:`slam_bridge.slam.map.Map`.
        timestamps: ``(F,)`` the frames' timestamps (a keyframe's frame is found by its time).

    Returns:
        ``(P,)`` int64 class id (:data:`geoseg.classes.CLASS_NAMES`), -1 for a point with no
        observation inside its image.
    """
    folder = Path(folder)
    timestamps = np.asarray(timestamps, dtype=np.float64)
    P = slam_map.num_points
    votes = np.zeros((P, NUM_CLASSES), np.int64)
    for k in range(slam_map.num_keyframes):
        idx = slam_map.keyframe_observations(k)
        if idx.size == 0:
            continue
        frame = int(np.searchsorted(timestamps, slam_map.timestamps[k]))
        path = folder / "labels" / f"{frame:06d}.png"
        labels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if labels is None:
            raise SlamError(f"{path}: missing or unreadable")
        H, W = labels.shape
        uv = np.rint(slam_map.obs_uv[idx]).astype(np.int64)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        cls = labels[uv[inside, 1], uv[inside, 0]].astype(np.int64)
        known = cls < NUM_CLASSES  # an ignore label votes for nothing
        pts = slam_map.obs_point[idx][inside][known].astype(np.int64)
        np.add.at(votes, (pts, cls[known]), 1)
    return np.where(votes.sum(1) > 0, votes.argmax(1), -1)


def facade_distances(world: Facades, points: np.ndarray, reach_m: float = 20.0) -> np.ndarray:
    """``(N,)`` each point's distance to the nearest true facade (inf beyond ``reach_m`` or for
    a NaN row).

    Args:
        world: the true facades (the exact model).
        points: ``(N, 3)`` world points.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise SlamError(f"points: expected (N, 3), got {points.shape}")
    out = np.full(points.shape[0], np.inf)
    pt, _, d = world.near(points, reach_m)
    np.minimum.at(out, pt, d)
    return out


def occluder_gaps(world, reach_m: float = 6.0) -> dict[str, np.ndarray]:
    """How far each occluder of a built city stands in front of the nearest facade, in plan.

    Args:
        world: a :class:`geoseg.synth.world.World`.
        reach_m: occluders with no facade this close (at a junction, before a gap between
            buildings) are left out.

    Returns:
        ``{kind: (n,) metres}`` for ``tree`` (the trunk's axis), ``shelter`` and ``panel`` (their
        centres) and ``parked`` (a parked vehicle's side nearest the facade).
    """
    table = world.facades()
    p0, p1 = table.p0, table.p1

    def gap(xy: np.ndarray) -> np.ndarray:  # plan distance to the nearest facade segment
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        seg = p1 - p0
        t = np.clip(
            np.einsum("nfk,fk->nf", xy[:, None] - p0[None], seg) / np.einsum("fk,fk->f", seg, seg),
            0.0, 1.0,
        )  # fmt: skip
        d = np.linalg.norm(xy[:, None] - (p0[None] + t[..., None] * seg[None]), axis=2)
        return d.min(1) if d.size else np.full(xy.shape[0], np.inf)

    out: dict[str, np.ndarray] = {}
    out["tree"] = gap([tree.xyz[:2] for tree in world.trees])
    for kind in ("shelter", "panel"):
        out[kind] = gap([xy for k, xy, _ in world.furniture if k == kind])
    parked = [v for v in world.vehicles if not v.moving]
    out["parked"] = gap([v.xy for v in parked]) - np.array([v.width / 2 for v in parked])
    return {k: v[v < reach_m] for k, v in out.items()}


def false_associations(run: dict, world: Facades) -> dict:
    """Where a run's wrong associations come from, and where the occluders stand.

    Args:
        run: a run's arrays (``runs/<method>_<model>.npz`` of the chapter-4 experiment):
            ``facade`` (P,) the association, ``right`` (P,) whether it is right,
            ``true_points`` (P, 3) the points' true positions, ``true_class`` (P,) their true
            classes (:func:`point_classes`), ``points`` (P, 3) the map's positions (NaN: not
            triangulated).
        world: the true facades.

    Returns:
        Flat figures: ``associated``, ``false``, ``false_share``; per class ``c``
        (:data:`~geoseg.classes.CLASS_NAMES`), ``false_<c>`` (its wrong associations; for
        ``building``, points given another facade than theirs); ``false_by_distance``, the
        wrong associations per bin of :data:`DISTANCE_BINS_M` of their true distance to the
        nearest facade (``"0-0.5"``, ...); and of the triangulated points of the occluders
        (:data:`OCCLUDER_CLASSES`; ``<g>`` ``occluder`` for all three, or a class name),
        ``<g>_points``, ``<g>_within_<r>m`` (the share whose true position is within 1, 1.5,
        2 and 3 m of a facade) and ``<g>_distance_median_m``.
    """
    for key in ("facade", "right", "true_points", "true_class", "points"):
        if key not in run:
            raise SlamError(f"run: no {key!r} array (a run saved before true_class was recorded?)")
    facade = np.asarray(run["facade"])
    right = np.asarray(run["right"], bool)
    cls = np.asarray(run["true_class"])
    triangulated = np.isfinite(np.asarray(run["points"])).all(1)
    dist = facade_distances(world, run["true_points"])
    got = (facade >= 0) & triangulated
    wrong = got & ~right
    out: dict = {
        "associated": int(got.sum()),
        "false": int(wrong.sum()),
        "false_share": float(wrong.sum() / got.sum()) if got.any() else None,
    }
    for c, name in enumerate(CLASS_NAMES):
        out[f"false_{name}"] = int((wrong & (cls == c)).sum())
    out["false_unlabelled"] = int((wrong & (cls < 0)).sum())
    edges = np.asarray(DISTANCE_BINS_M)
    counts, _ = np.histogram(np.where(np.isfinite(dist), dist, 1e9)[wrong], bins=edges)
    out["false_by_distance"] = {
        _bin_name(a, b): int(n) for a, b, n in zip(edges, edges[1:], counts)
    }
    # where the occluders' points stand: distances of the trees', vehicles' and objects' points
    occluder = triangulated & np.isin(cls, OCCLUDER_CLASSES) & np.isfinite(dist)
    groups = [("occluder", occluder)] + [
        (CLASS_NAMES[c], occluder & (cls == c)) for c in OCCLUDER_CLASSES
    ]
    for name, mask in groups:
        out[f"{name}_points"] = int(mask.sum())
        for r in (1.0, 1.5, 2.0, 3.0):
            out[f"{name}_within_{r:g}m"] = float(np.mean(dist[mask] <= r)) if mask.any() else None
        out[f"{name}_distance_median_m"] = float(np.median(dist[mask])) if mask.any() else None
    return out


def _bin_name(a: float, b: float) -> str:
    return f"{a:g}+" if not np.isfinite(b) else f"{a:g}-{b:g}"


def occluded_config(base, seed: int, length_m: float, methods=("raycast", "bayes")):
    """``base`` (a :class:`~slam_bridge.experiments.buildings_ch4.BuildingsConfig`) on a
    ``facade_occluded`` city: world and route ``seed``, ``length_m`` long, the exact model only,
    no timing runs; every other setting is ``base``'s (chosen on the chapter-4 city)."""
    from geoseg.synth.world_config import FACADE_OCCLUDED_LAYOUT

    drive = dataclasses.replace(
        base.drive, preset="facade_occluded", world=dict(FACADE_OCCLUDED_LAYOUT),
        world_seed=seed, route_seed=seed, length_m=length_m,
    )  # fmt: skip
    return dataclasses.replace(
        base, drive=drive, methods=list(methods), models=["exact"], async_run=False,
        timing_pairs=0,
    )  # fmt: skip
