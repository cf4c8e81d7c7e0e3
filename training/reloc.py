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

What :mod:`training.relpose` shares (:class:`RoutesConfig`, :func:`load_trunk`,
:func:`prepare_routes`, :class:`ResamplingLoader`, :func:`finalize_head_run`, the config base and
the start and end of a run) lives in :mod:`training.heads`; the public names stay importable
from here.

Usage::

    geoseg train reloc --config configs/reloc.yaml --set trunk_checkpoint=runs/seg
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from geoseg.config import check_range
from geoseg.data.pairs import sample_triplets
from geoseg.data.traversals import RouteFeatures
from geoseg.errors import ConfigError, GeosegError
from geoseg.models.registry import get_model
from geoseg.models.reloc import triplet_loss
from geoseg.reloc.retrieval import triplet_accuracy
from training import common
from training.heads import (
    HeadTrainConfig,
    ResamplingLoader,
    RoutesConfig,
    feature_shape,
    finalize_head_run,
    finish_head_run,
    fit_head,
    load_trunk,
    prepare_head_features,
    prepare_routes,
    split_count,
)
from training.heads import describe_routes as describe_routes  # re-exported
from training.heads import feature_loader as feature_loader  # re-exported
from training.heads import resume_epoch as resume_epoch  # re-exported
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


# ============================================================================ config


@dataclass
class RelocConfig(HeadTrainConfig):
    """Embedding-head training run (fields beyond :class:`~training.heads.HeadTrainConfig`:
    ``trunk_checkpoint``, ``routes``, ``feature_batch_size``, ``export``).

    Attributes:
        triplets_per_epoch: fresh triplets drawn each epoch.
        val_triplets: fixed validation triplets.
        max_distance_m, max_angle_deg: same place (positives, :func:`positive_mask`).
        min_negative_distance_m: a negative is at least this far from the ref, metres.
        hard_negatives: mine hard negatives with the current head each epoch.
        hard_k: hard-negative pool size per ref.
        hard_start_epoch: first epoch (0-based) with hard negatives (the head needs a start).
        loss_scale: inverse temperature of eq. 5.1 (1 = the thesis).
    """

    trainer: ClassVar[str] = "reloc"
    count_keys: ClassVar[tuple[str, ...]] = ("triplets_per_epoch", "val_triplets", "hard_k")

    model: str = "reloc"
    out_dir: Path = Path("runs/reloc")
    best_metric: str = "val_triplet_accuracy"
    best_mode: Literal["min", "max"] = "max"
    triplets_per_epoch: int = 4000
    val_triplets: int = 1000
    max_distance_m: float = 5.0
    max_angle_deg: float = 30.0
    min_negative_distance_m: float = 25.0
    hard_negatives: bool = True
    hard_k: int = 10
    hard_start_epoch: int = 1
    loss_scale: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.hard_start_epoch < 0:
            raise ConfigError(f"hard_start_epoch: expected >= 0, got {self.hard_start_epoch}")
        if not self.loss_scale > 0:
            raise ConfigError(f"loss_scale: expected > 0, got {self.loss_scale}")
        check_range("max_distance_m", self.max_distance_m, 0.0, None, low_open=True)
        check_range("max_angle_deg", self.max_angle_deg, 0.0, 180.0, low_open=True)
        if self.min_negative_distance_m < self.max_distance_m:
            raise ConfigError("min_negative_distance_m: expected >= max_distance_m")


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


def traversal_pairs(route: RouteFeatures) -> list[tuple[int, int]]:
    """Ordered ``(query, database)`` traversal pairs of a route: every cross-condition pair,
    or ``(0, 0)`` when the route has one traversal."""
    n = len(route.traversals)
    return [(0, 0)] if n == 1 else [(i, j) for i in range(n) for j in range(n) if i != j]


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


def main(cfg: RelocConfig, *, command: str | None = None) -> Path:
    """Train the embedding head as ``cfg`` says; returns the run directory.

    Raises:
        GeosegError: no ``trunk_checkpoint`` or one of another architecture, routes without
            triplets, an existing run without ``resume``/``overwrite``.
    """
    data = prepare_head_features(cfg)
    c = data.shape[0]
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
        data.train,
        cfg.triplets_per_epoch,
        seed=cfg.seed,
        hard_head=head if cfg.hard_negatives else None,
        hard_k=cfg.hard_k,
        hard_start_epoch=cfg.hard_start_epoch,
        **thresholds,
    )
    val_set = TripletSet(data.val, cfg.val_triplets, seed=cfg.seed + 10_000, **thresholds)
    run_dir = fit_head(
        cfg,
        model,
        train_set,
        val_set,
        TripletLoss(cfg.loss_scale),
        TripletAccuracyMeter(),
        model_name="reloc_triplet",
    )
    return finish_head_run(
        run_dir,
        model,
        cfg,
        data,
        kind="reloc",
        command=command,
        # the best weights, checked with the library metric on the validation triplets
        extra_metrics=lambda head: {
            "val_triplet_accuracy_final": triplet_accuracy(*triplet_embeddings(head, val_set))
        },
    )
