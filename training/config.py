"""The typed configuration shared by every trainer (defaults here, YAML presets override them).

Load one with :func:`geoseg.config.load_config`::

    cfg = load_config(TrainConfig, "configs/seg.yaml", overrides=["epochs=2", "optim.lr=1e-3"])

Trainer modules may subclass :class:`TrainConfig` (a dataclass) to add their own sections.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from geoseg.config import check_range, to_dict
from geoseg.data.transforms import AugmentConfig
from geoseg.errors import ConfigError, GeosegError


@dataclass
class OptimConfig:
    """Optimizer. Defaults are ENet's paper: Adam, learning rate 5e-4, weight decay 2e-4."""

    name: Literal["adam", "adamw", "sgd"] = "adam"
    lr: float = 5e-4
    weight_decay: float = 2e-4
    betas: tuple[float, float] = (0.9, 0.999)
    momentum: float = 0.9  # SGD only
    grad_clip: float | None = None  # max gradient L2 norm, None = no clipping

    def __post_init__(self) -> None:
        if self.lr <= 0:
            raise ConfigError(f"optim.lr: expected > 0, got {self.lr}")
        if self.weight_decay < 0:
            raise ConfigError(f"optim.weight_decay: expected >= 0, got {self.weight_decay}")
        if self.grad_clip is not None and self.grad_clip <= 0:
            raise ConfigError(f"optim.grad_clip: expected > 0 or null, got {self.grad_clip}")
        check_range("optim.momentum", self.momentum, 0.0, 1.0, high_open=True)
        for i, beta in enumerate(self.betas):
            check_range(f"optim.betas[{i}]", beta, 0.0, 1.0, high_open=True)


@dataclass
class ScheduleConfig:
    """Learning-rate schedule, stepped once per optimizer step.

    ``constant``: no change; ``step``: multiply by ``gamma`` every ``step_epochs`` epochs;
    ``poly``: ``(1 - t/T) ** power``; ``cosine``: cosine decay to ``min_factor``. A linear warm-up
    over ``warmup_steps`` steps precedes any of them.
    """

    name: Literal["constant", "step", "poly", "cosine"] = "constant"
    step_epochs: int = 10
    gamma: float = 0.1
    power: float = 0.9
    min_factor: float = 0.0
    warmup_steps: int = 0

    def __post_init__(self) -> None:
        if self.step_epochs < 1:
            raise ConfigError(f"schedule.step_epochs: expected >= 1, got {self.step_epochs}")
        if self.warmup_steps < 0:
            raise ConfigError(f"schedule.warmup_steps: expected >= 0, got {self.warmup_steps}")
        check_range("schedule.gamma", self.gamma, 0.0, None, low_open=True)
        check_range("schedule.power", self.power, 0.0, None, low_open=True)
        check_range("schedule.min_factor", self.min_factor, 0.0, 1.0)


@dataclass
class DataConfig:
    """Where the frames come from and how they are loaded.

    ``source`` picks the dataset (``synth``: frames rendered on the fly from the synthetic world,
    options in ``synth``; ``cityscapes``: a Cityscapes-format folder at ``root``; ``camvid``: a
    CamVid-layout folder at ``root``, :mod:`geoseg.data.camvid`).

    ``label_map`` (cityscapes / camvid) replaces the reader's table from the dataset's label ids
    to geoseg classes: ``{id: class name | "ignore"}`` (:mod:`geoseg.data.label_map`); the classes
    it reaches are the ones the mean IoU is taken over.
    """

    source: Literal["synth", "cityscapes", "camvid"] = "synth"
    root: Path | None = None
    label_map: dict[int, str] | None = None
    train_split: str = "train"
    val_split: str = "val"
    size: tuple[int, int] = (240, 320)  # (H, W) of the network input
    num_workers: int = 0
    cache_dir: Path | None = None
    # > 0: render the synthetic frames missing from cache_dir up front with this many processes
    # (then num_workers=0 suffices: cached frames load in ~10-25 ms)
    prerender_workers: int = 0
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    # probability that a training image becomes grey (BT.601 luma on all three channels,
    # training.frame_data.RandomGrayscale): trains the network for monochrome cameras
    grayscale: float = 0.0
    synth: dict[str, Any] = field(default_factory=dict)  # options for the synthetic dataset

    def __post_init__(self) -> None:
        if self.num_workers < 0 or self.prerender_workers < 0:
            raise ConfigError(
                "data.num_workers / data.prerender_workers: expected >= 0, got "
                f"{self.num_workers}, {self.prerender_workers}"
            )
        if not 0.0 <= self.grayscale <= 1.0:
            raise ConfigError(f"data.grayscale: expected a probability, got {self.grayscale}")
        if any(s < 1 for s in self.size):
            raise ConfigError(f"data.size: expected positive (H, W), got {self.size}")
        if self.label_map is not None:
            from geoseg.data.label_map import normalise_label_map

            if self.source == "synth":
                raise ConfigError("data.label_map: only for source=cityscapes or camvid")
            try:
                normalise_label_map(self.label_map)
            except GeosegError as err:
                raise ConfigError(f"data.{err}") from None


@dataclass
class TrainConfig:
    """One training run: model, optimisation, data, output, reproducibility."""

    model: str = "enet"
    model_config: dict[str, Any] = field(default_factory=dict)
    epochs: int = 10
    batch_size: int = 4
    val_batch_size: int | None = None  # None = batch_size
    device: str = "auto"  # "auto" (CUDA when present), "cpu", "cuda", "cuda:1"
    # torch intra-op threads on the CPU; None = the cores left per process after data workers.
    cpu_threads: int | None = None
    amp: bool = False  # mixed precision (CUDA only)
    out_dir: Path = Path("runs/run")
    seed: int = 0
    deterministic: bool = True
    # start from these weights (a model.pt, training checkpoint or run directory of the same
    # architecture, or a shipped name such as "seg" for geoseg/weights/seg); None = random
    # initialisation
    init_checkpoint: Path | None = None
    resume: bool = False  # continue from out_dir/last.pt
    overwrite: bool = False  # allow starting afresh over an existing out_dir/last.pt
    val_every: int = 1  # epochs between validations (the last epoch is always validated)
    best_metric: str = "val_loss"  # a key of the epoch row; decides best.pt
    best_mode: Literal["min", "max"] = "min"
    plots: bool = True
    find_unused_parameters: bool = False  # DDP: some trainable parameters get no gradient
    progress: bool = True
    optim: OptimConfig = field(default_factory=OptimConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    data: DataConfig = field(default_factory=DataConfig)

    def __post_init__(self) -> None:
        for key in ("epochs", "batch_size", "val_every"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{key}: expected >= 1, got {getattr(self, key)}")
        if self.val_batch_size is not None and self.val_batch_size < 1:
            raise ConfigError(f"val_batch_size: expected >= 1, got {self.val_batch_size}")
        if self.seed < 0:
            raise ConfigError(f"seed: expected >= 0, got {self.seed}")
        if self.cpu_threads is not None and self.cpu_threads < 1:
            raise ConfigError(f"cpu_threads: expected >= 1, got {self.cpu_threads}")
        if not (self.device in ("auto", "cpu", "cuda") or self.device.startswith("cuda:")):
            raise ConfigError(f"device: expected auto, cpu, cuda or cuda:N, got {self.device!r}")
        self.out_dir = Path(self.out_dir)
        if self.init_checkpoint is not None:
            self.init_checkpoint = Path(self.init_checkpoint)

    def as_dict(self) -> dict[str, Any]:
        """Plain-data form (Paths as strings) for checkpoints and JSON."""
        return _plain(to_dict(self))


def _plain(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value
