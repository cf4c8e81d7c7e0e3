"""Relocalise query images against a georeferenced image base: the library entry (thesis §5.1).

:class:`Localizer` chains the steps of :mod:`geoseg.reloc.retrieval` for a list of queries:

1. retrieval: the ``k`` base images nearest in embedding space (eq. 5.1), optionally only those
   within ``radius_m`` of each query's GPS fix; or, for queries that are one drive in order
   (``sequence``), the most probable base images of the route filter (:mod:`geoseg.reloc.route_filter`);
2. a relative pose per match: the relative-pose head (eq. 5.2; rotation, direction and, for the
   shipped head, the distance between the two cameras; by default gated with a second head for
   views of one place, :class:`~geoseg.reloc.networks.GatedRelPoseHead`) or the essential-matrix
   baseline;
3. re-ranking by the predicted distance, nearest first (optionally fused with the GPS fix's
   distance to each base image);
4. the absolute position from the matches' rays (ranged rays when distances are predicted,
   fig. 5.6).

:meth:`Localizer.from_base` builds one over an :class:`~geoseg.reloc.image_base.ImageBase` on disk with
the shipped networks (``geoseg/weights/{seg,reloc,relpose}``); ``geoseg localize`` and
``geoseg base build`` are thin commands over it. The constructor takes plain callables instead,
so that a program (or ``bench/accuracy_reloc.py``) can run the same algorithm over embeddings and
features it already holds.

The shipped networks were trained on 320x240 images of a tram camera (horizontal field of view
~70 degrees): :meth:`~Localizer.from_base` resizes every image to that size before the networks
see it (``network_size``). Relative poses of other cameras are approximate.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from geoseg.errors import GeosegError, check_positive
from geoseg.reloc.networks import (
    NEAR_GATE_M,
    NETWORK_SIZE,
    GatedRelPoseHead,
    HeadRelativePose,
    load_head,
    load_trunk,
    make_embedder,
    shipped_weights,
)
from geoseg.reloc.retrieval import (
    RetrievalIndex,
    absolute_position,
    fuse_gps_distance,
    rerank_by_distance,
)

logger = logging.getLogger(__name__)

__all__ = [
    "Localizer",
    "LocalizerConfig",
    "QueryResult",
    "RelativePoseFn",
]

# a match's relative pose when the base's points gave the query's pose (the heads not run)
_NOT_COMPUTED = {
    "ok": False,
    "reason": "not computed: the base's points gave the pose",
    "R_ab": None,
    "t_dir_ab": None,
    "distance_m": None,
    "n_inliers": None,
}
# (base indices (k,), query) -> one dict per index: "ok", "reason", "R_ab" (3, 3), "t_dir_ab"
# (3,) (unit, base camera frame), "distance_m" (float or None), "n_inliers" (int or None).
RelativePoseFn = Callable[[np.ndarray, Any], list[dict[str, Any]]]


@dataclass
class LocalizerConfig:
    """Settings of :class:`Localizer` (the ``geoseg localize`` options of the same names).

    Attributes:
        k: matches per query (>= 1).
        radius_m: GPS window radius in metres (needs ``gps`` at :meth:`Localizer.localize`).
        gps_sigma_m: GPS noise per axis in metres: re-rank by the predicted distance fused with
            the fix's distance to each match (:func:`geoseg.reloc.retrieval.fuse_gps_distance`); with
            ``sequence``, the route filter's Gaussian GPS likelihood.
        distance_rel_sigma: relative error of the predicted distances, for ``gps_sigma_m``.
        appearance_weight: re-rank by ``log(distance) + weight x embedding distance``
            (:func:`geoseg.reloc.retrieval.rerank_by_distance`); 0.5 suits the learned embedding.
        rerank: re-rank by predicted distance when the relative poses carry distances.
        position_k: matches used for the absolute position, best first (None: all ``k``).
        min_agreeing_rays: the ranged rays of at least this many matches must agree (the
            robust fit's inliers) for the position to come from them; otherwise the heads are
            taken to be out of their depth and the position is the best match's camera
            (``method`` "best match"). Measured: on real KITTI frames the rays of the top 3
            agreed for no query, and their position was worse than the best match's
            (``bench/reloc_real.py``); on a synthetic tram drive all agreed. A single ray
            (``k`` or ``position_k`` 1) is used as it is.
        sequence: ``"filter"`` (causal) or ``"smooth"`` (whole drive): the queries are one
            drive in order along the base's route; None: each query on its own.
        step_m: with ``sequence``, metres driven between consecutive queries (None: the base's
            median spacing).
        appearance_scale: with ``sequence``, ``tau`` of the appearance likelihood (None: the
            route filter's default).
    """

    k: int = 3
    radius_m: float | None = None
    gps_sigma_m: float | None = None
    distance_rel_sigma: float = 0.3
    appearance_weight: float = 0.0
    rerank: bool = True
    position_k: int | None = None
    min_agreeing_rays: int = 2
    sequence: Literal["filter", "smooth"] | None = None
    step_m: float | None = None
    appearance_scale: float | None = None

    def __post_init__(self) -> None:
        for name in ("k", "position_k", "min_agreeing_rays"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or int(v) != v or v < 1):
                raise GeosegError(f"{name}: expected an int >= 1, got {v!r}")
        for name in ("radius_m", "gps_sigma_m", "distance_rel_sigma", "appearance_scale"):
            if getattr(self, name) is not None:
                check_positive(name, getattr(self, name))
        for name in ("appearance_weight", "step_m"):
            if getattr(self, name) is not None:
                check_positive(name, getattr(self, name), strict=False)
        if self.sequence not in (None, "filter", "smooth"):
            raise GeosegError(
                f"sequence: expected 'filter', 'smooth' or None, got {self.sequence!r}"
            )
        if self.sequence is None and (self.step_m is not None or self.appearance_scale is not None):
            raise GeosegError("step_m, appearance_scale: only with a sequence")


@dataclass
class QueryResult:
    """One query's outcome.

    Attributes:
        name: the query's name (file path for images).
        gps: ``(x, y)`` fix in the base's world frame, or None.
        matches: best first; each ``{"rank", "appearance_rank", "index", "image", "distance"
            (embedding), "base_t_wc" (3,), "relative_pose": {...}}`` (plus
            ``"sequence_probability"`` or ``"gps_fused_distance_m"`` when those apply).
        position: ``{"method", "xyz" (3,) or None, "degenerate", "n_rays", "n_inliers",
            "inlier_ranks", "reason"}``; with the base's points (method ``structure``)
            ``{"method", "xyz", "R_wc" (3, 3), "degenerate", "n_matches", "n_inliers",
            "rms_px", "reason"}``, and ``"structure_reason"`` when they gave no pose.
    """

    name: str
    gps: tuple[float, float] | None
    matches: list[dict[str, Any]] = field(default_factory=list)
    position: dict[str, Any] = field(default_factory=dict)

    @property
    def xyz(self) -> np.ndarray | None:
        """The query camera's position ``(3,)`` in the world frame, or None (degenerate)."""
        return None if self.position.get("xyz") is None else np.asarray(self.position["xyz"])

    def to_dict(self) -> dict[str, Any]:
        return {
            "image": self.name,
            "gps": self.gps,
            "matches": self.matches,
            "position": self.position,
        }


class Localizer:
    """Retrieval + relative poses + absolute position for queries against one image base.

    Args:
        index: the base's embeddings with its poses (``R_wc`` ``(M, 3, 3)``, ``t_wc``
            ``(M, 3)``).
        embed: ``embed([query]) -> (1, D)``, the query's embedding in the index's space.
        relative_pose: see :data:`RelativePoseFn`.
        base_names: ``M`` names of the base images (for the results).
        timestamps: ``(M,)`` seconds or None: the route's order for ``sequence`` (else the
            index order).
        config: :class:`LocalizerConfig`.
        embedding_name, relative_pose_name: descriptions for reports.
        check_query: optional ``fn(name, query)`` raising :class:`GeosegError` for a query
            the relative poses cannot use (e.g. an image of another size than the intrinsics').
        structure: a :class:`~geoseg.reloc.base_structure.StructureLocator` over the base's
            triangulated points: a query it localises (PnP on its matches' points) takes that
            pose (method ``structure``); the others the relative poses' position.
    """

    def __init__(
        self,
        *,
        index: RetrievalIndex,
        embed: Callable[[Sequence[Any]], Any],
        relative_pose: RelativePoseFn,
        base_names: Sequence[str],
        timestamps: Any = None,
        config: LocalizerConfig | None = None,
        embedding_name: str = "",
        relative_pose_name: str = "",
        check_query: Callable[[str, Any], None] | None = None,
        structure: Any = None,
    ) -> None:
        if index.R_wc is None or index.t_wc is None:
            raise GeosegError("index: needs the base poses (R_wc, t_wc)")
        if len(base_names) != len(index):
            raise GeosegError(f"base_names: expected {len(index)} names, got {len(base_names)}")
        self.index = index
        self.embed = embed
        self.relative_pose = relative_pose
        self.base_names = list(base_names)
        self.timestamps = None if timestamps is None else np.asarray(timestamps, dtype=np.float64)
        self.config = config or LocalizerConfig()
        self.embedding_name = embedding_name
        self.relative_pose_name = relative_pose_name
        self.check_query = check_query
        self.structure = structure

    def __len__(self) -> int:
        return len(self.index)

    # ------------------------------------------------------------------ building
    @classmethod
    def from_base(
        cls,
        base: Any,
        *,
        embedding: Literal["learned", "layer21", "thumbnail"] = "learned",
        relative_pose: Literal["head", "essential"] = "head",
        trunk: str | Path | None = None,
        reloc_head: str | Path | None = None,
        relpose_head: str | Path | None = None,
        near_head: str | Path | None = None,
        near_gate_m: float | None = NEAR_GATE_M,
        network_size: tuple[int, int] | None = NETWORK_SIZE,
        pool: tuple[int, int] | None = None,
        features: Literal["orb", "sift"] = "orb",
        focal: float | None = None,
        device: str = "cpu",
        cache: bool = True,
        config: LocalizerConfig | None = None,
        structure: bool = False,
        query_K: Any = None,
    ) -> Localizer:
        """A localizer over an image base directory with the shipped networks by default.

        Args:
            base: an :class:`~geoseg.reloc.image_base.ImageBase` or its directory
                (``geoseg base build`` makes one from a folder of geotagged images).
            embedding: ``learned`` (the embedding head of eq. 5.1 on the trunk's layer-21
                features, the default), ``layer21`` (the raw features, §5.1.1) or
                ``thumbnail`` (a grey thumbnail, a placeholder for tests: it finds
                near-duplicates only).
            relative_pose: ``head`` (the relative-pose head, eq. 5.2, the default) or
                ``essential`` (ORB/SIFT essential matrix: needs the base's ``camera.json`` or
                ``focal``, and queries of the intrinsics' size).
            trunk, reloc_head, relpose_head: weight files (default: the shipped ``seg``,
                ``reloc`` and ``relpose`` ``model.pt``).
            near_head: weights of the head for views of one place, gated with the relative-pose
                head (:class:`~geoseg.reloc.networks.GatedRelPoseHead`); default: the shipped ``relpose_near`` when
                ``relpose_head`` is the shipped one too (the two are a pair: the near head is a
                fine-tune of the shipped head), else none.
            near_gate_m: the near head's distance below which it gives the distance; None: the
                relative-pose head alone.
            network_size: ``(W, H)`` every image is resized to before the networks (the
                shipped networks' 320x240); None keeps each image's size (base and queries must
                then share one).
            pool: average-pool the raw layer-21 features to ``(h, w)`` (``layer21`` only).
            features: keypoints of the essential-matrix baseline.
            focal: focal length in pixels when the base has no ``camera.json`` (essential).
            device: torch device of the networks.
            cache: read/write the base embeddings under ``BASE/cache/``.
            structure: localise queries on the base's triangulated points where enough match
                (:mod:`geoseg.reloc.base_structure`; needs the base's ``camera.json``).
            query_K: ``(3, 3)`` the queries' intrinsics for ``structure`` (default: the base's).
            config: :class:`LocalizerConfig` (default: ``appearance_weight`` 0.5 with the
                learned embedding).

        Raises:
            GeosegError: a bad base, option or weight file (naming it).
        """
        from geoseg.reloc.image_base import ImageBase, load_image_base

        if not isinstance(base, ImageBase):
            base = load_image_base(base)
        if embedding not in ("learned", "layer21", "thumbnail"):
            raise GeosegError(
                f"embedding: expected learned, layer21 or thumbnail, got {embedding!r}"
            )
        if relative_pose not in ("head", "essential"):
            raise GeosegError(f"relative_pose: expected head or essential, got {relative_pose!r}")
        if near_gate_m is not None:
            check_positive("near_gate_m", near_gate_m)
        if pool is not None and embedding != "layer21":
            raise GeosegError("pool: only with the layer21 embedding")
        if config is None:
            config = LocalizerConfig(appearance_weight=0.5 if embedding == "learned" else 0.0)
        segmenter = None
        if embedding != "thumbnail" or relative_pose == "head":
            segmenter = load_trunk(trunk, device)
        embedder, embedding_name, feature_fn = make_embedder(
            embedding,
            segmenter,
            reloc_head=reloc_head,
            network_size=network_size,
            pool=pool,
            device=device,
        )
        index = base.build_index(embedder, cache=cache)
        check_query = None
        if relative_pose == "head":
            head_path = relpose_head if relpose_head is not None else shipped_weights("relpose")
            head = load_head(head_path, "relpose", device)
            pose_name = f"relative-pose head ({Path(head_path).parent.name}/{Path(head_path).name})"
            if near_head is None and relpose_head is None and near_gate_m is not None:
                near_head = shipped_weights("relpose_near")
            if near_head is not None and near_gate_m is not None:
                near = load_head(near_head, "relpose", device)
                head = GatedRelPoseHead(head, near, near_m=near_gate_m)
                pose_name += (
                    f" gated with the near head ({Path(near_head).parent.name}/"
                    f"{Path(near_head).name}) below {near_gate_m:g} m"
                )
            pose_fn: RelativePoseFn = HeadRelativePose(base, feature_fn, head, device)
        else:
            from geoseg.reloc.image_base import check_image_size

            K, k_source, size, size_source = _intrinsics(base, focal)
            pose_fn = _EssentialRelativePose(base, K, features, k_source)
            pose_name = f"essential matrix ({features.upper()} + MAGSAC; K from {k_source})"

            def check_query(name: str, image: Any) -> None:
                check_image_size(f"query {name}", image, size, size_source)

        locator = None
        if structure:
            from geoseg.reloc.base_structure import StructureLocator, build_structure

            K_q = base.K if query_K is None else query_K
            locator = StructureLocator(build_structure(base, cache=cache), K_q)
        stamps = base.timestamps if np.isfinite(base.timestamps).all() else None
        return cls(
            index=index,
            embed=embedder,
            relative_pose=pose_fn,
            base_names=base.images,
            timestamps=stamps,
            config=config,
            embedding_name=embedding_name,
            relative_pose_name=pose_name,
            check_query=check_query,
            structure=locator,
        )

    # ------------------------------------------------------------------ localisation
    def localize(
        self,
        queries: Sequence[Any],
        *,
        gps: Any = None,
        names: Sequence[str] | None = None,
        sequence: Literal["filter", "smooth"] | None | str = "config",
    ) -> list[QueryResult]:
        """Localise ``queries`` (RGB uint8 ``(H, W, 3)`` images for :meth:`from_base`).

        Args:
            queries: ``T`` queries, in driving order for a sequence.
            gps: ``(T, 2)`` fixes in the base's world frame (metres), or None.
            names: ``T`` names for the results (default ``query_<i>``).
            sequence: ``"filter"``, ``"smooth"`` or None; default: the config's.

        Returns:
            One :class:`QueryResult` per query, in order.
        """
        cfg = self.config
        seq = cfg.sequence if sequence == "config" else sequence
        if seq not in (None, "filter", "smooth"):
            raise GeosegError(f"sequence: expected 'filter', 'smooth' or None, got {seq!r}")
        queries = list(queries)
        if not queries:
            return []
        names = [f"query_{i}" for i in range(len(queries))] if names is None else list(names)
        if len(names) != len(queries):
            raise GeosegError(f"names: expected {len(queries)} names, got {len(names)}")
        gps_arr = _check_gps(gps, len(queries))
        if cfg.radius_m is not None and gps_arr is None:
            raise GeosegError("radius_m: the GPS window needs the queries' gps")
        if cfg.gps_sigma_m is not None and gps_arr is None:
            raise GeosegError("gps_sigma_m: needs the queries' gps")
        if self.check_query is not None:
            for name, q in zip(names, queries):
                self.check_query(name, q)
        q_emb = self._embed_queries(queries, names)
        k = min(cfg.k, len(self))
        sequence_prob = None
        if seq is not None:
            ranked, dists, sequence_prob = self._route_matches(q_emb, gps_arr, k, seq)
        else:
            ranked, dists = self.index.query(q_emb, k=k, gps=gps_arr, radius_m=cfg.radius_m)
        out = []
        for j, (name, query) in enumerate(zip(names, queries)):
            rows = [r for r in range(ranked.shape[1]) if ranked[j, r] >= 0]
            idx = np.array([int(ranked[j, r]) for r in rows], dtype=np.int64)
            placed = None
            if self.structure is not None and idx.size:
                placed = self.structure.locate(query, idx)
            try:
                if placed is not None and placed.ok:  # the pose is known: no rays needed
                    poses = [dict(_NOT_COMPUTED) for _ in idx]
                else:
                    poses = self.relative_pose(idx, query) if idx.size else []
            except GeosegError as err:
                raise GeosegError(f"query {name}: {err}") from None
            matches = []
            for r, i, rp in zip(rows, idx, poses):
                rp = dict(rp)
                rp["rotation_deg"] = _rotation_deg(rp["R_ab"]) if rp["ok"] else None
                rp["query_R_wc"] = self.index.R_wc[i] @ rp["R_ab"] if rp["ok"] else None
                m = {
                    "rank": r + 1,
                    "index": int(i),
                    "image": self.base_names[i],
                    "distance": float(dists[j, r]),
                    "base_t_wc": self.index.t_wc[i],
                    "relative_pose": rp,
                }
                if sequence_prob is not None:
                    m["sequence_probability"] = float(sequence_prob[j, r])
                matches.append(m)
            fix = None if gps_arr is None else gps_arr[j]
            matches = self._rerank(matches, fix, seq)
            out.append(
                QueryResult(
                    name=str(name),
                    gps=None if fix is None else (float(fix[0]), float(fix[1])),
                    matches=matches,
                    position=self._position_of(placed, matches),
                )
            )
        return out

    def _embed_queries(self, queries: list[Any], names: list[str]) -> np.ndarray:
        rows = []
        for name, q in zip(names, queries):
            try:
                e = np.asarray(self.embed([q]), dtype=np.float64)
            except GeosegError as err:
                raise GeosegError(f"query {name}: {err}") from None
            if e.shape != (1, self.index.dim):
                raise GeosegError(
                    f"query {name}: embedding of size {e.shape[-1]} but the base's is "
                    f"{self.index.dim} (query and base images of different sizes?)"
                )
            rows.append(e[0])
        return np.stack(rows)

    def _route_matches(self, q_emb: np.ndarray, gps: Any, k: int, mode: str) -> tuple:
        """``(ranked (T, k), embedding distances (T, k), posterior (T, k))`` of the route HMM."""
        from geoseg.reloc.route_filter import RouteFilter, RouteFilterConfig

        cfg = self.config
        route_cfg = RouteFilterConfig(
            **({} if cfg.appearance_scale is None else {"appearance_scale": cfg.appearance_scale})
        )
        if self.timestamps is None:
            logger.info("the base has no timestamps: its route is the order of the base")
        route = RouteFilter(self.index.t_wc, timestamps=self.timestamps, config=route_cfg)
        all_dist = self.index.distances(q_emb)
        steps = None if cfg.step_m is None else np.full(len(q_emb) - 1, cfg.step_m)
        run = route.filter if mode == "filter" else route.smooth
        post = run(all_dist, steps, gps=gps, radius_m=cfg.radius_m, gps_sigma_m=cfg.gps_sigma_m)
        ranked, prob = post.top(k)
        dists = np.take_along_axis(all_dist, ranked, axis=1)
        if cfg.radius_m is not None:  # the window's outside has probability 0: not a match
            ranked = np.where(prob > 0, ranked, -1)
        return ranked, dists, prob

    def _rerank(self, matches: list[dict], fix: Any, seq: str | None) -> list[dict]:
        """Nearest predicted distance first (the sequence posterior already orders its
        matches); ranks renumbered, the retrieval rank kept as ``appearance_rank``."""
        cfg = self.config
        ranged = bool(matches) and all(
            m["relative_pose"].get("distance_m") is not None for m in matches
        )
        if ranged and cfg.rerank and seq is None:
            dist = np.array([[m["relative_pose"]["distance_m"] for m in matches]])
            if cfg.gps_sigma_m is not None and fix is not None:
                gps_m = np.array([[np.linalg.norm(m["base_t_wc"][:2] - fix) for m in matches]])
                dist = fuse_gps_distance(
                    dist,
                    gps_m,
                    relative_sigma=cfg.distance_rel_sigma,
                    gps_sigma_m=cfg.gps_sigma_m,
                )
                for m, d in zip(matches, dist[0]):
                    m["gps_fused_distance_m"] = float(d)
            order = rerank_by_distance(
                np.arange(len(matches))[None],
                dist,
                appearance=np.array([[m["distance"] for m in matches]]),
                appearance_weight=cfg.appearance_weight,
            )[2][0]
            matches = [matches[i] for i in order]
        for r, m in enumerate(matches, start=1):
            m["appearance_rank"], m["rank"] = m["rank"], r
        return matches

    def _position_of(self, placed: Any, matches: list[dict]) -> dict[str, Any]:
        """The pose from the base's points (``placed``, a
        :class:`~geoseg.reloc.base_structure.StructurePose` or None), else :meth:`_position`."""
        if placed is None or not placed.ok:
            position = self._position(matches)
            if placed is not None:
                position["structure_reason"] = placed.reason
            return position
        return {
            "method": "structure",
            "xyz": placed.t_wc,
            "R_wc": placed.R_wc,
            "degenerate": False,
            "n_matches": placed.n_matches,
            "n_inliers": placed.n_inliers,
            "rms_px": placed.rms_px,
            "reason": "",
        }

    def _position(self, matches: list[dict]) -> dict[str, Any]:
        """The absolute position from the best ``position_k`` matches' rays."""
        ranged = bool(matches) and all(
            m["relative_pose"].get("distance_m") is not None for m in matches
        )
        ok = [m for m in matches if m["relative_pose"]["ok"]][: self.config.position_k]
        position: dict[str, Any] = {
            "method": "ranged rays" if ranged else "rays",
            "xyz": None,
            "degenerate": True,
            "n_rays": len(ok),
            "n_inliers": 0,
            "inlier_ranks": [],
            "reason": "",
        }
        radius = self.config.radius_m
        if not matches:
            position["reason"] = (
                f"no base image within {radius} m of the query's GPS" if radius else "no match"
            )
            return position
        need = 1 if ranged else 2
        if len(ok) < need:
            position["reason"] = f"{len(ok)} relative pose(s), at least {need} needed"
            return position
        idx = [m["index"] for m in ok]
        dirs = np.stack([m["relative_pose"]["t_dir_ab"] for m in ok])
        ranges = [m["relative_pose"]["distance_m"] for m in ok] if ranged else None
        ray = absolute_position(self.index.R_wc[idx], self.index.t_wc[idx], dirs, ranges)
        position.update(
            xyz=None if ray.degenerate else ray.point,
            degenerate=ray.degenerate,
            n_inliers=int(ray.inliers.sum()),
            inlier_ranks=[m["rank"] for m, inl in zip(ok, ray.inliers) if inl],
            residuals_m=ray.residuals,
            reason="near-parallel or inconsistent rays" if ray.degenerate else "",
        )
        agreeing = min(self.config.min_agreeing_rays, len(ok))
        if ranged and position["n_inliers"] < agreeing:
            position.update(
                method="best match",
                xyz=np.asarray(matches[0]["base_t_wc"], dtype=np.float64),
                degenerate=False,
                reason=f"the relative poses do not agree ({position['n_inliers']} of {len(ok)} "
                "ranged rays consistent): the best match's position",
            )
        return position


def _rotation_deg(R: Any) -> float:
    """Angle of a rotation matrix in degrees."""
    c = (float(np.trace(np.asarray(R, dtype=np.float64))) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def _check_gps(gps: Any, n: int) -> np.ndarray | None:
    if gps is None:
        return None
    arr = np.asarray(gps, dtype=np.float64)
    if arr.shape != (n, 2):
        raise GeosegError(f"gps: expected shape ({n}, 2), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise GeosegError("gps: values are not finite")
    return arr


class _EssentialRelativePose:
    """Relative poses base -> query from the essential matrix (no scale: ``distance_m`` None)."""

    def __init__(self, base: Any, K: np.ndarray, features: str, k_source: str) -> None:
        self.base, self.K, self.features, self.k_source = base, K, features, k_source

    def __call__(self, idx: np.ndarray, query: Any) -> list[dict[str, Any]]:
        from geoseg.reloc.essential_baseline import estimate_relative_pose

        out = []
        for i in idx:
            est = estimate_relative_pose(
                self.base.load_image(int(i)), query, self.K, method=self.features
            )
            out.append(
                {
                    "ok": est.ok,
                    "reason": est.reason,
                    "R_ab": est.R_ab,
                    "t_dir_ab": est.t_dir_ab,
                    "distance_m": None,
                    "n_inliers": est.n_inliers,
                }
            )
        return out


def _intrinsics(base: Any, focal: float | None) -> tuple:
    """``(K, where K comes from, (W, H) it holds for, where that size comes from)``."""
    from geoseg.reloc.image_base import CAMERA_FILE

    h, w = base.load_image(0).shape[:2]
    if base.K is not None:
        if focal is not None:
            raise GeosegError(
                f"focal: {base.root / CAMERA_FILE} gives the intrinsics; drop the focal (or the file)"
            )
        if base.image_size is not None:
            return base.K, "camera.json", base.image_size, str(base.root / CAMERA_FILE)
        return base.K, "camera.json", (w, h), f"{base.root / CAMERA_FILE} (base image size)"
    if focal is not None:
        check_positive("focal", focal)
        f, source = float(focal), "focal"
    else:
        f, source = float(max(w, h)), "assumed"
        logger.warning(
            "no camera.json in the base and no focal length: assuming %.0f px (relative poses "
            "of the essential-matrix baseline are approximate)",
            f,
        )
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    return K, source, (w, h), f"{source} focal on the base images' size"
