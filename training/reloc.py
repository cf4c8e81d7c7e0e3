"""Train the relocalisation embedding head on frozen ENet layer-21 features (thesis §5.1.1, eq. 5.1).

The trunk (layers 1-21 of a trained ``enet`` or ``joint`` model, ``trunk_checkpoint``) is frozen,
so its features are computed **once** per traversal and cached
(:func:`geoseg.data.traversals.route_features`); the head (:func:`geoseg.models.reloc.reloc_head`)
then trains on features only, which is fast on a CPU.

Data (:class:`RoutesConfig`): one tram route per training city (seeds 1-6 by default, the
segmentation's training cities, bigger blocks), each driven under ``conditions_per_route``
conditions drawn from the training conditions, with along-track offsets and yaw jitter between
the traversals; the validation city (13) likewise. The evaluation city (1000) is never used here
(``bench/accuracy_reloc.py``).

Each epoch draws ``triplets_per_epoch`` fresh triplets (ref from one traversal, match and other
from another traversal of the same route: :func:`geoseg.data.pairs.sample_triplets`), spread
evenly over the routes and ordered traversal pairs, seeded by ``(seed, epoch)``. With
``hard_negatives`` the ``other`` of epochs ``>= hard_start_epoch`` is drawn among the
``hard_k`` true negatives closest to the ref under the current head (mined once per epoch).
Validation: eq. 5.1 and triplet accuracy on fixed validation triplets (uniform negatives).

The run directory holds the usual files (:mod:`training.common`); ``model.pt`` and
``model.onnx`` are the head alone: ``(B, 128, h, w)`` features -> ``{"embedding": (B, D)}``.

This module also holds what :mod:`training.relpose` shares: :class:`RoutesConfig`,
:func:`load_trunk`, :func:`prepare_routes`, :class:`ResamplingLoader` and
:func:`finalize_head_run`.

Usage::

    geoseg train reloc --config configs/reloc.yaml --set trunk_checkpoint=runs/seg
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from geoseg.data.pairs import sample_triplets
from geoseg.data.synthetic import TRAIN_CONDITIONS, VAL_SEEDS
from geoseg.data.traversals import RouteFeatures, TrunkFeatureExtractor, route_features, route_specs
from geoseg.errors import ConfigError, GeosegError
from geoseg.localize import triplet_accuracy
from geoseg.models.registry import get_model
from geoseg.models.reloc import triplet_loss
from training import common
from training import distributed as dd
from training.checkpoint import LAST, load_checkpoint
from training.config import TrainConfig
from training.loop import fit
from training.metrics import Meter

logger = logging.getLogger(__name__)

__all__ = [
    "CONFIG_CLASS",
    "RelocConfig",
    "ResamplingLoader",
    "RoutesConfig",
    "TripletAccuracyMeter",
    "TripletEmbedder",
    "TripletLoss",
    "TripletSet",
    "finalize_head_run",
    "load_trunk",
    "main",
    "prepare_routes",
]


# ============================================================================ shared config


@dataclass
class RoutesConfig:
    """The routes the heads train and validate on (:mod:`geoseg.data.traversals`).

    Attributes:
        world: ``WorldConfig`` keys shared by every city (bigger cities than the default).
        size: ``(H, W)`` of the rendered keyframes (the trunk's training scale).
        hfov_deg: horizontal field of view (None: the tram rig's 70 degrees).
        cache_dir: cache of rendered traversals and features (None: no cache).
        train_seeds: training cities.
        val_seeds: validation cities (not the evaluation city).
        conditions: condition pool (the held-out ``sun_low`` is not in it by default).
        conditions_per_route: traversals per route.
        length_m: track length of each training route, metres.
        val_length_m: track length of each validation route, metres.
        spacing_m: keyframe spacing, metres.
        offset_m: along-track shift between consecutive traversals, metres.
        yaw_jitter_deg: yaw jitter of traversals after the first, +- degrees.
        draw_seed: seeds the conditions and routes of the cities.
    """

    world: dict[str, Any] = field(default_factory=lambda: {"blocks_x": 6, "blocks_y": 5})
    size: tuple[int, int] = (240, 320)
    hfov_deg: float | None = None
    cache_dir: Path | None = Path("runs/cache/traversals")
    train_seeds: list[int] = field(default_factory=lambda: [1, 2, 3, 4, 5, 6])
    val_seeds: list[int] = field(default_factory=lambda: list(VAL_SEEDS))
    conditions: list[str] = field(default_factory=lambda: list(TRAIN_CONDITIONS))
    conditions_per_route: int = 3
    length_m: float = 2000.0
    val_length_m: float = 1000.0
    spacing_m: float = 8.0
    offset_m: float = 3.0
    yaw_jitter_deg: float = 5.0
    draw_seed: int = 0

    def __post_init__(self) -> None:
        from geoseg.data.synthetic import EVAL_SEEDS, HELDOUT_CONDITIONS

        if not self.train_seeds or not self.val_seeds:
            raise ConfigError("routes.train_seeds / routes.val_seeds: expected at least one city")
        held = sorted(set(self.train_seeds + self.val_seeds) & set(EVAL_SEEDS))
        if held:
            raise ConfigError(f"routes: {held} are held-out evaluation cities")
        conds = sorted(set(self.conditions) & set(HELDOUT_CONDITIONS))
        if conds:
            raise ConfigError(f"routes.conditions: {conds} are held-out conditions")
        if not 1 <= self.conditions_per_route <= len(self.conditions):
            raise ConfigError(
                f"routes.conditions_per_route: expected 1..{len(self.conditions)}, got "
                f"{self.conditions_per_route}"
            )
        if self.cache_dir is not None:
            self.cache_dir = Path(self.cache_dir)
        self.specs("train")  # validate the world keys and lengths now

    def specs(self, split: str) -> list[Any]:
        """The :class:`~geoseg.data.traversals.RouteSpec` list of ``split`` (train or val)."""
        if split not in ("train", "val"):
            raise GeosegError(f"split: expected train or val, got {split!r}")
        train = split == "train"
        return route_specs(
            self.train_seeds if train else self.val_seeds,
            conditions=self.conditions,
            conditions_per_route=self.conditions_per_route,
            draw_seed=self.draw_seed if train else self.draw_seed + 1,
            world=dict(self.world),
            size=tuple(self.size),
            hfov_deg=self.hfov_deg,
            length_m=self.length_m if train else self.val_length_m,
            spacing_m=self.spacing_m,
            offset_m=self.offset_m,
            yaw_jitter_deg=self.yaw_jitter_deg,
        )


def load_trunk(
    path: str | os.PathLike | None, *, device: str = "cpu", batch_size: int = 16
) -> TrunkFeatureExtractor:
    """The frozen trunk of a trained ``enet``/``joint`` model (file or run directory).

    Raises:
        GeosegError: no path, or a checkpoint of another architecture.
    """
    if path is None:
        raise GeosegError(
            "trunk_checkpoint: the heads sit on a trained ENet trunk; set it to a seg run "
            "directory or model file (e.g. --set trunk_checkpoint=runs/seg)"
        )
    state, ckpt = common.load_state(path)
    name = ckpt.get("model_name")
    if name not in ("enet", "joint"):
        raise GeosegError(f"{path}: holds a {name!r} model; the trunk comes from enet or joint")
    model = get_model(name, **dict(ckpt.get("model_config") or {}))
    model.load_state_dict(state)
    return TrunkFeatureExtractor(
        model,
        normalization=ckpt.get("normalization"),
        device=dd.resolve_device(device, 0),
        batch_size=batch_size,
    )


def prepare_routes(
    routes: RoutesConfig,
    split: str,
    extractor: TrunkFeatureExtractor,
    *,
    progress: bool = True,
) -> list[RouteFeatures]:
    """Render (or read) the routes of ``split`` and their layer-21 features (images dropped)."""
    return [
        route_features(
            spec, extractor, cache_dir=routes.cache_dir, progress=progress, keep_images=False
        )
        for spec in routes.specs(split)
    ]


def feature_shape(routes: Sequence[RouteFeatures]) -> tuple[int, int, int]:
    """The common ``(C, h, w)`` of the routes' features.

    Raises:
        GeosegError: feature maps of mismatched sizes.
    """
    shapes = {tuple(f.shape[1:]) for r in routes for f in r.features}
    if len(shapes) != 1:
        raise GeosegError(f"feature maps of mismatched sizes across routes: {sorted(shapes)}")
    return shapes.pop()


def traversal_pairs(route: RouteFeatures) -> list[tuple[int, int]]:
    """Ordered ``(query, database)`` traversal pairs of a route: every cross-condition pair,
    or ``(0, 0)`` when the route has one traversal."""
    n = len(route.traversals)
    return [(0, 0)] if n == 1 else [(i, j) for i in range(n) for j in range(n) if i != j]


def split_count(total: int, parts: int) -> list[int]:
    """``total`` spread over ``parts`` as evenly as possible."""
    base, rest = divmod(int(total), int(parts))
    return [base + (1 if i < rest else 0) for i in range(parts)]


class ResamplingLoader:
    """A DataLoader over a dataset that is resampled at the start of every epoch.

    ``dataset.resample(epoch)`` runs at each ``iter()`` (epoch 0, 1, ...; ``start_epoch`` when
    resuming), then the batches of the inner loader follow. Attributes that
    :func:`training.loop.fit` reads for shuffling and resume (``sampler``, ``batch_sampler``,
    ``generator``) are the inner loader's.

    Args:
        dataset: a dataset with ``resample(epoch: int)`` and a fixed length.
        loader: the inner DataLoader over ``dataset``.
        start_epoch: index of the first epoch iterated.
    """

    def __init__(self, dataset: Any, loader: Any, *, start_epoch: int = 0) -> None:
        self.dataset = dataset
        self.loader = loader
        self.epoch = int(start_epoch)
        self.sampler = getattr(loader, "sampler", None)
        self.batch_sampler = getattr(loader, "batch_sampler", None)
        self.generator = getattr(loader, "generator", None)

    def __len__(self) -> int:
        return len(self.loader)

    def __iter__(self):
        self.dataset.resample(self.epoch)
        self.epoch += 1
        return iter(self.loader)


def resume_epoch(cfg: TrainConfig) -> int:
    """The epoch a run resumes at (0 for a fresh run)."""
    last = Path(cfg.out_dir) / LAST
    if cfg.resume and last.is_file():
        return int(load_checkpoint(last).get("epoch", 0))
    return 0


def finalize_head_run(
    run_dir: Path,
    head: nn.Module,
    *,
    kind: str,
    cfg: Any,
    model_name: str,
    model_config: dict[str, Any],
    metrics: dict[str, Any],
    data_summary: dict[str, Any],
    example_inputs: Sequence[torch.Tensor],
    command: str | None,
    export: bool,
    extra_card: dict[str, Any] | None = None,
) -> Path:
    """``model.pt`` (the head), ``model.onnx`` (feature inputs) and the model card.

    :func:`training.common.finalize_run` exports image networks; the heads take feature maps,
    so the export is done here with ``example_inputs`` and the card's ``files`` updated.
    """
    files = {"checkpoint": common.MODEL_FILE}
    if export and dd.is_main_process():
        from geoseg.export import export_onnx

        export_onnx(
            head,
            run_dir / common.ONNX_FILE,
            example_inputs=tuple(example_inputs),
            metadata={"model_name": model_name, "model_config": model_config},
        )
        files["onnx"] = common.ONNX_FILE
    return common.finalize_run(
        run_dir,
        head,
        kind=kind,
        cfg=cfg,
        model_name=model_name,
        model_config=model_config,
        metrics=metrics,
        data_summary=data_summary,
        command=command,
        export=False,
        extra_card={"files": files, **(extra_card or {})},
    )


def describe_routes(routes: RoutesConfig, extractor: TrunkFeatureExtractor) -> dict[str, Any]:
    """Plain-data summary of the routes and trunk of a run (model cards)."""
    from geoseg.config import to_dict

    return {
        "source": "synth traversals (geoseg.data.traversals)",
        "train_routes": [to_dict(s) for s in routes.specs("train")],
        "val_routes": [to_dict(s) for s in routes.specs("val")],
        "trunk_fingerprint": extractor.fingerprint,
    }


# ============================================================================ reloc config


@dataclass
class RelocConfig(TrainConfig):
    """Embedding-head training run (fields beyond :class:`~training.config.TrainConfig`;
    ``data`` is unused: the traversals come from ``routes``).

    Attributes:
        trunk_checkpoint: the trained ENet (or joint) model: file or run directory (required).
        routes: the training and validation routes.
        triplets_per_epoch: fresh triplets drawn each epoch.
        val_triplets: fixed validation triplets.
        max_distance_m, max_angle_deg: same place (positives, :func:`positive_mask`).
        min_negative_distance_m: a negative is at least this far from the ref, metres.
        hard_negatives: mine hard negatives with the current head each epoch.
        hard_k: hard-negative pool size per ref.
        hard_start_epoch: first epoch (0-based) with hard negatives (the head needs a start).
        loss_scale: inverse temperature of eq. 5.1 (1 = the thesis).
        feature_batch_size: images per trunk forward pass when extracting features.
        export: export ``model.onnx`` at the end.
    """

    model: str = "reloc"
    out_dir: Path = Path("runs/reloc")
    batch_size: int = 32
    best_metric: str = "val_triplet_accuracy"
    best_mode: Literal["min", "max"] = "max"
    trunk_checkpoint: Path | None = None
    routes: RoutesConfig = field(default_factory=RoutesConfig)
    triplets_per_epoch: int = 4000
    val_triplets: int = 1000
    max_distance_m: float = 5.0
    max_angle_deg: float = 30.0
    min_negative_distance_m: float = 25.0
    hard_negatives: bool = True
    hard_k: int = 10
    hard_start_epoch: int = 1
    loss_scale: float = 1.0
    feature_batch_size: int = 16
    export: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.model != "reloc":
            raise ConfigError(f"model: the reloc trainer trains 'reloc', got {self.model!r}")
        for key in ("triplets_per_epoch", "val_triplets", "hard_k", "feature_batch_size"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{key}: expected >= 1, got {getattr(self, key)}")
        if self.hard_start_epoch < 0:
            raise ConfigError(f"hard_start_epoch: expected >= 0, got {self.hard_start_epoch}")
        if not self.loss_scale > 0:
            raise ConfigError(f"loss_scale: expected > 0, got {self.loss_scale}")
        if self.min_negative_distance_m < self.max_distance_m:
            raise ConfigError("min_negative_distance_m: expected >= max_distance_m")
        if self.trunk_checkpoint is not None:
            self.trunk_checkpoint = Path(self.trunk_checkpoint)


CONFIG_CLASS = RelocConfig


# ============================================================================ model, loss, meter


class TripletEmbedder(nn.Module):
    """The shared-weight head applied to the three maps of each triplet.

    Forward:
        x: ``(B, 3, C, h, w)`` features of (ref, match, other).
        Returns ``{"embedding": (B, 3, D)}``.
    """

    def __init__(self, head: nn.Module) -> None:
        super().__init__()
        self.head = head

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        if x.ndim != 5:
            raise GeosegError(f"x: expected (B, k, C, h, w) stacked features, got {tuple(x.shape)}")
        b, k = x.shape[:2]
        emb = self.head(x.flatten(0, 1))["embedding"]
        return {"embedding": emb.view(b, k, -1)}


class TripletLoss:
    """Eq. 5.1 on ``outputs["embedding"]`` ``(B, 3, D)`` (:func:`triplet_loss`)."""

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = float(scale)

    def __call__(self, outputs: dict[str, torch.Tensor], batch: dict[str, Any]) -> torch.Tensor:
        e = outputs["embedding"]
        return triplet_loss(e[:, 0], e[:, 1], e[:, 2], scale=self.scale)


class TripletAccuracyMeter(Meter):
    """Share of triplets with ``d(ref, match) < d(ref, other)``; also the mean distance gap."""

    def reset(self) -> None:
        self.state = {
            "correct": torch.zeros((), dtype=torch.float64),
            "count": torch.zeros((), dtype=torch.float64),
            "gap": torch.zeros((), dtype=torch.float64),
        }

    def update(self, outputs: Any, batch: Any) -> None:
        e = outputs["embedding"].detach().double().cpu()
        d_pos = (e[:, 0] - e[:, 1]).norm(dim=1)
        d_neg = (e[:, 0] - e[:, 2]).norm(dim=1)
        self.state["correct"] += (d_pos < d_neg).sum()
        self.state["count"] += e.shape[0]
        self.state["gap"] += (d_neg - d_pos).sum()

    def compute(self) -> dict[str, float]:
        n = float(self.state["count"])
        if n == 0:
            return {"triplet_accuracy": float("nan"), "distance_gap": float("nan")}
        return {
            "triplet_accuracy": float(self.state["correct"]) / n,
            "distance_gap": float(self.state["gap"]) / n,
        }


# ============================================================================ data


def embed_features(
    head: nn.Module, features: torch.Tensor, *, batch_size: int = 64
) -> torch.Tensor:
    """``(N, C, h, w)`` features -> ``(N, D)`` float32 embeddings (eval mode, no gradient;
    the head's training mode is restored)."""
    param = next(iter(head.parameters()), None)
    device = param.device if param is not None else torch.device("cpu")
    was_training = head.training
    head.eval()
    out = []
    with torch.no_grad():
        for s in range(0, features.shape[0], batch_size):
            x = features[s : s + batch_size].to(device).float()
            out.append(head(x)["embedding"].float().cpu())
    head.train(was_training)
    return torch.cat(out)


def triplet_embeddings(
    head: nn.Module, triplets: TripletSet
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(ref, match, other)`` embeddings ``(n, D)`` each of a :class:`TripletSet`'s current
    triplets (every traversal embedded once)."""
    cache: dict[tuple[int, int], torch.Tensor] = {}
    parts: list[list[torch.Tensor]] = [[], [], []]
    for r, q, d, a, p, n in triplets.index.tolist():
        for t in (q, d):
            if (r, t) not in cache:
                cache[(r, t)] = embed_features(head, triplets.routes[r].features[t])
        parts[0].append(cache[(r, q)][a])
        parts[1].append(cache[(r, d)][p])
        parts[2].append(cache[(r, d)][n])
    return tuple(torch.stack(p) for p in parts)  # type: ignore[return-value]


class TripletSet(Dataset):
    """Triplets over the traversals of several routes, redrawn by :meth:`resample`.

    Args:
        routes: the routes with their features.
        n: triplets per draw (spread evenly over routes and ordered traversal pairs).
        seed: seeds every draw (``(seed, epoch)``).
        hard_head: the head whose embeddings pick hard negatives (None: uniform negatives).
        hard_start_epoch: first epoch with hard negatives.
        sample_kwargs: :func:`sample_triplets` thresholds (``max_distance_m``, ...).

    Items: ``{"image": (3, C, h, w) float32}`` (ref, match, other) and ``"index"``
    ``(6,)`` int64 ``(route, query traversal, db traversal, ref, match, other)``.
    """

    def __init__(
        self,
        routes: Sequence[RouteFeatures],
        n: int,
        *,
        seed: int = 0,
        hard_head: nn.Module | None = None,
        hard_k: int = 10,
        hard_start_epoch: int = 1,
        **sample_kwargs: Any,
    ) -> None:
        if not routes:
            raise GeosegError("routes: no route to draw triplets from")
        feature_shape(routes)
        self.routes = list(routes)
        self.n = int(n)
        self.seed = int(seed)
        self.hard_head = hard_head
        self.hard_k = int(hard_k)
        self.hard_start_epoch = int(hard_start_epoch)
        self.sample_kwargs = sample_kwargs
        self.index = np.zeros((0, 6), dtype=np.int64)
        self.resample(0)

    def resample(self, epoch: int) -> None:
        """Draw this epoch's triplets."""
        jobs = [(r, q, d) for r, route in enumerate(self.routes) for q, d in traversal_pairs(route)]
        counts = split_count(self.n, len(jobs))
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, int(epoch), 5101]))
        hard = self.hard_head is not None and epoch >= self.hard_start_epoch
        emb_cache: dict[tuple[int, int], torch.Tensor] = {}
        rows = []
        for (r, q, d), count in zip(jobs, counts):
            if count == 0:
                continue
            route = self.routes[r]
            dist = None
            if hard:
                for t in (q, d):
                    if (r, t) not in emb_cache:
                        emb_cache[(r, t)] = embed_features(self.hard_head, route.features[t])
                dist = torch.cdist(emb_cache[(r, q)], emb_cache[(r, d)]).numpy()
            ref, match, other = sample_triplets(
                route.traversals[d].poses,
                route.traversals[q].poses,
                count,
                rng=rng,
                hard_negatives=dist,
                hard_k=self.hard_k,
                exclude_same_index=q == d,
                **self.sample_kwargs,
            )
            block = np.stack([np.full(count, r), np.full(count, q), np.full(count, d)], 1)
            rows.append(np.concatenate([block, np.stack([ref, match, other], 1)], 1))
        self.index = np.concatenate(rows).astype(np.int64)
        logger.debug("epoch %d: %d triplets (hard negatives: %s)", epoch, len(self.index), hard)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        r, q, d, a, p, n = (int(v) for v in self.index[i])
        feats = self.routes[r].features
        x = torch.stack([feats[q][a], feats[d][p], feats[d][n]]).float()
        return {"image": x, "index": torch.from_numpy(self.index[i].copy())}


# ============================================================================ main


def feature_loader(cfg: TrainConfig, dataset: Dataset, *, shuffle: bool, batch_size: int) -> Any:
    """A seeded in-process loader over a feature dataset (:func:`training.distributed.make_loader`)."""
    return dd.make_loader(
        dataset,
        batch_size=batch_size,
        shuffle=shuffle,
        seed=cfg.seed,
        num_workers=0,
        drop_last=shuffle and len(dataset) > batch_size,
    )


def main(cfg: RelocConfig, *, command: str | None = None) -> Path:
    """Train the embedding head as ``cfg`` says; returns the run directory.

    Raises:
        GeosegError: no ``trunk_checkpoint`` or one of another architecture, routes without
            triplets, an existing run without ``resume``/``overwrite``.
    """
    extractor = load_trunk(
        cfg.trunk_checkpoint, device=cfg.device, batch_size=cfg.feature_batch_size
    )
    train_routes = prepare_routes(cfg.routes, "train", extractor, progress=cfg.progress)
    val_routes = prepare_routes(cfg.routes, "val", extractor, progress=cfg.progress)
    c, h, w = feature_shape(train_routes + val_routes)
    if c != int(cfg.model_config.get("in_channels", 128)):
        raise GeosegError(
            f"model_config.in_channels: the trunk's features have {c} channels, the head expects "
            f"{cfg.model_config.get('in_channels', 128)}"
        )
    common.seed_model_init(cfg.seed)
    head = get_model("reloc", **cfg.model_config)
    model = TripletEmbedder(head)
    thresholds = {
        "max_distance_m": cfg.max_distance_m,
        "max_angle_deg": cfg.max_angle_deg,
        "min_negative_distance_m": cfg.min_negative_distance_m,
    }
    train_set = TripletSet(
        train_routes,
        cfg.triplets_per_epoch,
        seed=cfg.seed,
        hard_head=head if cfg.hard_negatives else None,
        hard_k=cfg.hard_k,
        hard_start_epoch=cfg.hard_start_epoch,
        **thresholds,
    )
    val_set = TripletSet(val_routes, cfg.val_triplets, seed=cfg.seed + 10_000, **thresholds)
    train_loader = ResamplingLoader(
        train_set,
        feature_loader(cfg, train_set, shuffle=True, batch_size=cfg.batch_size),
        start_epoch=resume_epoch(cfg),
    )
    val_loader = feature_loader(
        cfg, val_set, shuffle=False, batch_size=cfg.val_batch_size or cfg.batch_size
    )
    run_dir = fit(
        cfg,
        model,
        train_loader,
        val_loader,
        TripletLoss(cfg.loss_scale),
        TripletAccuracyMeter(),
        model_name="reloc_triplet",
        model_config=cfg.model_config,
        extra={"trunk_checkpoint": str(cfg.trunk_checkpoint)},
    )
    common.load_best_weights(model, run_dir)
    metrics = common.best_row(common.read_history(run_dir), cfg.best_metric, cfg.best_mode)
    # the best weights, checked with the library metric on the validation triplets
    metrics["val_triplet_accuracy_final"] = triplet_accuracy(*triplet_embeddings(head, val_set))
    finalize_head_run(
        run_dir,
        head.cpu().eval(),
        kind="reloc",
        cfg=cfg,
        model_name="reloc",
        model_config=dict(cfg.model_config),
        metrics=metrics,
        data_summary=describe_routes(cfg.routes, extractor),
        example_inputs=(torch.zeros(1, c, h, w),),
        command=command,
        export=cfg.export,
        extra_card={
            "trunk_checkpoint": str(cfg.trunk_checkpoint),
            "frozen": "trunk (features precomputed)",
            "input": f"(B, {c}, h, w) ENet layer-21 features; trained at h, w = {h}, {w}",
        },
    )
    return run_dir
