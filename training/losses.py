"""Loss functions of the segmentation-side trainers (``loss_fn(outputs, batch)``, see
:mod:`training.loop`).

* :class:`WeightedCrossEntropy`: softmax cross-entropy with ENet's class weights
  ``w_k = 1 / ln(1.02 + p_k)`` (Paszke et al. 2016), ``p_k`` the share of class k among the
  labelled pixels of (a sample of) the training set (:func:`class_weights_from_dataset`);
  :data:`~geoseg.classes.IGNORE_INDEX` pixels are ignored. Also accepts an ``(B, C, h, w)``
  output smaller than the labels (the encoder-first stage): the labels are then downsampled by
  nearest neighbour.
* :class:`NormalsLoss`: eq. 4.10, the mean over valid pixels of ``||n_pred - n_gt||^2`` (the
  squared L2 distance of the 3-vectors). Predicted normals are unit vectors, so this equals
  ``2 (1 - cos theta)`` and already is an angular loss; the optional extra term
  ``angular_weight * mean(theta)`` (radians) keeps a useful gradient for small errors, where
  ``1 - cos theta ~ theta^2 / 2`` flattens. Off by default (the thesis uses the MSE alone).
* :class:`PatchNLL`: negative log-likelihood of the naive CNN's ``log_probs`` (its LogSoftMax
  output), ``(B, C)`` against ``(B,)`` patch-centre labels.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from geoseg.classes import IGNORE_INDEX, NUM_CLASSES
from geoseg.errors import GeosegError
from geoseg.vectors import vector_length
from training.metrics import class_counts, enet_class_weights

logger = logging.getLogger(__name__)


def class_weights_from_dataset(
    dataset: Any,
    *,
    max_samples: int = 64,
    seed: int = 0,
    num_classes: int = NUM_CLASSES,
    c: float = 1.02,
) -> tuple[torch.Tensor, torch.Tensor]:
    """ENet class weights from the label frequencies of a sample of ``dataset``.

    Args:
        dataset: yields ``{"labels": (H, W) int}`` samples.
        max_samples: how many samples to count (drawn without replacement with ``seed``).
        seed: picks the samples and seeds torch's generator for their random transforms (a
            training set's zoom and flips), so that a run's weights do not depend on what drew
            from the generator before (the global state is restored afterwards).
        num_classes: C.
        c: ENet's constant.

    Returns:
        ``(weights (C,) float32, counts (C,) int64)``.

    Raises:
        GeosegError: empty dataset, or no labelled pixel in the sample.
    """
    n = len(dataset)
    if n == 0:
        raise GeosegError("dataset: empty; cannot compute class weights")
    rng = np.random.default_rng(seed)
    picks = np.sort(rng.choice(n, size=min(n, max_samples), replace=False))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        counts = class_counts(
            (torch.as_tensor(dataset[int(i)]["labels"]) for i in picks), num_classes
        )
    if int(counts.sum()) == 0:
        raise GeosegError("dataset: no labelled pixel in the sampled frames")
    weights = enet_class_weights(counts, c=c)
    logger.info(
        "class weights from %d frames: %s", len(picks), [round(float(w), 3) for w in weights]
    )
    return weights, counts


def downsample_labels(labels: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
    """Nearest-neighbour downsampling of `(B, H, W)` integer labels to `(B, h, w)` = ``size``."""
    if tuple(labels.shape[-2:]) == tuple(size):
        return labels
    out = F.interpolate(labels[:, None].float(), size=tuple(size), mode="nearest")
    return out[:, 0].long()


class WeightedCrossEntropy(nn.Module):
    """Softmax cross-entropy with per-class weights and an ignore label.

    Args:
        weight: `(C,)` class weights (e.g. :func:`class_weights_from_dataset`), None = uniform.
        ignore_index: label id excluded from the loss.
        output_key: key of the `(B, C, h, w)` logits in the model's outputs.

    Call:
        ``loss(outputs, batch)`` with ``batch["labels"]`` `(B, H, W)` int64; returns a scalar.
    """

    def __init__(
        self,
        weight: torch.Tensor | None = None,
        *,
        ignore_index: int = IGNORE_INDEX,
        output_key: str = "logits",
    ) -> None:
        super().__init__()
        self.register_buffer("weight", None if weight is None else torch.as_tensor(weight).float())
        self.ignore_index = ignore_index
        self.output_key = output_key

    def forward(
        self, outputs: Mapping[str, torch.Tensor], batch: Mapping[str, Any]
    ) -> torch.Tensor:
        logits = outputs[self.output_key]
        labels = batch["labels"]
        labels = downsample_labels(labels, logits.shape[-2:])
        weight = None if self.weight is None else self.weight.to(logits.device, logits.dtype)
        if not (labels != self.ignore_index).any():
            return logits.sum() * 0.0  # nothing labelled: zero loss, graph kept
        return F.cross_entropy(logits, labels, weight=weight, ignore_index=self.ignore_index)


class NormalsLoss(nn.Module):
    """Eq. 4.10: mean squared distance of predicted and true normals on valid pixels.

    Args:
        angular_weight: weight of the extra mean-angle term (radians), 0 = MSE only.
        output_key: key of the `(B, 3, H, W)` predicted normals.

    Call:
        ``loss(outputs, batch)`` with ``batch["normals"]`` `(B, 3, H, W)` and optionally
        ``batch["normal_valid"]`` `(B, H, W)` bool (default: true normals of unit length).
        Returns ``{"loss", "mse", "angle_deg"}`` (the last two for logging).
    """

    def __init__(self, *, angular_weight: float = 0.0, output_key: str = "normals") -> None:
        super().__init__()
        if angular_weight < 0:
            raise GeosegError(f"angular_weight: expected >= 0, got {angular_weight}")
        self.angular_weight = float(angular_weight)
        self.output_key = output_key

    def forward(
        self, outputs: Mapping[str, torch.Tensor], batch: Mapping[str, Any]
    ) -> dict[str, torch.Tensor]:
        pred = outputs[self.output_key]
        target = batch["normals"].to(pred.dtype)
        if pred.shape != target.shape:
            raise GeosegError(
                f"normals: prediction {tuple(pred.shape)} and target {tuple(target.shape)} differ"
            )
        valid = batch.get("normal_valid")
        valid = vector_length(target, 1) > 0.5 if valid is None else valid.bool()
        n = valid.sum()
        if int(n) == 0:
            zero = pred.sum() * 0.0
            return {"loss": zero, "mse": zero.detach(), "angle_deg": zero.detach()}
        sq = (pred - target).square().sum(1)  # (B, H, W)
        mse = (sq * valid).sum() / n
        cos = (pred * target).sum(1).clamp(-1 + 1e-6, 1 - 1e-6)
        angle = torch.acos(cos)
        mean_angle = (angle * valid).sum() / n
        loss = mse + self.angular_weight * mean_angle if self.angular_weight else mse
        return {"loss": loss, "mse": mse.detach(), "angle_deg": torch.rad2deg(mean_angle).detach()}


class PatchNLL(nn.Module):
    """Negative log-likelihood of the naive CNN's `(B, C)` ``log_probs`` vs `(B,)` labels.

    Args:
        weight: optional `(C,)` class weights (patches are class-balanced: None by default).
        ignore_index: label id excluded from the loss.
    """

    def __init__(
        self, weight: torch.Tensor | None = None, *, ignore_index: int = IGNORE_INDEX
    ) -> None:
        super().__init__()
        self.register_buffer("weight", None if weight is None else torch.as_tensor(weight).float())
        self.ignore_index = ignore_index

    def forward(
        self, outputs: Mapping[str, torch.Tensor], batch: Mapping[str, Any]
    ) -> torch.Tensor:
        log_probs = outputs["log_probs"]
        labels = batch["labels"]
        if log_probs.ndim == 4:  # dense output (B, C, H, W) vs (B, H, W)
            labels = downsample_labels(labels, log_probs.shape[-2:])
        weight = None if self.weight is None else self.weight.to(log_probs.device)
        return F.nll_loss(log_probs, labels, weight=weight, ignore_index=self.ignore_index)
