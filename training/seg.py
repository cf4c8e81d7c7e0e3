"""Train ENet for the 8-class segmentation (thesis §4.3.1; Paszke et al. 2016).

Softmax cross-entropy with ENet's class weights ``1 / ln(1.02 + p_class)`` computed on a sample
of the training frames, Adam with learning rate 5e-4 and weight decay 2e-4 (the paper's values,
the defaults of :class:`~training.config.OptimConfig`).

Optional encoder-first schedule (``encoder_epochs > 0``), as in the ENet paper: first the encoder
(the shared trunk, layers 1-21) is trained alone with a 1x1 convolution classifying the
layer-21 map against labels downsampled by 8 (nearest neighbour), in ``<out_dir>/encoder``; then
the whole network starts from that trunk (the decoder from scratch) and trains for ``epochs``
epochs in ``<out_dir>``. ENet's own encoder also holds bottlenecks 3.7-3.8, which here belong to
the head (the joint network branches after layer 21) and therefore start untrained in stage 2.

``init_checkpoint`` starts the whole network from earlier ENet weights (fine-tuning, e.g. the
shipped ``geoseg/weights/seg`` on real labelled images, ``configs/seg_camvid.yaml``).

Usage::

    geoseg train seg --config configs/seg.yaml
    # or
    from geoseg.config import load_config
    from training.seg import SegConfig, main
    main(load_config(SegConfig, "configs/seg.yaml"))
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from torch import nn

from geoseg.classes import NUM_CLASSES
from geoseg.config import check_range
from geoseg.errors import ConfigError
from geoseg.models.enet import pad_to_multiple
from geoseg.models.registry import get_model
from training import common, frame_data
from training.checkpoint import LAST, load_checkpoint
from training.config import TrainConfig
from training.loop import fit
from training.losses import WeightedCrossEntropy, class_weights_from_dataset
from training.metrics import SegmentationMeter

logger = logging.getLogger(__name__)

ENCODER_DIR = "encoder"


@dataclass
class SegConfig(TrainConfig):
    """ENet training run (fields beyond :class:`~training.config.TrainConfig`).

    Attributes:
        encoder_epochs: epochs of the encoder-first stage (0 = train the whole network only).
        class_weight_samples: training frames whose labels give the class frequencies.
        class_weight_c: ENet's constant in ``1 / ln(c + p)``.
        export: export ``model.onnx`` at the end.
        train_crop: ``(h, w)`` random training crops of the ``data.size`` frames (None: whole
            frames); validation always uses whole frames.
        freeze: ENet submodules kept as ``init_checkpoint`` has them, batch-norm statistics
            included (:meth:`~geoseg.models.enet.ENet.freeze`): ``[trunk]`` trains the head
            alone and keeps the trunk's layer-21 features, and so every normals or
            relocalisation head trained on them, as they were; ``[trunk.initial, trunk.down1,
            trunk.stage1]`` keeps the first layers' low-level filters. Needs ``init_checkpoint``.
    """

    model: str = "enet"
    out_dir: Path = Path("runs/seg")
    best_metric: str = "val_miou"
    best_mode: Literal["min", "max"] = "max"
    encoder_epochs: int = 0
    class_weight_samples: int = 48
    class_weight_c: float = 1.02
    export: bool = True
    train_crop: tuple[int, int] | None = None
    freeze: list[str] = dataclasses.field(default_factory=list)

    def __post_init__(self) -> None:
        super().__post_init__()
        common.check_trainer_config(self, trainer="seg", model="enet")
        if self.freeze and (self.init_checkpoint is None or self.encoder_epochs > 0):
            raise ConfigError(
                "freeze: needs init_checkpoint (trained weights to keep) and "
                "encoder_epochs 0 (the encoder-first stage trains the trunk)"
            )
        if self.freeze:  # names checked now, not after the frames are rendered
            get_model("enet", **self.model_config).freeze(self.freeze)
        if self.encoder_epochs < 0:
            raise ConfigError(f"encoder_epochs: expected >= 0, got {self.encoder_epochs}")
        if self.class_weight_samples < 1:
            raise ConfigError(
                f"class_weight_samples: expected >= 1, got {self.class_weight_samples}"
            )
        # ENet's weights 1 / ln(c + p) are positive and finite for every p in [0, 1] iff c > 1
        check_range("class_weight_c", self.class_weight_c, 1.0, None, low_open=True)


CONFIG_CLASS = SegConfig


class EncoderClassifier(nn.Module):
    """ENet's trunk (layers 1-21) + a 1x1 convolution: the encoder-first stage's network.

    Forward:
        x: `(B, 3, H, W)` normalised image.
        Returns ``{"logits": (B, C, ceil(H/8), ceil(W/8))}``.
    """

    def __init__(self, trunk: nn.Module, num_classes: int = NUM_CLASSES) -> None:
        super().__init__()
        self.trunk = trunk
        self.classifier = nn.Conv2d(128, num_classes, 1)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        features, _, _ = self.trunk(pad_to_multiple(x))
        return {"logits": self.classifier(features)}


def _stage_cfg(cfg: SegConfig, **changes: Any) -> SegConfig:
    return dataclasses.replace(cfg, **changes)


def main(cfg: SegConfig, *, command: str | None = None) -> Path:
    """Train ENet as ``cfg`` says; returns the run directory (see :mod:`training.common`).

    Raises:
        GeosegError: bad data, an existing run without ``resume``/``overwrite``, a checkpoint
            (``init_checkpoint``, ``resume``) from another architecture.
    """
    train_set = frame_data.build_frame_dataset(cfg.data, "train", crop=cfg.train_crop)
    val_set = frame_data.build_frame_dataset(cfg.data, "val")
    common.prerender_frames(cfg.data, train_set, val_set)
    weights, counts = class_weights_from_dataset(
        train_set,
        max_samples=cfg.class_weight_samples,
        seed=cfg.seed,
        num_classes=int(cfg.model_config.get("num_classes", NUM_CLASSES)),
        c=cfg.class_weight_c,
    )
    loss_fn = WeightedCrossEntropy(weights)
    train_loader, val_loader = common.make_loaders(cfg, train_set, val_set)
    extra = {"class_weights": weights.tolist(), "class_counts": counts.tolist()}

    common.seed_model_init(cfg.seed)
    model = get_model("enet", **cfg.model_config)
    if cfg.init_checkpoint is not None:
        common.load_init_weights(model, cfg.init_checkpoint, model_name="enet")
    model.freeze(cfg.freeze)
    if cfg.encoder_epochs > 0:
        enc_dir = Path(cfg.out_dir) / ENCODER_DIR
        enc_cfg = _stage_cfg(
            cfg,
            epochs=cfg.encoder_epochs,
            out_dir=enc_dir,
            best_metric="val_loss",
            best_mode="min",
            encoder_epochs=0,
        )
        encoder = EncoderClassifier(model.trunk, model.num_classes)
        logger.info("encoder-first stage: %d epochs in %s", cfg.encoder_epochs, enc_dir)
        fit(
            enc_cfg,
            encoder,
            train_loader,
            val_loader,
            loss_fn,
            None,
            model_name="enet_encoder",
            model_config=cfg.model_config,
            extra=extra,
        )
        # stage 2 starts from the encoder's last weights (the end of its schedule)
        state = load_checkpoint(enc_dir / LAST)["model"]
        model.trunk.load_state_dict(
            {k[len("trunk.") :]: v for k, v in state.items() if k.startswith("trunk.")}
        )
    run_dir = fit(
        cfg,
        model,
        train_loader,
        val_loader,
        loss_fn,
        # mean IoU over the classes the dataset labels (CamVid has no terrain, for one)
        SegmentationMeter(model.num_classes, classes=frame_data.dataset_classes(val_set)),
        model_name="enet",
        model_config=cfg.model_config,
        extra=extra,
    )
    return common.finish_run(
        run_dir, model, cfg, kind="seg", model_name="enet", command=command, extra_card=extra
    )
