"""Train the surface-normals head of the joint network (thesis §4.3.2, fig. 4.18, eq. 4.10).

Transfer learning as in the thesis (no dataset holds both labels and normals): the joint
network's trunk (layers 1-21) and label head are copied from a trained ENet
(:meth:`~geoseg.models.joint.JointNet.load_enet_weights`) and frozen (``requires_grad=False``,
batch-norm statistics and dropout fixed); only the normals head trains, with the MSE to the
ground-truth normals on valid (non-sky) pixels (:class:`~training.losses.NormalsLoss`, optional
angular term). Validation reports the angular error (mean, median, share within 11.25, 22.5 and
30 degrees) over all valid pixels (``val_angle_*``) and over building pixels
(``val_building_angle_*``), plus the (unchanged) label mIoU.

The training data must carry normals: the synthetic source.

Usage::

    geoseg train normals --config configs/normals.yaml --set enet_checkpoint=runs/seg
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from torch import nn

from geoseg.errors import ConfigError, GeosegError
from geoseg.models.registry import get_model
from training import common, frame_data
from training.config import TrainConfig
from training.loop import fit
from training.losses import NormalsLoss
from training.metrics import (
    MeterCollection,
    NormalsMeter,
    SegmentationMeter,
    building_normals_meter,
)

logger = logging.getLogger(__name__)


@dataclass
class NormalsConfig(TrainConfig):
    """Normals-head training run (fields beyond :class:`~training.config.TrainConfig`).

    Attributes:
        enet_checkpoint: the trained ENet: a ``model.pt``, a training checkpoint or a seg run
            directory (required).
        angular_weight: weight of the extra mean-angle loss term (0: the thesis's MSE only).
        normals_init: a trained joint network (run directory, ``model.pt`` or shipped name,
            e.g. ``normals_real``) whose normals head starts this one (None: a fresh head). A
            head trained on a related trunk converges in a fraction of the steps when the trunk
            is fine-tuned (``configs/street.yaml``: ``normals_real``'s head on the trunk
            fine-tuned on real labels).
        export: export ``model.onnx`` at the end.
        train_crop: ``(h, w)`` random training crops of the ``data.size`` frames (None: whole
            frames); validation always uses whole frames.
    """

    model: str = "joint"
    out_dir: Path = Path("runs/normals")
    best_metric: str = "val_building_angle_median"
    best_mode: Literal["min", "max"] = "min"
    enet_checkpoint: Path | None = None
    angular_weight: float = 0.0
    normals_init: Path | None = None
    export: bool = True
    train_crop: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        common.check_trainer_config(self, trainer="normals", model="joint")
        if self.angular_weight < 0:
            raise ConfigError(f"angular_weight: expected >= 0, got {self.angular_weight}")
        if self.enet_checkpoint is not None:
            self.enet_checkpoint = Path(self.enet_checkpoint)
        if self.normals_init is not None:
            self.normals_init = Path(self.normals_init)


CONFIG_CLASS = NormalsConfig


def normals_meter(num_classes: int) -> MeterCollection:
    """Angular errors on all valid pixels and on building pixels, plus the label confusion."""
    return MeterCollection(NormalsMeter(), building_normals_meter(), SegmentationMeter(num_classes))


def load_normal_head(model: nn.Module, path: str | Path) -> Path:
    """Copy the normals head of the joint network at ``path`` (run directory, ``model.pt`` or a
    shipped name) into ``model``'s; returns the file read.

    Raises:
        GeosegError: not a joint network, or a head of other shapes.
    """
    from geoseg.pretrained import path_or_shipped

    source = path_or_shipped(path)
    state, _ = common.load_state(source, expected_model="joint", option="normals_init")
    head = {k[len("normal_head.") :]: v for k, v in state.items() if k.startswith("normal_head.")}
    try:
        model.normal_head.load_state_dict(head, strict=True)
    except RuntimeError as err:
        raise GeosegError(f"normals_init {path}: does not match the normals head: {err}") from None
    logger.info("normals head initialised from %s", source)
    return source


def main(cfg: NormalsConfig, *, command: str | None = None) -> Path:
    """Train the normals head as ``cfg`` says; returns the run directory.

    Raises:
        GeosegError: no ``enet_checkpoint``, a checkpoint of another architecture, data without
            normals, an existing run without ``resume``/``overwrite``.
    """
    if cfg.enet_checkpoint is None:
        raise GeosegError(
            "enet_checkpoint: the normals trainer starts from a trained ENet; set it to a seg "
            "run directory or model file (e.g. --set enet_checkpoint=runs/seg)"
        )
    if cfg.data.source != "synth":
        raise GeosegError(
            f"data.source: normals training needs ground-truth normals (synth), got "
            f"{cfg.data.source!r}"
        )
    state, _ = common.load_state(
        cfg.enet_checkpoint, expected_model="enet", option="enet_checkpoint"
    )
    common.seed_model_init(cfg.seed)
    model = get_model("joint", **cfg.model_config)
    model.load_enet_weights(state)
    if cfg.normals_init is not None:
        load_normal_head(model, cfg.normals_init)
    model.freeze_trunk_and_labels(True)
    logger.info(
        "joint network from %s: %d trainable of %d parameters (normals head)",
        cfg.enet_checkpoint,
        sum(p.numel() for p in model.parameters() if p.requires_grad),
        sum(p.numel() for p in model.parameters()),
    )
    train_set = frame_data.build_frame_dataset(cfg.data, "train", crop=cfg.train_crop)
    val_set = frame_data.build_frame_dataset(cfg.data, "val")
    common.prerender_frames(cfg.data, train_set, val_set)
    train_loader, val_loader = common.make_loaders(cfg, train_set, val_set)
    loss_fn = NormalsLoss(angular_weight=cfg.angular_weight)
    run_dir = fit(
        cfg,
        model,
        train_loader,
        val_loader,
        loss_fn,
        normals_meter(model.num_classes),
        model_name="joint",
        model_config=cfg.model_config,
        extra={"enet_checkpoint": str(cfg.enet_checkpoint)},
    )
    return common.finish_run(
        run_dir,
        model,
        cfg,
        kind="normals",
        model_name="joint",
        command=command,
        extra_card={"enet_checkpoint": str(cfg.enet_checkpoint), "frozen": "trunk, label_head"},
    )
