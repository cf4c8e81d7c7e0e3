"""How a training run starts or resumes in its run directory, without losing or mixing anything.

:func:`start_run` is called by :func:`training.loop.fit` (main process) before any training:

* the run directory is prepared with :func:`geoseg.output_dir.prepare_output_dir` (producer
  ``train``): a folder holding files that no geoseg training wrote is refused unless
  ``overwrite``; leftover temporary files of interrupted writes are removed;
* ``resume`` with a ``last.pt``: the checkpoint pair is reconciled
  (:func:`training.checkpoint.reconcile_run_checkpoints`) and returned;
* ``resume`` without a ``last.pt`` in a folder that holds an earlier run's results
  (``best.pt``, ``metrics.csv``, ``model.pt``...) is refused: starting over would overwrite them;
* a fresh start over an earlier run (``overwrite``) first removes that run's checkpoints and
  results, so that an old ``best.pt`` cannot outlive the run it belonged to.

:func:`check_resume_config` compares the resumed checkpoint's config with the new one: keys a
resumed run cannot honour (the seed, the model, the optimizer type, the data, the batch size,
the best-epoch rule) must not change; the optimizer's hyperparameters may, and
:func:`apply_optim_config` makes the resumed optimizer use them, so that ``config.yaml`` and the
model card record what the run actually did.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch

from geoseg.errors import GeosegError
from geoseg.output_dir import prepare_output_dir, record_outputs, remove_outputs
from training.checkpoint import BEST, LAST, reconcile_run_checkpoints

logger = logging.getLogger(__name__)

PRODUCER = "train"
# What fit and the end of a run write (training.loop, training.common, training.plots).
CHECKPOINT_FILES = (LAST, BEST)
HISTORY_FILES = ("metrics.csv", "metrics.json", "loss.png", "metrics.png")
RESULT_FILES = ("model.pt", "model.onnx", "model_card.json", "model_card.md")
RUN_FILES = ("config.yaml", *CHECKPOINT_FILES, *HISTORY_FILES, *RESULT_FILES)

# Config keys a resumed run cannot honour: the saved state was produced under the old values.
FIXED_ON_RESUME = (
    "seed",
    "model",
    "model_config",
    "batch_size",
    "best_metric",
    "best_mode",
    "optim.name",
    "data.source",
    "data.root",
    "data.size",
    "data.train_split",
    "data.val_split",
    "data.synth",
    "data.augment",
    # trainer sections: the weights a run starts from, the routes the heads train on
    "enet_checkpoint",
    "trunk_checkpoint",
    "naive_checkpoint",
    "routes",
)


def _legacy_run(folder: Path) -> list[str] | None:
    """The run files of a run directory written before output markers existed (None: not one)."""
    names = {p.name for p in folder.iterdir()}
    if "config.yaml" in names and names & {LAST, BEST}:
        return sorted(names & set(RUN_FILES))
    return None


def start_run(
    run_dir: str | Path, *, resume: bool, overwrite: bool, option: str = "out_dir"
) -> dict[str, Any] | None:
    """Prepare ``run_dir`` for training; return the checkpoint to resume from (None: fresh).

    Args:
        run_dir: the run directory (created).
        resume: continue from ``run_dir/last.pt``.
        overwrite: start afresh over an earlier run, or write into a folder holding other files.
        option: the option naming the folder, for messages.

    Raises:
        GeosegError: the folder holds files no training wrote (without ``overwrite``); an
            earlier run exists and neither ``resume`` nor ``overwrite`` is set; ``resume`` has
            no ``last.pt`` to continue while earlier results exist; inconsistent checkpoints.
        OutputError: the folder cannot be created or written.
    """
    run_dir = Path(run_dir)
    adopted = _legacy_run(run_dir) if run_dir.is_dir() else None
    prepare_output_dir(
        run_dir,
        producer=PRODUCER,
        overwrite=overwrite,
        option=option,
        adopt=lambda folder: adopted is not None,
    )
    if adopted:
        record_outputs(run_dir, adopted)
    last = run_dir / LAST
    earlier = [
        name
        for name in (*CHECKPOINT_FILES, *RESULT_FILES, "metrics.csv")
        if (run_dir / name).is_file()
    ]
    if resume:
        if last.is_file():
            return reconcile_run_checkpoints(run_dir)
        if earlier and not overwrite:
            raise GeosegError(
                f"resume: {last} does not exist but {run_dir} holds an earlier run's "
                f"{', '.join(earlier)}; starting over would overwrite them: pass --overwrite "
                "(overwrite=true) to start afresh, or choose another output folder"
            )
        logger.warning("resume requested but %s does not exist: starting a new run", last)
    elif earlier and not overwrite:
        raise GeosegError(
            f"{run_dir} holds an earlier run ({', '.join(earlier)}): pass --resume "
            "(resume=true) to continue it, or --overwrite (overwrite=true) to start afresh, "
            "or choose another output folder"
        )
    if earlier:
        removed = remove_outputs(run_dir, (*CHECKPOINT_FILES, *HISTORY_FILES, *RESULT_FILES))
        if removed:
            logger.info(
                "starting afresh: removed the earlier run's %s", ", ".join(p.name for p in removed)
            )
    return None


def record_run_files(run_dir: str | Path, names: Iterable[str] = RUN_FILES) -> None:
    """Record a run's files in its output marker (:func:`geoseg.output_dir.record_outputs`)."""
    record_outputs(run_dir, list(names))


def _dotted(data: Mapping[str, Any], key: str) -> Any:
    node: Any = data
    for part in key.split("."):
        if not isinstance(node, Mapping):
            return None
        node = node.get(part)
    return node


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def check_resume_config(old: Mapping[str, Any], new: Mapping[str, Any], path: str | Path) -> None:
    """Refuse resuming ``path`` under a config that changes a key the run cannot honour.

    Args:
        old: the config stored in the checkpoint (plain dict).
        new: the config of this invocation (plain dict).
        path: the checkpoint, for messages.

    Raises:
        GeosegError: naming each changed key of :data:`FIXED_ON_RESUME` with both values.
    """
    if not old:
        return
    changed = [
        f"{key} {_dotted(old, key)!r} -> {_dotted(new, key)!r}"
        for key in FIXED_ON_RESUME
        if _dotted(old, key) is not None and not _same(_dotted(old, key), _dotted(new, key))
    ]
    if changed:
        raise GeosegError(
            f"resume: {path} was trained with other values of {'; '.join(changed)}; a resumed "
            "run cannot change them: drop those overrides, or start a new run (another output "
            "folder, or overwrite)"
        )


def apply_optim_config(
    optimizer: torch.optim.Optimizer, scheduler: Any, optim: Any, old: Mapping[str, Any]
) -> None:
    """Make a restored optimizer (and its LR scheduler) use the config's hyperparameters.

    ``optimizer.load_state_dict`` brings back the saved learning rate, weight decay, betas and
    momentum; a resumed run asked for other values must train with them. The scheduler's base
    learning rates are set to ``optim.lr`` and the current rate recomputed from its factor.

    Args:
        optimizer: the restored optimizer (built by :func:`training.loop.build_optimizer`).
        scheduler: the restored :class:`~torch.optim.lr_scheduler.LambdaLR`, or None.
        optim: the run's :class:`~training.config.OptimConfig`.
        old: the saved config's ``optim`` section (for the log message).
    """
    wanted: dict[str, Any] = {"weight_decay": float(optim.weight_decay)}
    if optim.name in ("adam", "adamw"):
        wanted["betas"] = tuple(float(b) for b in optim.betas)
    else:
        wanted["momentum"] = float(optim.momentum)
    for group in optimizer.param_groups:
        group.update({k: v for k, v in wanted.items() if k in group})
    lr = float(optim.lr)
    if (
        scheduler is not None
        and hasattr(scheduler, "base_lrs")
        and hasattr(scheduler, "lr_lambdas")
    ):
        scheduler.base_lrs = [lr for _ in optimizer.param_groups]
        step = int(getattr(scheduler, "last_epoch", 0))
        for group, fn in zip(optimizer.param_groups, scheduler.lr_lambdas):
            group["initial_lr"] = lr
            group["lr"] = lr * fn(step)
        scheduler._last_lr = [g["lr"] for g in optimizer.param_groups]
    else:
        for group in optimizer.param_groups:
            group["lr"] = lr
    changes = [
        f"{k} {old.get(k)!r} -> {v!r}"
        for k, v in {"lr": lr, "weight_decay": wanted["weight_decay"]}.items()
        if old.get(k) is not None and not _same(old.get(k), v)
    ]
    if changes:
        logger.warning(
            "resuming with changed optimizer settings, applied from here on: %s", ", ".join(changes)
        )
