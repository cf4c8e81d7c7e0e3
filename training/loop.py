"""The shared training loop: ``train_one_epoch``, ``evaluate`` and ``fit`` (the generic main).

Conventions every trainer follows:

* a **batch** is a dict of tensors, at least ``{"image": (B, 3, H, W) float}`` plus the targets
  (``"labels": (B, H, W) int64``, ``"normals": (B, 3, H, W)``...); a ``(image, labels)`` tuple is
  accepted and turned into that dict;
* the **model** maps ``batch["image"]`` to a dict of named outputs (``{"logits": (B, C, H, W),
  "normals": (B, 3, H, W), ...}``); a bare tensor is read as ``{"logits": tensor}``;
* a **loss function** ``loss_fn(outputs, batch)`` returns a scalar tensor, or a dict with a
  scalar ``"loss"`` and further scalar terms that are logged;
* a **metric** is a :class:`training.metrics.Meter` (``reset``, ``update(outputs, batch)``,
  ``compute() -> dict``).

:func:`fit` writes into ``cfg.out_dir``: ``config.yaml``, ``last.pt`` / ``best.pt`` (atomic),
``metrics.csv`` / ``metrics.json`` (one row per epoch) and ``loss.png`` / ``metrics.png``, and
returns that directory (a stage with a path contract, docs/architecture.md). With ``cfg.resume`` it continues from ``last.pt`` exactly:
weights, optimizer, scheduler, AMP scaler, epoch, step, history and every RNG, including the
training loader's generators, are restored.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
import yaml
from torch import nn
from tqdm.auto import tqdm

from geoseg.atomic import atomic_write
from geoseg.config import to_dict
from geoseg.errors import GeosegError
from training import distributed as dd
from training.checkpoint import (
    LAST,
    build_checkpoint,
    restore_checkpoint,
    save_run_checkpoints,
    to_plain,
)
from training.config import OptimConfig, ScheduleConfig, TrainConfig
from training.plots import plot_history
from training.reproducibility import (
    capture_generators,
    loader_generators,
    restore_generators,
    seed_everything,
    set_deterministic,
)
from training.resume import apply_optim_config, check_resume_config, record_run_files, start_run

logger = logging.getLogger(__name__)

LossFn = Callable[[Mapping[str, torch.Tensor], Mapping[str, Any]], Any]
_VOLATILE_KEYS = {"epochs", "resume", "overwrite", "progress", "plots", "device", "out_dir"}


# ----------------------------------------------------------------------------- helpers
def as_batch(batch: Any) -> dict[str, Any]:
    """A batch as a dict: dicts pass, ``(image, labels, ...)`` tuples become
    ``{"image": ..., "labels": ...}``."""
    if isinstance(batch, Mapping):
        return dict(batch)
    if isinstance(batch, list | tuple) and len(batch) >= 2:
        return {"image": batch[0], "labels": batch[1]}
    raise GeosegError(
        f"batch: expected a dict or an (image, labels) pair, got {type(batch).__name__}"
    )


def to_device(batch: Mapping[str, Any], device: torch.device) -> dict[str, Any]:
    """Move every tensor of a batch dict to ``device`` (others untouched)."""
    non_blocking = device.type == "cuda"
    return {
        k: v.to(device, non_blocking=non_blocking) if isinstance(v, torch.Tensor) else v
        for k, v in batch.items()
    }


def as_outputs(outputs: Any) -> dict[str, torch.Tensor]:
    """The model's outputs as a dict (a bare tensor is ``{"logits": tensor}``)."""
    if isinstance(outputs, Mapping):
        return dict(outputs)
    if isinstance(outputs, torch.Tensor):
        return {"logits": outputs}
    raise GeosegError(f"model output: expected a dict or a tensor, got {type(outputs).__name__}")


def _split_loss(value: Any) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    if isinstance(value, Mapping):
        if "loss" not in value:
            raise GeosegError(f"loss_fn: a dict result needs a 'loss' entry, got {sorted(value)}")
        return value["loss"], {k: v for k, v in value.items() if k != "loss"}
    if isinstance(value, torch.Tensor):
        return value, {}
    raise GeosegError(f"loss_fn: expected a tensor or a dict, got {type(value).__name__}")


def _batch_size(batch: Mapping[str, Any]) -> int:
    image = batch.get("image")
    if not isinstance(image, torch.Tensor) or image.ndim < 1:
        raise GeosegError("batch: expected an 'image' tensor of shape (B, 3, H, W)")
    return int(image.shape[0])


def build_optimizer(model: nn.Module, cfg: OptimConfig) -> torch.optim.Optimizer:
    """The optimizer of ``cfg`` over the parameters that require gradients.

    Raises:
        GeosegError: the model has no trainable parameter.
    """
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise GeosegError("model: no parameter requires grad (everything frozen?)")
    if cfg.name == "adam":
        return torch.optim.Adam(params, lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
    if cfg.name == "adamw":
        return torch.optim.AdamW(params, lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
    return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)


def lr_factor(cfg: ScheduleConfig, step: int, steps_per_epoch: int, epochs: int) -> float:
    """Learning-rate multiplier after ``step`` optimizer steps (see :class:`ScheduleConfig`)."""
    total = max(1, steps_per_epoch * epochs)
    warm = min(1.0, (step + 1) / cfg.warmup_steps) if cfg.warmup_steps else 1.0
    if cfg.name == "step":
        base = cfg.gamma ** (step // max(1, cfg.step_epochs * steps_per_epoch))
    elif cfg.name == "poly":
        base = max(0.0, 1.0 - step / total) ** cfg.power
    elif cfg.name == "cosine":
        t = min(step, total) / total
        base = cfg.min_factor + (1.0 - cfg.min_factor) * 0.5 * (1.0 + math.cos(math.pi * t))
    else:
        base = 1.0
    return warm * base


def build_scheduler(
    optimizer: torch.optim.Optimizer, cfg: ScheduleConfig, *, steps_per_epoch: int, epochs: int
) -> torch.optim.lr_scheduler.LambdaLR:
    """A per-step :class:`LambdaLR` following :func:`lr_factor` (its state is plain data)."""

    def factor(step: int) -> float:
        return lr_factor(cfg, step, steps_per_epoch, epochs)

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


# ----------------------------------------------------------------------------- epoch
def train_one_epoch(
    model: nn.Module,
    loader: Any,
    loss_fn: LossFn,
    optimizer: torch.optim.Optimizer,
    *,
    device: torch.device | str,
    scaler: torch.amp.GradScaler | None = None,
    scheduler: Any = None,
    progress: bool = True,
    grad_clip: float | None = None,
    epoch: int | None = None,
) -> dict[str, float]:
    """One pass over ``loader`` with one optimizer step per batch.

    Args:
        model: maps `(B, 3, H, W)` images to named outputs (module docstring).
        loader: iterable of batches.
        loss_fn: ``loss_fn(outputs, batch)`` → scalar tensor or dict with ``"loss"``.
        optimizer: steps once per batch.
        device: where the batches go (the model must already be there).
        scaler: AMP grad scaler; when given, forward runs under ``torch.autocast``.
        scheduler: stepped once per batch (after the optimizer).
        progress: show a tqdm bar (main process only).
        grad_clip: max global gradient L2 norm, or None.
        epoch: only for the progress bar's label.

    Returns:
        This process's sample-weighted means ``{"loss", <extra loss terms>...}`` plus ``lr``
        (after the epoch), ``n_samples`` and ``steps``.

    Raises:
        GeosegError: a non-finite loss (names the step), an empty loader, a malformed batch.
    """
    device = torch.device(device)
    model.train()
    totals: dict[str, float] = {}
    n_samples = 0
    steps = 0
    desc = "train" if epoch is None else f"epoch {epoch}"
    bar = tqdm(
        loader,
        desc=desc,
        leave=False,
        dynamic_ncols=True,
        disable=not (progress and dd.is_main_process()),
    )
    for batch in bar:
        batch = to_device(as_batch(batch), device)
        bs = _batch_size(batch)
        with torch.autocast(device_type=device.type, enabled=scaler is not None):
            outputs = as_outputs(model(batch["image"]))
            loss, parts = _split_loss(loss_fn(outputs, batch))
        if loss.ndim != 0:
            raise GeosegError(f"loss_fn: expected a scalar loss, got shape {tuple(loss.shape)}")
        loss_value = float(loss.detach())
        if not math.isfinite(loss_value):
            raise GeosegError(f"loss is {loss_value} at step {steps} of {desc}; stopping")
        optimizer.zero_grad(set_to_none=True)
        if scaler is not None:
            scaler.scale(loss).backward()
            if grad_clip is not None:
                scaler.unscale_(optimizer)
                nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
            scaler.step(optimizer)
            scaler.update()
        else:
            loss.backward()
            if grad_clip is not None:
                nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
            optimizer.step()
        if scheduler is not None:
            scheduler.step()
        totals["loss"] = totals.get("loss", 0.0) + loss_value * bs
        for key, value in parts.items():
            totals[key] = totals.get(key, 0.0) + float(value.detach()) * bs
        n_samples += bs
        steps += 1
        if steps % 10 == 0 or steps == 1:
            bar.set_postfix(loss=f"{loss_value:.4f}")
    if steps == 0:
        raise GeosegError("train loader: yielded no batch (empty dataset?)")
    out = {k: v / n_samples for k, v in totals.items()}
    out.update(lr=float(optimizer.param_groups[0]["lr"]), n_samples=n_samples, steps=steps)
    return out


def evaluate(
    model: nn.Module,
    loader: Any,
    metric_fn: Any,
    *,
    device: torch.device | str,
    loss_fn: LossFn | None = None,
    progress: bool = False,
) -> dict[str, float]:
    """Evaluate without gradients; metrics and loss are reduced over processes.

    Args:
        model: maps `(B, 3, H, W)` images to named outputs.
        loader: iterable of batches.
        metric_fn: a :class:`training.metrics.Meter`, or None for the loss only.
        device: where the batches go.
        loss_fn: when given, its sample-weighted mean is reported as ``"loss"``.
        progress: show a tqdm bar (main process only).

    Returns:
        ``metric_fn.compute()`` merged with ``{"loss": ...}`` when ``loss_fn`` is given.
    """
    device = torch.device(device)
    model.eval()
    if metric_fn is not None:
        metric_fn.reset()
    total_loss, n_samples = 0.0, 0
    with torch.inference_mode():
        for batch in tqdm(
            loader,
            desc="eval",
            leave=False,
            dynamic_ncols=True,
            disable=not (progress and dd.is_main_process()),
        ):
            batch = to_device(as_batch(batch), device)
            bs = _batch_size(batch)
            outputs = as_outputs(model(batch["image"]))
            if metric_fn is not None:
                metric_fn.update(outputs, batch)
            if loss_fn is not None:
                loss, _ = _split_loss(loss_fn(outputs, batch))
                total_loss += float(loss) * bs
            n_samples += bs
    out: dict[str, float] = {}
    if metric_fn is not None:
        dd.reduce_meter_(metric_fn)
        out.update(metric_fn.compute())
    if loss_fn is not None:
        local = total_loss / n_samples if n_samples else math.nan
        out["loss"] = dd.all_reduce_mean({"loss": local}, weight=n_samples)["loss"]
    return out


# ----------------------------------------------------------------------------- history files
def _atomic_text(path: Path, text: str) -> None:
    atomic_write(path, text)


def write_history(history: list[Mapping[str, Any]], run_dir: str | Path) -> tuple[Path, Path]:
    """Write ``metrics.csv`` and ``metrics.json`` (one row per epoch; NaN → empty / null)."""
    run_dir = Path(run_dir)
    columns: list[str] = []
    for row in history:
        columns.extend(k for k in row if k not in columns)

    def clean(v: Any) -> Any:
        return None if isinstance(v, float) and not math.isfinite(v) else v

    rows = [{k: clean(row.get(k)) for k in columns} for row in history]
    import io

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns)
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
    csv_path, json_path = run_dir / "metrics.csv", run_dir / "metrics.json"
    _atomic_text(csv_path, buf.getvalue())
    _atomic_text(json_path, json.dumps(rows, indent=1))
    return csv_path, json_path


def _config_dict(cfg: Any) -> dict[str, Any]:
    if hasattr(cfg, "as_dict"):
        return cfg.as_dict()
    return to_plain(to_dict(cfg))


def _better(value: Any, best: float | None, mode: str) -> bool:
    if not isinstance(value, int | float) or not math.isfinite(value):
        return False
    if best is None:
        return True
    return value < best if mode == "min" else value > best


# ----------------------------------------------------------------------------- main
def fit(
    cfg: TrainConfig,
    model: nn.Module,
    train_loader: Any,
    val_loader: Any,
    loss_fn: LossFn,
    metric_fn: Any,
    *,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler: Any = None,
    model_name: str | None = None,
    model_config: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Train ``model`` for ``cfg.epochs`` epochs, validating, logging and checkpointing.

    Args:
        cfg: the run's :class:`TrainConfig` (a subclass is fine).
        model: the freshly built model (moved to the device and DDP-wrapped here when running
            under torchrun).
        train_loader: training batches; use :func:`training.distributed.make_loader` for a
            seeded, resumable, shard-aware loader.
        val_loader: validation batches, or None.
        loss_fn: ``loss_fn(outputs, batch)`` (module docstring); also the validation loss.
        metric_fn: a :class:`training.metrics.Meter` for validation, or None.
        optimizer: default :func:`build_optimizer` (``cfg.optim``).
        scheduler: default :func:`build_scheduler` (``cfg.schedule``), stepped per batch.
        model_name, model_config: stored in the checkpoints (default ``cfg.model`` /
            ``cfg.model_config``); a resumed checkpoint must hold the same name.
        extra: plain data stored in every checkpoint (e.g. class weights).

    Returns:
        The run directory ``cfg.out_dir``.

    Raises:
        GeosegError: ``out_dir/last.pt`` exists but neither ``resume`` nor ``overwrite`` is set;
            the checkpoint does not fit; a non-finite loss; an unwritable output directory.
    """
    run_dir = Path(cfg.out_dir)
    main = dd.is_main_process()
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    device = dd.resolve_device(cfg.device, local_rank)
    model_name = model_name if model_name is not None else cfg.model
    model_config = dict(model_config if model_config is not None else cfg.model_config)
    last = run_dir / LAST
    saved, resuming = _open_run(cfg, run_dir, main)

    own_optimizer = optimizer is None and scheduler is None
    net, optimizer, scheduler, scaler = _setup_training(
        cfg,
        model,
        train_loader,
        device,
        resuming=resuming,
        optimizer=optimizer,
        scheduler=scheduler,
    )

    cfg_dict = _config_dict(cfg)
    start_epoch, global_step, history, best, best_epoch = 0, 0, [], None, None
    gens = loader_generators(train_loader)
    if resuming:
        start_epoch, global_step, history, best, best_epoch = _resume(
            cfg,
            saved if saved is not None else last,
            model,
            optimizer,
            scheduler,
            scaler,
            model_name=model_name,
            device=device,
            cfg_dict=cfg_dict,
            gens=gens,
            own_optimizer=own_optimizer,
        )
    if main:
        record_run_files(run_dir)
        _atomic_text(run_dir / "config.yaml", yaml.safe_dump(cfg_dict, sort_keys=False))
        if history:  # a run stopped after last.pt but before its history files: redo them
            write_history(history, run_dir)
            if cfg.plots:
                plot_history(history, run_dir)
    if start_epoch >= cfg.epochs:
        logger.info("%s: all %d epochs done already", run_dir, cfg.epochs)
        return run_dir

    for epoch in range(start_epoch, cfg.epochs):
        row = _train_and_validate(
            cfg,
            epoch,
            net,
            train_loader,
            val_loader,
            loss_fn,
            metric_fn,
            optimizer,
            scheduler,
            scaler,
            device=device,
            global_step=global_step,
        )
        global_step = row["global_step"]
        history.append(row)
        is_best = _better(row.get(cfg.best_metric), best, cfg.best_mode)
        if is_best:
            best, best_epoch = float(row[cfg.best_metric]), epoch + 1
        (logger.info if main else logger.debug)(
            "epoch %d/%d: %s",
            epoch + 1,
            cfg.epochs,
            ", ".join(f"{k}={v:.4g}" for k, v in row.items() if isinstance(v, float)),
        )
        if main:
            checkpoint = build_checkpoint(
                model, optimizer=optimizer, scheduler=scheduler, scaler=scaler, epoch=epoch + 1,
                global_step=global_step, model_name=model_name, model_config=model_config,
                config=cfg_dict, history=history, best=best, best_epoch=best_epoch,
                generators=capture_generators(gens), extra=extra,
            )  # fmt: skip
            _save_epoch(cfg, run_dir, checkpoint, history, is_best=is_best)
        dd.barrier()
    return run_dir


def _save_epoch(
    cfg: TrainConfig, run_dir: Path, checkpoint: dict[str, Any], history: list, *, is_best: bool
) -> None:
    """An epoch's end on the main process: ``last.pt`` (and ``best.pt``), the history files
    and, with ``cfg.plots``, their plots."""
    save_run_checkpoints(checkpoint, run_dir, is_best=is_best)
    write_history(history, run_dir)
    if cfg.plots:
        plot_history(history, run_dir)


def _setup_training(
    cfg: TrainConfig,
    model: nn.Module,
    train_loader: Any,
    device: torch.device,
    *,
    resuming: bool,
    optimizer: torch.optim.Optimizer | None,
    scheduler: Any,
) -> tuple[nn.Module, torch.optim.Optimizer, Any, Any]:
    """Seeds (a fresh run) or determinism (a resumed one), threads, the model on its device
    (DDP-wrapped under torchrun), the optimizer, the scheduler and the AMP scaler:
    ``(net, optimizer, scheduler, scaler)``."""
    if resuming:
        set_deterministic(cfg.deterministic)
    else:
        seed_everything(cfg.seed, deterministic=cfg.deterministic)
    if device.type == "cpu":
        torch.set_num_threads(dd.cpu_threads_per_process(cfg.cpu_threads, cfg.data.num_workers))
    model.to(device)
    net = dd.wrap_model(model, device, find_unused_parameters=cfg.find_unused_parameters)
    optimizer = optimizer or build_optimizer(model, cfg.optim)
    steps_per_epoch = len(train_loader)
    scheduler = scheduler or build_scheduler(
        optimizer, cfg.schedule, steps_per_epoch=steps_per_epoch, epochs=cfg.epochs
    )
    scaler = torch.amp.GradScaler("cuda") if cfg.amp and device.type == "cuda" else None
    if cfg.amp and scaler is None:
        logger.info("amp requested but the device is %s; training in float32", device)
    return net, optimizer, scheduler, scaler


def _open_run(cfg: TrainConfig, run_dir: Path, main: bool) -> tuple[dict[str, Any] | None, bool]:
    """``(the checkpoint to resume from or None, whether the run resumes)``: the main process
    opens the run directory (:func:`training.resume.start_run`); every process stops when it
    refuses it."""
    last = run_dir / LAST
    saved: dict[str, Any] | None = None
    failure: GeosegError | None = None
    if main:
        try:
            saved = start_run(run_dir, resume=cfg.resume, overwrite=cfg.overwrite)
        except GeosegError as err:
            failure = err
    # every process stops when the main one refuses the run directory (no rank left waiting)
    if float(dd.all_reduce_sum_(torch.tensor([float(failure is not None)]))[0]) > 0:
        raise failure or GeosegError(f"{run_dir}: the main process refused the run directory")
    resuming = saved is not None if main else bool(cfg.resume) and last.is_file()
    return saved, resuming


def _resume(
    cfg: TrainConfig,
    source: Any,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    scaler: Any,
    *,
    model_name: str | None,
    device: torch.device,
    cfg_dict: dict[str, Any],
    gens: Any,
    own_optimizer: bool,
) -> tuple[int, int, list, Any, Any]:
    """Restore the run's state from ``source`` (``last.pt`` or its loaded content):
    ``(start epoch, global step, history, best, best epoch)``."""
    last = Path(cfg.out_dir) / LAST
    ckpt = restore_checkpoint(
        source,
        model,
        optimizer=optimizer,
        scheduler=scheduler,
        scaler=scaler,
        model_name=model_name,
        map_location=device,
        path=last,
    )
    old_cfg = ckpt.get("config") or {}
    check_resume_config(old_cfg, cfg_dict, last)
    if own_optimizer:
        apply_optim_config(optimizer, scheduler, cfg.optim, old_cfg.get("optim") or {})
    start_epoch, global_step = int(ckpt["epoch"]), int(ckpt["global_step"])
    history, best = list(ckpt.get("history") or []), ckpt.get("best")
    best_epoch = ckpt.get("best_epoch")
    saved_gens = list(ckpt.get("generators") or [])
    if len(saved_gens) == len(gens):
        restore_generators(gens, saved_gens)
    else:
        logger.warning(
            "%s holds %d loader generator states, the loader has %d: shuffling will differ",
            last,
            len(saved_gens),
            len(gens),
        )
    _log_config_changes(old_cfg, cfg_dict, last)
    logger.info("resumed %s at epoch %d (step %d)", last, start_epoch, global_step)
    return start_epoch, global_step, history, best, best_epoch


def _train_and_validate(
    cfg: TrainConfig,
    epoch: int,
    net: nn.Module,
    train_loader: Any,
    val_loader: Any,
    loss_fn: LossFn,
    metric_fn: Any,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    scaler: Any,
    *,
    device: torch.device,
    global_step: int,
) -> dict[str, Any]:
    """One epoch of training (and validation when due): the history row, its ``global_step``
    advanced by the epoch's steps."""
    t0 = time.perf_counter()
    dd.set_epoch(train_loader, epoch)
    train = train_one_epoch(
        net,
        train_loader,
        loss_fn,
        optimizer,
        device=device,
        scaler=scaler,
        scheduler=scheduler,
        progress=cfg.progress,
        grad_clip=cfg.optim.grad_clip,
        epoch=epoch + 1,
    )
    global_step += int(train.pop("steps"))
    n_local = train.pop("n_samples")
    lr = train.pop("lr")
    train = dd.all_reduce_mean(train, weight=n_local)
    row: dict[str, Any] = {"epoch": epoch + 1, "global_step": global_step, "lr": lr}
    row.update({f"train_{k}": v for k, v in train.items()})
    last_epoch = epoch + 1 == cfg.epochs
    if val_loader is not None and ((epoch + 1) % cfg.val_every == 0 or last_epoch):
        val = evaluate(net, val_loader, metric_fn, device=device, loss_fn=loss_fn)
        row.update({f"val_{k}": v for k, v in val.items()})
    row["time_s"] = time.perf_counter() - t0
    return row


def _log_config_changes(old: Mapping[str, Any], new: Mapping[str, Any], path: Path) -> None:
    changed = sorted(
        k for k in set(old) | set(new) if k not in _VOLATILE_KEYS and old.get(k) != new.get(k)
    )
    if changed:
        logger.warning("resuming %s with a changed config: %s", path, ", ".join(changed))
    schedule = (new.get("schedule") or {}).get("name")
    if old.get("epochs") != new.get("epochs") and schedule in ("poly", "cosine"):
        logger.warning(
            "resuming %s with epochs %s -> %s: the %s schedule is stretched from here on",
            path,
            old.get("epochs"),
            new.get("epochs"),
            schedule,
        )
