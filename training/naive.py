"""Train the 2015 naive patch classifier (thesis §4.2.1, fig. 4.5) and evaluate it densely.

Training samples are 46x46 patches around class-balanced centres drawn from the frames
(:class:`~geoseg.data.synthetic.PatchDataset`: a class uniformly among those present in the
frame, then a pixel of that class), labelled with the centre pixel's class; the loss is the
negative log-likelihood of the network's LogSoftMax output (:class:`~training.losses.PatchNLL`).
Per-epoch validation runs on patches of the validation frames (class-balanced, so its
``val_miou`` is a patch score); at the end the best network is evaluated densely
(:meth:`~geoseg.models.naive_cnn.NaiveCNN.dense`: the patch classifier at every pixel) on
``dense_eval_frames`` validation frames, reported as ``dense_miou``, ``dense_iou_building``...

Usage::

    geoseg train naive --config configs/naive.yaml
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from torch import nn
from torch.utils.data import Subset

from geoseg.errors import ConfigError
from geoseg.models.naive_cnn import NaiveCNN
from geoseg.models.registry import get_model
from training import common, frame_data
from training import distributed as dd
from training.config import TrainConfig
from training.loop import evaluate, fit
from training.losses import PatchNLL
from training.metrics import SegmentationMeter

logger = logging.getLogger(__name__)


@dataclass
class NaiveConfig(TrainConfig):
    """Naive CNN training run (fields beyond :class:`~training.config.TrainConfig`).

    Attributes:
        patches_per_frame: training patches drawn from each training frame.
        val_patches_per_frame: validation patches per validation frame.
        dense_eval_frames: validation frames evaluated densely at the end (0: none).
        band_rows: rows per band in dense evaluation (bounds memory; None: whole images).
        export: export ``model.onnx`` (the dense form) at the end.
        frame_augment: apply the data section's frame augmentations (zoom, colour jitter,
            camera effects: ``data.augment``) to each training frame before its patches are cut,
            for a network meant for real photographs; off, the frames are used as rendered and
            only the patches are flipped. A frame's draw holds for all its patches in an epoch
            (frames are kept decoded per worker process); with ``data.num_workers`` >= 1 each
            epoch draws anew.
    """

    model: str = "naive_cnn"
    out_dir: Path = Path("runs/naive")
    batch_size: int = 128
    best_metric: str = "val_loss"
    best_mode: Literal["min", "max"] = "min"
    patches_per_frame: int = 64
    val_patches_per_frame: int = 32
    dense_eval_frames: int = 8
    band_rows: int | None = 64
    export: bool = True
    frame_augment: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        common.check_trainer_config(self, trainer="naive", model="naive_cnn")
        for key in ("patches_per_frame", "val_patches_per_frame"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{key}: expected >= 1, got {getattr(self, key)}")
        if self.dense_eval_frames < 0:
            raise ConfigError(f"dense_eval_frames: expected >= 0, got {self.dense_eval_frames}")
        if self.band_rows is not None and self.band_rows < 1:
            raise ConfigError(f"band_rows: expected >= 1 or null, got {self.band_rows}")


CONFIG_CLASS = NaiveConfig


class DenseNaive(nn.Module):
    """Whole-image form of a naive CNN for evaluation, in bands of ``band_rows`` rows.

    Forward:
        x: `(B, 3, H, W)` normalised image. Returns ``{"log_probs": (B, C, H, W)}``.
    """

    def __init__(self, net: NaiveCNN, band_rows: int | None = 64) -> None:
        super().__init__()
        self.net = net
        self.band_rows = band_rows

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"log_probs": self.net.dense(x, band_rows=self.band_rows)}


def patch_datasets(cfg: NaiveConfig) -> tuple[Any, Any]:
    """Training and validation :class:`~geoseg.data.synthetic.PatchDataset` of ``cfg``."""
    from geoseg.data.synthetic import PatchDataset

    # frames in [0, 1]; patches are normalised (and flipped) themselves
    train_frames = frame_data.build_frame_dataset(
        cfg.data, "train", augment=cfg.frame_augment, normalize=False
    )
    val_frames = frame_data.build_frame_dataset(cfg.data, "val", augment=False, normalize=False)
    common.prerender_frames(cfg.data, train_frames, val_frames)
    train = PatchDataset(
        train_frames,
        patches_per_frame=cfg.patches_per_frame,
        normalize=frame_data.NORMALIZATION,
        seed=cfg.seed,
        hflip=cfg.data.augment.hflip,
    )
    val = PatchDataset(
        val_frames,
        patches_per_frame=cfg.val_patches_per_frame,
        normalize=frame_data.NORMALIZATION,
        seed=cfg.seed + 1,
    )
    return train, val


def dense_evaluate(model: NaiveCNN, cfg: NaiveConfig) -> dict[str, float]:
    """Dense scores (``dense_miou``, ``dense_iou_<class>``...) on the first
    ``cfg.dense_eval_frames`` validation frames."""
    if cfg.dense_eval_frames == 0:
        return {}
    frames = frame_data.build_frame_dataset(cfg.data, "val", augment=False)
    frames = Subset(frames, range(min(cfg.dense_eval_frames, len(frames))))
    loader = dd.make_loader(
        frames,
        batch_size=cfg.val_batch_size or 2,
        shuffle=False,
        num_workers=cfg.data.num_workers,
    )
    device = dd.resolve_device(cfg.device)
    dense = DenseNaive(model, cfg.band_rows).to(device)
    scores = evaluate(
        dense,
        loader,
        SegmentationMeter(model.num_classes, output_key="log_probs"),
        device=device,
        progress=cfg.progress,
    )
    return {f"dense_{k}": v for k, v in scores.items()}


def main(cfg: NaiveConfig, *, command: str | None = None) -> Path:
    """Train the naive CNN on patches, evaluate it densely; returns the run directory."""
    train_set, val_set = patch_datasets(cfg)
    train_loader, val_loader = common.make_loaders(cfg, train_set, val_set)
    common.seed_model_init(cfg.seed)
    model = get_model("naive_cnn", **cfg.model_config)
    if cfg.init_checkpoint is not None:
        common.load_init_weights(model, cfg.init_checkpoint, model_name="naive_cnn")
    run_dir = fit(
        cfg,
        model,
        train_loader,
        val_loader,
        PatchNLL(),
        SegmentationMeter(model.num_classes, output_key="log_probs"),
        model_name="naive_cnn",
        model_config=cfg.model_config,
    )
    return common.finish_run(
        run_dir,
        model,
        cfg,
        kind="naive",
        model_name="naive_cnn",
        command=command,
        extra_card={"patches_per_frame": cfg.patches_per_frame, "patch_size": model.patch_size},
        # dense scores of the best weights, before finish_run moves the model to the CPU
        extra_metrics=lambda best: dense_evaluate(best, cfg),
    )
