"""What the head trainers (:mod:`training.reloc`, :mod:`training.relpose`) share.

Both heads sit on the frozen layers 1-21 of a trained ``enet``/``joint`` model
(``trunk_checkpoint``): the trunk's ``(C, h, w)`` features (``C`` = 128) are computed **once** per
traversal of the tram routes of :class:`RoutesConfig` and cached
(:func:`geoseg.data.traversals.route_features`), then a head trains on features only, with a
dataset redrawn every epoch (:class:`ResamplingLoader`).

A head trainer's ``main`` reads::

    data = prepare_head_features(cfg)                  # trunk, route features, (C, h, w)
    common.seed_model_init(cfg.seed)
    head = get_model(cfg.model, **cfg.model_config)
    model = Wrapper(head)                              # stacked features -> head outputs
    run_dir = fit_head(cfg, model, train_set, val_set, loss_fn, meter, model_name=...)
    finish_head_run(run_dir, model, cfg, data, kind=..., command=command)

The config base is :class:`HeadTrainConfig`; ``model.pt`` and ``model.onnx`` of a run are the head
alone, taking ``(B, C, h, w)`` feature maps.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from geoseg.config import check_range
from geoseg.data.synthetic import TRAIN_CONDITIONS, VAL_SEEDS
from geoseg.data.traversals import RouteFeatures, TrunkFeatureExtractor, route_features, route_specs
from geoseg.errors import ConfigError, GeosegError
from geoseg.models.registry import get_model
from training import common
from training import distributed as dd
from training.checkpoint import LAST, load_checkpoint
from training.config import TrainConfig
from training.loop import fit

__all__ = [
    "HeadFeatures",
    "HeadTrainConfig",
    "ResamplingLoader",
    "RoutesConfig",
    "describe_routes",
    "feature_loader",
    "feature_shape",
    "finalize_head_run",
    "finish_head_run",
    "fit_head",
    "load_trunk",
    "prepare_head_features",
    "prepare_routes",
    "resume_epoch",
    "split_count",
]


# ============================================================================ config


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
        aligned_conditions: per route, that many more traversals at its first traversal's
            poses (no along-track offset), in conditions of the pool the route does not use:
            views of one place in two conditions, for the relative-pose head's near pairs.
        aligned_yaw_jitter_deg: yaw jitter of the aligned traversals, +- degrees.
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
    aligned_conditions: int = 0
    aligned_yaw_jitter_deg: float = 3.0
    draw_seed: int = 0

    def __post_init__(self) -> None:
        from geoseg.data.synthetic import EVAL_SEEDS, HELDOUT_CONDITIONS

        if not self.train_seeds or not self.val_seeds:
            raise ConfigError("routes.train_seeds / routes.val_seeds: expected at least one city")
        for key in ("train_seeds", "val_seeds"):
            if any(seed < 0 for seed in getattr(self, key)):
                raise ConfigError(f"routes.{key}: expected seeds >= 0, got {getattr(self, key)}")
        if self.draw_seed < 0:
            raise ConfigError(f"routes.draw_seed: expected >= 0, got {self.draw_seed}")
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
        check_range("routes.hfov_deg", self.hfov_deg, 0.0, 180.0, low_open=True, high_open=True)
        for key in ("length_m", "val_length_m", "spacing_m"):
            check_range(f"routes.{key}", getattr(self, key), 0.0, None, low_open=True)
        check_range("routes.offset_m", self.offset_m, 0.0)
        check_range("routes.yaw_jitter_deg", self.yaw_jitter_deg, 0.0, 180.0)
        check_range("routes.aligned_yaw_jitter_deg", self.aligned_yaw_jitter_deg, 0.0, 180.0)
        spare = len(self.conditions) - self.conditions_per_route
        if not 0 <= self.aligned_conditions <= spare:
            raise ConfigError(
                f"routes.aligned_conditions: expected 0..{spare} (the conditions a route does "
                f"not use), got {self.aligned_conditions}"
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

    def aligned_spec(self, spec: Any) -> Any:
        """The traversals of ``spec``'s route at its first traversal's poses: a
        :class:`~geoseg.data.traversals.RouteSpec` whose first condition is ``spec``'s first
        (the same cached traversal) followed by ``aligned_conditions`` others, drawn with
        ``(draw_seed, seed, 5152)``; None when ``aligned_conditions`` is 0."""
        if not self.aligned_conditions:
            return None
        spare = [c for c in self.conditions if c not in spec.conditions]
        rng = np.random.default_rng(np.random.SeedSequence([self.draw_seed, spec.seed, 5152]))
        pick = rng.choice(len(spare), size=self.aligned_conditions, replace=False)
        return dataclasses.replace(
            spec,
            conditions=[spec.conditions[0], *(spare[j] for j in pick)],
            offset_m=0.0,
            yaw_jitter_deg=self.aligned_yaw_jitter_deg,
        )


@dataclass
class HeadTrainConfig(TrainConfig):
    """The fields and checks every head trainer's config shares (beyond
    :class:`~training.config.TrainConfig`; ``data`` is unused: the traversals come from
    ``routes``).

    A subclass sets ``trainer`` (its name, which is also the registry name of the head it trains,
    so ``model`` must equal it) and ``count_keys`` (its fields that must be >= 1, checked in
    that order before ``feature_batch_size``), and adds its own fields and checks.

    Attributes:
        trunk_checkpoint: the trained ENet (or joint) model: file or run directory (required).
        routes: the training and validation routes.
        feature_batch_size: images per trunk forward pass when extracting features.
        export: export ``model.onnx`` at the end.
    """

    trainer: ClassVar[str] = ""
    count_keys: ClassVar[tuple[str, ...]] = ()

    batch_size: int = 32
    trunk_checkpoint: Path | None = None
    routes: RoutesConfig = field(default_factory=RoutesConfig)
    feature_batch_size: int = 16
    export: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        common.check_trainer_config(self, trainer=self.trainer, model=self.trainer)
        for key in (*self.count_keys, "feature_batch_size"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{key}: expected >= 1, got {getattr(self, key)}")
        if self.trunk_checkpoint is not None:
            self.trunk_checkpoint = Path(self.trunk_checkpoint)


# ============================================================================ trunk and routes


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
    state, ckpt = common.load_state(path, option="trunk_checkpoint")
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
    """Render (or read) the routes of ``split`` and their layer-21 features (images dropped);
    a route's aligned traversals (``routes.aligned_conditions``) follow its own."""
    out = []
    for spec in routes.specs(split):
        kw = {"cache_dir": routes.cache_dir, "progress": progress, "keep_images": False}
        route = route_features(spec, extractor, **kw)
        aligned = routes.aligned_spec(spec)
        if aligned is not None:
            extra = route_features(aligned, extractor, **kw)
            if not np.allclose(extra.traversals[0].t_wc, route.traversals[0].t_wc, atol=1e-6):
                raise GeosegError(f"city {spec.seed}: the aligned traversals left the route")
            route = RouteFeatures(
                spec,
                route.traversals + extra.traversals[1:],
                route.features + extra.features[1:],
                aligned=aligned,
            )
        out.append(route)
    return out


def feature_shape(routes: Sequence[RouteFeatures]) -> tuple[int, int, int]:
    """The common ``(C, h, w)`` of the routes' features.

    Raises:
        GeosegError: feature maps of mismatched sizes.
    """
    shapes = {tuple(f.shape[1:]) for r in routes for f in r.features}
    if len(shapes) != 1:
        raise GeosegError(f"feature maps of mismatched sizes across routes: {sorted(shapes)}")
    return shapes.pop()


@dataclass
class HeadFeatures:
    """The frozen trunk of a head run and the features of its routes.

    Attributes:
        extractor: the trunk (its ``fingerprint`` goes into the model card).
        train, val: the training and validation routes with their ``(n, C, h, w)`` features.
        shape: the common ``(C, h, w)`` of every feature map.
    """

    extractor: TrunkFeatureExtractor
    train: list[RouteFeatures]
    val: list[RouteFeatures]
    shape: tuple[int, int, int]


def prepare_head_features(cfg: HeadTrainConfig) -> HeadFeatures:
    """Load the trunk of ``cfg.trunk_checkpoint``, then render (or read) the training and
    validation routes of ``cfg.routes`` and their features.

    Raises:
        GeosegError: no ``trunk_checkpoint`` or one of another architecture, feature maps of
            mismatched sizes.
    """
    extractor = load_trunk(
        cfg.trunk_checkpoint, device=cfg.device, batch_size=cfg.feature_batch_size
    )
    train = prepare_routes(cfg.routes, "train", extractor, progress=cfg.progress)
    val = prepare_routes(cfg.routes, "val", extractor, progress=cfg.progress)
    return HeadFeatures(extractor, train, val, feature_shape(train + val))


def describe_routes(routes: RoutesConfig, extractor: TrunkFeatureExtractor) -> dict[str, Any]:
    """Plain-data summary of the routes and trunk of a run (model cards)."""
    from geoseg.config import to_dict

    out = {
        "source": "synth traversals (geoseg.data.traversals)",
        "train_routes": [to_dict(s) for s in routes.specs("train")],
        "val_routes": [to_dict(s) for s in routes.specs("val")],
        "trunk_fingerprint": extractor.fingerprint,
    }
    for split in ("train", "val"):
        aligned = [routes.aligned_spec(s) for s in routes.specs(split)]
        if any(a is not None for a in aligned):
            out[f"{split}_aligned_routes"] = [to_dict(a) for a in aligned if a is not None]
    return out


# ============================================================================ sampling and loaders


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


def fit_head(
    cfg: HeadTrainConfig,
    model: nn.Module,
    train_set: Dataset,
    val_set: Dataset,
    loss_fn: Any,
    meter: Any,
    *,
    model_name: str,
) -> Path:
    """:func:`training.loop.fit` on feature datasets; returns the run directory.

    Args:
        cfg: the run's config.
        model: the head in its training wrapper (stacked features ``(B, k, C, h, w)`` -> outputs).
        train_set: redrawn every epoch through ``resample(epoch)`` (:class:`ResamplingLoader`,
            starting at the resumed epoch so that a resumed run draws the next epoch's samples).
        val_set: fixed validation samples.
        loss_fn, meter: the loss and validation meter.
        model_name: name of the wrapper in the training checkpoints.
    """
    train_loader = ResamplingLoader(
        train_set,
        feature_loader(cfg, train_set, shuffle=True, batch_size=cfg.batch_size),
        start_epoch=resume_epoch(cfg),
    )
    val_loader = feature_loader(
        cfg, val_set, shuffle=False, batch_size=cfg.val_batch_size or cfg.batch_size
    )
    return fit(
        cfg,
        model,
        train_loader,
        val_loader,
        loss_fn,
        meter,
        model_name=model_name,
        model_config=cfg.model_config,
        extra={"trunk_checkpoint": str(cfg.trunk_checkpoint)},
    )


# ============================================================================ end of a run


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


def finish_head_run(
    run_dir: Path,
    model: nn.Module,
    cfg: HeadTrainConfig,
    data: HeadFeatures,
    *,
    kind: str,
    input_names: Sequence[str] = (),
    command: str | None = None,
    extra_card: Mapping[str, Any] | None = None,
    extra_metrics: Callable[[nn.Module], Mapping[str, Any]] | None = None,
) -> Path:
    """The end of a head trainer's ``main``: best weights, best epoch's metrics, artefacts.

    Loads the best weights into ``model`` and takes the metrics of the epoch they come from
    (:func:`training.common.load_best_weights`), adds
    ``extra_metrics(head)`` when given (run on the best weights before the head moves to the
    CPU), then writes the head's ``model.pt``, ``model.onnx`` (when ``cfg.export``) and card
    (:func:`finalize_head_run`).

    Args:
        run_dir: the run directory :func:`fit_head` returned.
        model: the training wrapper, the head (registry name ``cfg.model``) at ``model.head``.
        cfg: the run's config.
        data: the run's trunk and features (``data.shape`` = ``(C, h, w)`` sizes the export's
            example inputs, zeros ``(1, C, h, w)``).
        kind: trainer name (``reloc``, ``relpose``).
        input_names: names of the head's feature inputs, one example input each (none: one
            unnamed input); the card's ``input`` line lists them.
        command: the command line that produced the run.
        extra_card: more entries for the model card (after ``trunk_checkpoint``, ``frozen``,
            ``input``).
        extra_metrics: ``head -> {name: value}`` merged into the final metrics.

    Returns:
        ``run_dir``.
    """
    _, metrics = common.load_best_weights(model, run_dir)
    if extra_metrics is not None:
        metrics.update(extra_metrics(model.head))
    c, h, w = data.shape
    example = torch.zeros(1, c, h, w)
    examples = [example] + [example.clone() for _ in range(len(input_names) - 1)]
    names = f"{', '.join(input_names)}: " if input_names else ""
    return finalize_head_run(
        run_dir,
        model.head.cpu().eval(),
        kind=kind,
        cfg=cfg,
        model_name=cfg.model,
        model_config=dict(cfg.model_config),
        metrics=metrics,
        data_summary=describe_routes(cfg.routes, data.extractor),
        example_inputs=examples,
        command=command,
        export=cfg.export,
        extra_card={
            "trunk_checkpoint": str(cfg.trunk_checkpoint),
            "frozen": "trunk (features precomputed)",
            "input": f"{names}(B, {c}, h, w) ENet layer-21 features; trained at h, w = {h}, {w}",
            **(extra_card or {}),
        },
    )
