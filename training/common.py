"""What the segmentation-side trainers share: loaders from a config (the frame datasets are
:mod:`training.frame_data`), weights from earlier runs, and the end of a run (model checkpoint,
ONNX export, model card with the training frames' colour statistics, :mod:`training.colour_stats`).

Every trainer's run directory ends up holding (a stage with a path contract, docs/architecture.md)::

    config.yaml  last.pt  best.pt  metrics.csv  metrics.json  loss.png  metrics.png   (fit)
    model.pt     the best weights as a geoseg model checkpoint (geoseg.infer)
    model.onnx   the same network exported to ONNX (geoseg.export)
    model_card.json / model_card.md   data, config, command, metrics, timings

Images reach the networks normalised with :data:`training.frame_data.NORMALIZATION`, stored in
``model.pt`` and the ONNX metadata so that :class:`geoseg.infer.Segmenter` applies the same.
"""

from __future__ import annotations

import json
import logging
import math
import os
import platform
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.utils.data import Dataset

from geoseg.atomic import atomic_write
from geoseg.errors import ConfigError, GeosegError
from geoseg.infer import (
    MODEL_FILE,
    read_model_state,
    save_model_checkpoint,
)
from geoseg.infer import resolve_weights_file as resolve_weights_file  # re-exported
from geoseg.integrity import file_sha256
from training import distributed as dd
from training.checkpoint import BEST, LAST, restore_checkpoint
from training.colour_stats import card_entry
from training.config import DataConfig, TrainConfig
from training.frame_data import NORMALIZATION

logger = logging.getLogger(__name__)

ONNX_FILE = "model.onnx"
CARD_JSON = "model_card.json"
CARD_MD = "model_card.md"
# training frames pooled into the card's colour statistics (they settle within a few dozen)
COLOUR_STAT_FRAMES = 32


# ----------------------------------------------------------------------------- config
# trainers whose whole network can start from earlier weights of the same architecture
INIT_CHECKPOINT_TRAINERS = ("seg", "naive", "relpose")


def check_trainer_config(cfg: TrainConfig, *, trainer: str, model: str) -> None:
    """The ``__post_init__`` checks every image trainer's config shares.

    Args:
        cfg: the config; its ``train_crop`` (``(h, w)`` or None, when the trainer has one) must be
            positive and its ``model`` must be ``model``.
        trainer: trainer name for the message (``seg``, ``normals``, ``naive``).
        model: the registry name that trainer trains.

    Raises:
        ConfigError: a non-positive crop, another model, model options its builder does not
            take (checked now, not after the data are prepared), bad ``data.synth`` keys,
            ``init_checkpoint`` for a trainer that does not take it.
    """
    from geoseg.models.registry import check_model_config

    crop = getattr(cfg, "train_crop", None)
    if crop is not None and min(crop) < 1:
        raise ConfigError(f"train_crop: expected positive (h, w), got {crop}")
    if cfg.model != model:
        raise ConfigError(f"model: the {trainer} trainer trains {model!r}, got {cfg.model!r}")
    try:
        check_model_config(model, dict(cfg.model_config))
    except ConfigError as err:
        raise ConfigError(f"model_config: {err}") from None
    if cfg.init_checkpoint is not None and trainer not in INIT_CHECKPOINT_TRAINERS:
        raise ConfigError(
            f"init_checkpoint: the {trainer} trainer does not take it (trainers that do: "
            f"{', '.join(INIT_CHECKPOINT_TRAINERS)}; the others start from their *_checkpoint key)"
        )
    if cfg.data.source == "synth":
        from geoseg.data.synthetic import synthetic_config

        for split in ("train", "val"):
            synthetic_config(cfg.data.synth, split=split)


# ----------------------------------------------------------------------------- data
def prerender_frames(data: DataConfig, *datasets: Dataset | None) -> None:
    """Render the synthetic frames missing from ``data.cache_dir`` before training starts.

    Only with ``data.prerender_workers > 0``, a synthetic source and a cache directory. Under
    DDP the main process renders while the others wait at a barrier. Frames already cached are
    skipped.
    """
    if data.prerender_workers < 1 or data.source != "synth" or data.cache_dir is None:
        return
    from geoseg.data.synthetic import prerender

    if dd.is_main_process():
        for dataset in datasets:
            if dataset is not None:
                prerender(dataset, num_workers=data.prerender_workers)
    dd.barrier()


def make_loaders(cfg: TrainConfig, train_set: Dataset, val_set: Dataset | None) -> tuple[Any, Any]:
    """Seeded, shard-aware training and validation loaders (:func:`training.distributed.make_loader`)."""
    train = dd.make_loader(
        train_set,
        batch_size=cfg.batch_size,
        shuffle=True,
        seed=cfg.seed,
        num_workers=cfg.data.num_workers,
        drop_last=len(train_set) > cfg.batch_size,
    )
    return train, None if val_set is None else make_val_loader(cfg, val_set)


def make_val_loader(cfg: TrainConfig, val_set: Dataset) -> Any:
    """The validation loader of :func:`make_loaders`: in order, ``val_batch_size`` batches."""
    return dd.make_loader(
        val_set,
        batch_size=cfg.val_batch_size or cfg.batch_size,
        shuffle=False,
        seed=cfg.seed,
        num_workers=cfg.data.num_workers,
    )


def describe_data(data: DataConfig) -> dict[str, Any]:
    """Plain-data summary of the data a run used (for model cards)."""
    out: dict[str, Any] = {"source": data.source, "size_hw": list(data.size)}
    if data.source == "synth":
        from geoseg.config import to_dict
        from geoseg.data.synthetic import RENDER_VERSION, synthetic_config

        for split in ("train", "val"):
            out[split] = to_dict(synthetic_config(data.synth, split=split))
        out["render_version"] = RENDER_VERSION
    else:
        out.update(root=str(data.root), train_split=data.train_split, val_split=data.val_split)
    from geoseg.config import to_dict

    out["augment"] = to_dict(data.augment)
    out["grayscale"] = data.grayscale
    return out


# ----------------------------------------------------------------------------- weights
def load_state(
    path: str | os.PathLike, *, expected_model: str | None = None, option: str | None = None
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Weights and metadata of a model or training checkpoint, or a run directory holding one,
    through the package's one reader (:func:`geoseg.infer.read_model_state`).

    Args:
        path: file or run directory (:func:`resolve_weights_file`).
        expected_model: registry name the checkpoint must hold (e.g. ``"enet"``).
        option: the config key that named ``path`` (e.g. ``"trunk_checkpoint"``), prefixed to
            error messages.

    Returns:
        ``(state_dict, checkpoint)``.

    Raises:
        GeosegError: unreadable file, not a geoseg checkpoint, or another architecture.
    """
    try:
        return read_model_state(path, expected_model=expected_model)
    except GeosegError as err:
        if option is None:
            raise
        raise GeosegError(f"{option}: {err}") from None


def load_init_weights(model: nn.Module, path: str | os.PathLike, *, model_name: str) -> Path:
    """Initialise ``model`` from the weights at ``path`` (the ``init_checkpoint`` config key).

    Args:
        model: the freshly built network.
        path: a ``model.pt``, a training checkpoint or a run directory holding one, of the same
            architecture; or, when no such path exists, the name of shipped weights
            (``"seg"``: ``geoseg/weights/seg``, :mod:`geoseg.pretrained`).
        model_name: registry name of ``model``; a checkpoint of another model is refused.

    Returns:
        The file the weights came from.

    Raises:
        GeosegError: unreadable file, another architecture (another model name, or tensors
            whose names or shapes differ: the message lists the first ones).
    """
    try:
        from geoseg.pretrained import path_or_shipped

        file = resolve_weights_file(path_or_shipped(path))
    except GeosegError as err:
        raise GeosegError(f"init_checkpoint: {err}") from None
    state, _ = load_state(file, expected_model=model_name, option="init_checkpoint")
    own = model.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    reshaped = [
        f"{k} {tuple(state[k].shape)} vs {tuple(v.shape)}"
        for k, v in own.items()
        if k in state and tuple(state[k].shape) != tuple(v.shape)
    ]
    if missing or unexpected or reshaped:
        parts = []
        for label, names in (("missing", missing), ("unexpected", unexpected), ("shape", reshaped)):
            if names:
                parts.append(f"{label}: {', '.join(names[:3])}{' ...' if len(names) > 3 else ''}")
        raise GeosegError(
            f"init_checkpoint: {file} does not fit this {model_name!r} architecture "
            f"(model_config {_model_config_of(model)}); {'; '.join(parts)}"
        )
    model.load_state_dict(state)
    logger.info("initialised %s from %s", model_name, file)
    return file


def _model_config_of(model: nn.Module) -> str:
    num_classes = getattr(model, "num_classes", None)
    return f"num_classes={num_classes}" if num_classes is not None else type(model).__name__


def seed_model_init(seed: int) -> None:
    """Seed torch before building a model so that its initial weights depend on ``seed`` only."""
    torch.manual_seed(int(seed))


# ----------------------------------------------------------------------------- end of a run
def read_history(run_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The per-epoch rows of ``metrics.json`` (empty when absent)."""
    path = Path(run_dir) / "metrics.json"
    if not path.is_file():
        return []
    return list(json.loads(path.read_text()))


def load_best_weights(model: nn.Module, run_dir: str | os.PathLike) -> tuple[Path, dict[str, Any]]:
    """Load ``best.pt`` (else ``last.pt``) of ``run_dir`` into ``model``.

    Returns:
        ``(file, metrics)``: the file loaded and the metric row of the epoch it holds (from its
        own history), so that a model card always reports the metrics of the weights it ships.
    """
    run_dir = Path(run_dir)
    file = run_dir / BEST if (run_dir / BEST).is_file() else run_dir / LAST
    ckpt = restore_checkpoint(file, model, restore_rng=False)
    epoch = int(ckpt["epoch"])
    rows = [dict(r) for r in ckpt.get("history") or [] if r.get("epoch") == epoch]
    return file, rows[-1] if rows else {}


def finalize_run(
    run_dir: str | os.PathLike,
    model: nn.Module,
    *,
    kind: str,
    cfg: Any,
    model_name: str,
    model_config: Mapping[str, Any],
    metrics: Mapping[str, Any],
    data_summary: Mapping[str, Any],
    command: str | None = None,
    export: bool = True,
    example_size: Sequence[int] = (48, 64),
    extra_card: Mapping[str, Any] | None = None,
    extra_checkpoint: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``model.pt``, ``model.onnx`` (when ``export``) and the model card (main process).

    Args:
        run_dir: the run directory.
        model: the trained model, best weights already loaded.
        kind: trainer name (``seg``, ``normals``, ``naive``).
        cfg: the run's config (``as_dict()`` or a dataclass).
        model_name, model_config: registry name and builder arguments.
        metrics: final metrics (flat mapping).
        data_summary: :func:`describe_data` output.
        command: the command line that produced the run.
        export: export ONNX.
        example_size: ``(H, W)`` of the export's example input (the graph is dynamic).
        extra_card: more entries for the card.
        extra_checkpoint: more entries for ``model.pt``.

    Returns:
        ``run_dir``.
    """
    run_dir = Path(run_dir)
    if not dd.is_main_process():
        return run_dir
    files = {"checkpoint": MODEL_FILE}
    save_model_checkpoint(
        model,
        run_dir / MODEL_FILE,
        model_name=model_name,
        model_config=dict(model_config),
        normalization=NORMALIZATION,
        extra=dict(extra_checkpoint or {}),
    )
    if export:
        from geoseg.export import export_onnx

        t0 = time.perf_counter()
        h, w = (int(s) for s in example_size)
        export_onnx(
            model,
            run_dir / ONNX_FILE,
            example_inputs=torch.zeros(1, 3, h, w),
            metadata={
                "model_name": model_name,
                "model_config": dict(model_config),
                "normalization": NORMALIZATION,
            },
        )
        files["onnx"] = ONNX_FILE
        logger.info("exported %s in %.1f s", run_dir / ONNX_FILE, time.perf_counter() - t0)
    cfg_dict = cfg.as_dict() if hasattr(cfg, "as_dict") else _plain(cfg)
    history = read_history(run_dir)
    card: dict[str, Any] = {
        "trainer": kind,
        "model_name": model_name,
        "model_config": dict(model_config),
        "parameters": sum(p.numel() for p in model.parameters()),
        "normalization": NORMALIZATION,
        "data": dict(data_summary),
        "config": cfg_dict,
        "command": command or f"python -c 'from training.{kind} import main; main(cfg)'",
        "metrics": {k: _json_number(v) for k, v in metrics.items()},
        "epochs": len(history),
        "train_minutes": round(sum(float(r.get("time_s") or 0.0) for r in history) / 60.0, 3),
        "files": files,
        "machine": {
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "torch": torch.__version__,
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        },
    }
    card.update(extra_card or {})
    # what load_model_checkpoint / OnnxModel verify files without an embedded digest against
    card["sha256"] = {
        f: file_sha256(run_dir / f) for f in card["files"].values() if (run_dir / f).is_file()
    }
    atomic_write(run_dir / CARD_JSON, json.dumps(card, indent=1, default=str))
    atomic_write(run_dir / CARD_MD, _card_markdown(card))
    return run_dir


def finish_run(
    run_dir: str | os.PathLike,
    model: nn.Module,
    cfg: Any,
    *,
    kind: str,
    model_name: str,
    command: str | None = None,
    extra_card: Mapping[str, Any] | None = None,
    extra_metrics: Callable[[nn.Module], Mapping[str, Any]] | None = None,
) -> Path:
    """The end of an image trainer's ``main``: best weights, best epoch's metrics, artefacts.

    Loads the best weights into ``model`` and takes the metrics of the epoch they come from
    (:func:`load_best_weights`), records the training frames' colour statistics in the card
    (``colour_statistics``, :mod:`training.colour_stats`), adds
    ``extra_metrics(model)`` when given (e.g. a dense evaluation, run on the best weights before
    the model moves to the CPU), then :func:`finalize_run` with the config's data summary,
    ``cfg.export`` and ``cfg.data.size`` as the export's example size.

    Args:
        run_dir: the run directory :func:`training.loop.fit` returned.
        model: the trained model (any device).
        cfg: the run's :class:`~training.config.TrainConfig` (with ``export``).
        kind: trainer name (``seg``, ``normals``, ``naive``).
        model_name: registry name of ``model``.
        command: the command line that produced the run.
        extra_card: more entries for the model card.
        extra_metrics: ``model -> {name: value}`` merged into the final metrics.

    Returns:
        ``run_dir`` as a :class:`~pathlib.Path`.
    """
    _, metrics = load_best_weights(model, run_dir)
    if extra_metrics is not None:
        metrics.update(extra_metrics(model))
    card = dict(extra_card or {})
    if dd.is_main_process():  # the training set's colours, for the colour transfer at inference
        card.update(card_entry(cfg.data, frames=COLOUR_STAT_FRAMES))
    return finalize_run(
        run_dir,
        model.cpu(),
        kind=kind,
        cfg=cfg,
        model_name=model_name,
        model_config=cfg.model_config,
        metrics=metrics,
        data_summary=describe_data(cfg.data),
        command=command,
        export=cfg.export,
        example_size=cfg.data.size,
        extra_card=card,
    )


def _json_number(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _plain(cfg: Any) -> Any:
    from geoseg.config import to_dict

    return to_dict(cfg)


def _card_markdown(card: Mapping[str, Any]) -> str:
    lines = [
        f"# Model card: {card['model_name']} ({card['trainer']})",
        "",
        f"- parameters: {card['parameters']:,}",
        f"- epochs: {card['epochs']}, CPU/GPU training time: {card['train_minutes']} min",
        f"- command: `{card['command']}`",
        f"- files: {', '.join(str(v) for v in card['files'].values())}",
        f"- normalisation (images in [0, 1]): mean {card['normalization']['mean']}, "
        f"std {card['normalization']['std']}",
        "",
        "## Metrics",
        "",
        "| metric | value |",
        "|---|---|",
    ]
    for key, value in card["metrics"].items():
        shown = f"{value:.4f}" if isinstance(value, float) else str(value)
        lines.append(f"| {key} | {shown} |")
    if card.get("averaged_from"):  # training/average.py: the weights' ancestry
        lines += ["", "## Averaged from", "", *_source_lines(card["averaged_from"], depth=0)]
    lines += [
        "",
        "## Data",
        "",
        "```json",
        json.dumps(card["data"], indent=1, default=str),
        "```",
        "",
        "## Config",
        "",
        "```json",
        json.dumps(card["config"], indent=1, default=str),
        "```",
        "",
    ]
    return "\n".join(lines)


def _source_lines(sources: Sequence[Mapping[str, Any]], depth: int) -> list[str]:
    """Markdown bullets for an average's sources, nested under the averages they come from."""
    lines = []
    for source in sources:
        made_by = f", made by `{source['command']}`" if source.get("command") else ""
        lines.append(
            f"{'  ' * depth}- {source['weight']} x `{source['file']}` "
            f"(SHA-256 {source['sha256'][:12]}...){made_by}"
        )
        lines += _source_lines(source.get("averaged_from") or [], depth + 1)
    return lines
