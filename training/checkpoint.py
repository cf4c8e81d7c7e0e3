"""Checkpoints: atomic writes, safe loads, and clear errors for files that do not fit.

A checkpoint is the mapping :mod:`geoseg.checkpoint_format` describes (that module holds the
format, so that :mod:`geoseg.infer` reads these files without importing the trainers).

Writes go to a temporary file in the destination's directory, are flushed and fsync-ed, then
``os.replace``-d over the destination: a crash or a full disk never leaves a truncated
checkpoint, and the previous one stays intact. A corrupted file (flipped bytes) fails its
digest check on load instead of training on.

A run keeps :data:`LAST` and :data:`BEST`, written in that order. The pair is consistent after
a kill at any point: a kill between the two writes leaves ``last.pt`` recording a best epoch
that ``best.pt`` does not hold yet, and :func:`reconcile_run_checkpoints` (called when a run
starts or resumes) restores ``best.pt`` from ``last.pt``, which holds exactly those weights.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from geoseg.atomic import atomic_write, clean_temp_files
from geoseg.checkpoint_format import (
    BEST,
    FORMAT,
    FORMAT_VERSION,
    LAST,
    REQUIRED_KEYS,
    validate_checkpoint,
)
from geoseg.errors import GeosegError, OutputError
from geoseg.integrity import read_torch_file, save_torch_file, seal
from training.reproducibility import capture_rng_state, restore_rng_state

logger = logging.getLogger(__name__)


def unwrap_model(model: nn.Module) -> nn.Module:
    """The module inside a DistributedDataParallel / DataParallel wrapper (or ``model``)."""
    while isinstance(model, nn.parallel.DistributedDataParallel | nn.DataParallel):
        model = model.module
    return model


def to_plain(value: Any) -> Any:
    """Convert ``value`` to data ``torch.load(weights_only=True)`` accepts.

    Paths become strings, tuples become lists, NumPy scalars and arrays become Python numbers and
    tensors; dict keys become strings unless they are ints. Other objects raise GeosegError.
    """
    import numpy as np

    if value is None or isinstance(value, bool | int | float | str | torch.Tensor):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return torch.from_numpy(value.copy())
    if isinstance(value, Mapping):
        return {(k if isinstance(k, int) else str(k)): to_plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_plain(v) for v in value]
    raise GeosegError(
        f"checkpoint content: cannot store a {type(value).__name__} ({value!r:.80}); "
        "only tensors, numbers, strings, lists and dicts"
    )


def build_checkpoint(
    model: nn.Module,
    *,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler: Any = None,
    scaler: Any = None,
    epoch: int = 0,
    global_step: int = 0,
    model_name: str | None = None,
    model_config: Mapping[str, Any] | None = None,
    config: Mapping[str, Any] | None = None,
    history: list[Mapping[str, Any]] | None = None,
    best: float | None = None,
    best_epoch: int | None = None,
    generators: list[torch.Tensor] | None = None,
    rng: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Assemble the checkpoint mapping described in the module docstring.

    Args:
        model: the model (a DDP wrapper is unwrapped).
        optimizer, scheduler, scaler: objects with ``state_dict()``, or None.
        epoch: completed epochs.
        global_step: completed optimizer steps.
        model_name, model_config: how to rebuild the architecture.
        config: the run's configuration as a mapping (Paths and tuples are converted).
        history: per-epoch metric rows.
        best: best validation value so far.
        best_epoch: the epoch of ``best`` (what ``best.pt`` must hold).
        generators: data-loader generator states (uint8 tensors).
        rng: global RNG states; captured now when None.
        extra: any other plain data.
    """
    return {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "model_name": model_name,
        "model_config": to_plain(dict(model_config or {})),
        "model": unwrap_model(model).state_dict(),
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "scheduler": None if scheduler is None else to_plain(scheduler.state_dict()),
        "scaler": None if scaler is None else to_plain(scaler.state_dict()),
        "epoch": int(epoch),
        "global_step": int(global_step),
        "rng": dict(rng) if rng is not None else capture_rng_state(),
        "generators": list(generators or []),
        "config": to_plain(dict(config or {})),
        "history": to_plain(list(history or [])),
        "best": None if best is None else float(best),
        "best_epoch": None if best_epoch is None else int(best_epoch),
        "extra": to_plain(dict(extra or {})),
    }


def atomic_save(obj: Any, path: str | Path) -> Path:
    """``torch.save(obj)`` to ``path`` atomically (temp file, flush, fsync, ``os.replace``).

    Raises:
        GeosegError: the directory does not exist or is not writable, or the disk is full; the
            temporary file is removed and any previous file at ``path`` is left untouched.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise GeosegError(f"checkpoint {path}: directory {path.parent} does not exist")
    try:
        return save_torch_file(obj, path)
    except OutputError as err:
        kept = " (the previous checkpoint is kept)" if path.exists() else ""
        raise OutputError(f"checkpoint {err}{kept}", errno=err.errno) from err


def save_checkpoint(checkpoint: Mapping[str, Any], path: str | Path) -> Path:
    """Validate a mapping from :func:`build_checkpoint` and write it atomically to ``path``."""
    missing = [k for k in REQUIRED_KEYS if k not in checkpoint]
    if missing or checkpoint.get("format") != FORMAT:
        raise GeosegError(f"checkpoint {path}: not built by build_checkpoint (missing {missing})")
    out = atomic_save(seal(checkpoint), path)
    logger.debug("wrote checkpoint %s (epoch %s)", out, checkpoint["epoch"])
    return out


def save_run_checkpoints(
    checkpoint: Mapping[str, Any], run_dir: str | Path, *, is_best: bool
) -> Path:
    """Write ``run_dir/last.pt`` and, when ``is_best``, ``run_dir/best.pt``; return last.pt."""
    run_dir = Path(run_dir)
    last = save_checkpoint(checkpoint, run_dir / LAST)
    if is_best:
        save_checkpoint(checkpoint, run_dir / BEST)
    return last


def load_checkpoint(path: str | Path, *, map_location: Any = "cpu") -> dict[str, Any]:
    """Load and validate a checkpoint with ``torch.load(weights_only=True)``.

    Args:
        path: the ``.pt`` file.
        map_location: passed to ``torch.load``.

    Raises:
        GeosegError: the file does not exist, is corrupt or truncated (including a SHA-256
            mismatch), is not a geoseg checkpoint, or CUDA is asked for but unavailable; the
            message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise GeosegError(f"checkpoint {path} does not exist")
    return validate_checkpoint(read_torch_file(path, map_location=map_location), path)


def reconcile_run_checkpoints(run_dir: str | Path) -> dict[str, Any] | None:
    """Make ``last.pt`` and ``best.pt`` of a run consistent after a crash; return ``last.pt``.

    Removes the temporary files of interrupted writes, then checks that ``best.pt`` holds the
    epoch ``last.pt`` records as the best. A kill between the two writes of an epoch that
    improved the best leaves an older ``best.pt``; ``last.pt`` then holds exactly the best
    weights and is copied over it (atomically).

    Returns:
        The loaded ``last.pt`` (None when the run has none).

    Raises:
        GeosegError: ``best.pt`` and ``last.pt`` disagree in a way no crash produces (e.g. files
            copied from two runs): the message says which epochs and what to do.
    """
    run_dir = Path(run_dir)
    clean_temp_files(run_dir, recursive=False)
    last_path, best_path = run_dir / LAST, run_dir / BEST
    if not last_path.is_file():
        return None
    last = load_checkpoint(last_path)
    best_epoch = last.get("best_epoch")
    if best_epoch is None:  # written before best_epoch existed, or no best yet
        return last
    best_at = int(load_checkpoint(best_path)["epoch"]) if best_path.is_file() else None
    if best_at == best_epoch:
        return last
    if best_epoch == int(last["epoch"]):
        logger.warning(
            "%s holds epoch %s but %s records epoch %d as the best (a run stopped between the two "
            "writes): restoring %s from %s",
            best_path,
            best_at,
            last_path,
            best_epoch,
            BEST,
            LAST,
        )
        atomic_write(best_path, last_path.read_bytes())
        return last
    raise GeosegError(
        f"{best_path} holds epoch {best_at} but {last_path} records epoch {best_epoch} as the best: "
        "these files do not belong together; restore the run's own best.pt, or delete it to let "
        "the next better epoch write a new one"
    )


def check_compatible(
    checkpoint: Mapping[str, Any],
    model: nn.Module,
    *,
    model_name: str | None = None,
    path: str | Path = "<checkpoint>",
) -> None:
    """Raise unless ``checkpoint["model"]`` fits ``model`` (same keys and shapes, same name).

    Raises:
        GeosegError: naming the file and the first mismatching keys/shapes or the two names.
    """
    saved_name = checkpoint.get("model_name")
    if model_name is not None and saved_name is not None and saved_name != model_name:
        raise GeosegError(
            f"checkpoint {path} holds model {saved_name!r}, not {model_name!r} (another "
            "architecture)"
        )
    saved = checkpoint["model"]
    if not isinstance(saved, Mapping):
        raise GeosegError(f"checkpoint {path}: 'model' is not a state dict")
    current = unwrap_model(model).state_dict()
    missing = [k for k in current if k not in saved]
    unexpected = [k for k in saved if k not in current]
    shapes = [
        f"{k}: {tuple(saved[k].shape)} vs {tuple(v.shape)}"
        for k, v in current.items()
        if k in saved and hasattr(saved[k], "shape") and tuple(saved[k].shape) != tuple(v.shape)
    ]
    if missing or unexpected or shapes:
        parts = []
        if missing:
            parts.append(f"missing keys {missing[:5]}{' ...' if len(missing) > 5 else ''}")
        if unexpected:
            parts.append(f"unexpected keys {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}")
        if shapes:
            parts.append(f"shape mismatch {shapes[:5]}{' ...' if len(shapes) > 5 else ''}")
        name = f" ({saved_name!r})" if saved_name else ""
        raise GeosegError(
            f"checkpoint {path}{name} does not fit this model (another architecture?): "
            + "; ".join(parts)
        )


def restore_checkpoint(
    source: str | Path | Mapping[str, Any],
    model: nn.Module,
    *,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler: Any = None,
    scaler: Any = None,
    model_name: str | None = None,
    restore_rng: bool = True,
    map_location: Any = "cpu",
    path: str | Path | None = None,
) -> dict[str, Any]:
    """Load a checkpoint into ``model`` (and optimizer/scheduler/scaler/RNG when given).

    Args:
        source: a path, or a mapping already returned by :func:`load_checkpoint`.
        model: the freshly built model (DDP wrappers are unwrapped).
        optimizer, scheduler, scaler: restored when both given and stored.
        model_name: when given, must match the stored ``model_name``.
        restore_rng: restore the global RNG states.
        map_location: for ``torch.load``.
        path: the file a mapping ``source`` was read from (for messages).

    Returns:
        The checkpoint mapping (epoch, global_step, history, generators, config...).

    Raises:
        GeosegError: see :func:`load_checkpoint` and :func:`check_compatible`.
    """
    if isinstance(source, Mapping):
        ckpt, path = dict(source), path or "<checkpoint>"
    else:
        path = Path(source)
        ckpt = load_checkpoint(path, map_location=map_location)
    check_compatible(ckpt, model, model_name=model_name, path=path)
    unwrap_model(model).load_state_dict(ckpt["model"])
    try:
        if optimizer is not None and ckpt.get("optimizer") is not None:
            optimizer.load_state_dict(ckpt["optimizer"])
        if scheduler is not None and ckpt.get("scheduler") is not None:
            scheduler.load_state_dict(ckpt["scheduler"])
        if scaler is not None and ckpt.get("scaler") is not None:
            scaler.load_state_dict(ckpt["scaler"])
    except (ValueError, KeyError, RuntimeError) as err:
        raise GeosegError(
            f"checkpoint {path}: optimizer/scheduler state does not fit ({err})"
        ) from None
    if restore_rng and ckpt.get("rng"):
        restore_rng_state(ckpt["rng"])
    return ckpt
