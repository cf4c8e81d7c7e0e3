"""Evaluation metrics: segmentation (confusion matrix, IoU), class weights, normals, filters.

Functions work on tensors of any device; meters (:class:`SegmentationMeter`,
:class:`NormalsMeter`, :class:`MeterCollection`) accumulate over batches, keep their state in
tensors that :mod:`training.distributed` can all-reduce, and are what
:func:`training.loop.evaluate` calls (``reset()``, ``update(outputs, batch)``, ``compute()``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import torch

from geoseg.classes import BUILDING, CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from geoseg.errors import GeosegError, check_shape
from geoseg.vectors import vector_length

logger = logging.getLogger(__name__)

ANGLE_THRESHOLDS_DEG = (11.25, 22.5, 30.0)


# ----------------------------------------------------------------------------- segmentation
def confusion_matrix(
    pred: torch.Tensor,
    target: torch.Tensor,
    num_classes: int = NUM_CLASSES,
    *,
    ignore_index: int = IGNORE_INDEX,
) -> torch.Tensor:
    """Confusion matrix of predicted vs true class ids.

    Args:
        pred: `(...)` integer predicted class ids (e.g. ``logits.argmax(1)``, `(B, H, W)`).
        target: `(...)` integer true class ids, same shape; ``ignore_index`` pixels are skipped.
        num_classes: C.
        ignore_index: label id to skip.

    Returns:
        `(C, C)` int64, ``cm[t, p]`` = number of pixels of true class t predicted as p.

    Raises:
        GeosegError: shapes differ, or a non-ignored target id is outside ``[0, C)``.
    """
    if pred.shape != target.shape:
        raise GeosegError(
            f"pred/target: expected the same shape, got {tuple(pred.shape)} and "
            f"{tuple(target.shape)}"
        )
    t = target.reshape(-1).long()
    p = pred.reshape(-1).long()
    keep = t != ignore_index
    t, p = t[keep], p[keep]
    if t.numel() and (int(t.min()) < 0 or int(t.max()) >= num_classes):
        raise GeosegError(
            f"target: class ids must be in [0, {num_classes}) or {ignore_index}, got range "
            f"[{int(t.min())}, {int(t.max())}]"
        )
    p = p.clamp(0, num_classes - 1)
    return torch.bincount(t * num_classes + p, minlength=num_classes**2).reshape(
        num_classes, num_classes
    )


def iou_per_class(cm: torch.Tensor) -> torch.Tensor:
    """Per-class intersection over union from a confusion matrix.

    Args:
        cm: `(C, C)` confusion matrix (rows true, columns predicted).

    Returns:
        `(C,)` float64; NaN for a class that is neither present nor predicted.
    """
    check_shape("cm", cm, (None, cm.shape[0] if cm.ndim == 2 else None))
    cm = cm.double()
    tp = cm.diagonal()
    union = cm.sum(0) + cm.sum(1) - tp
    return torch.where(union > 0, tp / union.clamp_min(1), torch.full_like(tp, math.nan))


def segmentation_scores(
    cm: torch.Tensor,
    class_names: Sequence[str] | None = None,
    *,
    classes: Sequence[int] | None = None,
) -> dict[str, float]:
    """mIoU, pixel accuracy and per-class IoU.

    The mean is taken over ``classes`` (the classes the dataset labels), skipping those with an
    undefined IoU (neither present nor predicted). A class the dataset cannot contain (CamVid has
    no ``terrain``) is left out of the mean and of the per-class keys; predicting it still
    costs: those pixels are errors of their true class, whose IoU drops.

    Args:
        cm: `(C, C)` confusion matrix (rows true, columns predicted).
        class_names: C names for the ``iou_<name>`` keys (default: geoseg's 8 classes when
            C == 8, else ``iou_<index>``).
        classes: indices of the classes the dataset labels (default: all C).

    Returns:
        ``{"miou", "pixel_acc", "iou_<name>"...}`` as Python floats (NaN where undefined).

    Raises:
        GeosegError: wrong number of names, a class index outside ``[0, C)``.
    """
    iou = iou_per_class(cm)
    total = float(cm.sum())
    names = class_names or (CLASS_NAMES if cm.shape[0] == NUM_CLASSES else None)
    names = names or [str(i) for i in range(cm.shape[0])]
    if len(names) != cm.shape[0]:
        raise GeosegError(f"class_names: expected {cm.shape[0]} names, got {len(names)}")
    keep = list(range(cm.shape[0])) if classes is None else sorted({int(c) for c in classes})
    if not keep or keep[0] < 0 or keep[-1] >= cm.shape[0]:
        raise GeosegError(f"classes: expected indices in [0, {cm.shape[0]}), got {classes}")
    kept = iou[keep]
    defined = kept[~torch.isnan(kept)]
    out = {
        "miou": float(defined.mean()) if defined.numel() else math.nan,
        "pixel_acc": float(cm.diagonal().sum()) / total if total else math.nan,
    }
    out.update({f"iou_{names[c]}": float(iou[c]) for c in keep})
    return out


def class_counts(
    labels: torch.Tensor | Iterable[torch.Tensor],
    num_classes: int = NUM_CLASSES,
    *,
    ignore_index: int = IGNORE_INDEX,
) -> torch.Tensor:
    """Pixel count per class over one label map or an iterable of them.

    Args:
        labels: `(...)` integer label maps (ignore pixels skipped) or an iterable of those.

    Returns:
        `(C,)` int64 counts.
    """
    maps = [labels] if isinstance(labels, torch.Tensor) else labels
    counts = torch.zeros(num_classes, dtype=torch.int64)
    for lab in maps:
        flat = lab.reshape(-1).long()
        flat = flat[flat != ignore_index]
        if flat.numel() and (int(flat.min()) < 0 or int(flat.max()) >= num_classes):
            raise GeosegError(
                f"labels: class ids must be in [0, {num_classes}) or {ignore_index}, got range "
                f"[{int(flat.min())}, {int(flat.max())}]"
            )
        counts += torch.bincount(flat, minlength=num_classes).cpu()
    return counts


def enet_class_weights(counts: torch.Tensor, *, c: float = 1.02) -> torch.Tensor:
    """ENet's class weights ``w_k = 1 / ln(c + p_k)``, ``p_k`` the share of class k's pixels.

    Args:
        counts: `(C,)` pixel counts (or frequencies) per class.
        c: ENet's constant (1.02 in the paper) bounding the weights to ``[1/ln(c+1), 1/ln(c)]``.

    Returns:
        `(C,)` float32 weights (absent classes get the maximum ``1/ln(c)``).
    """
    counts = torch.as_tensor(counts, dtype=torch.float64)
    check_shape("counts", counts, (None,))
    if (counts < 0).any() or float(counts.sum()) <= 0:
        raise GeosegError("counts: expected non-negative counts with a positive total")
    if c <= 1.0:
        raise GeosegError(f"c: expected > 1 (so that ln(c + p) > 0), got {c}")
    p = counts / counts.sum()
    return (1.0 / torch.log(c + p)).float()


# ----------------------------------------------------------------------------- normals
def angular_error_deg(
    pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Angle between predicted and true normals, in degrees, on valid pixels.

    Args:
        pred: `(B, 3, H, W)` or `(3, H, W)` or `(N, 3)`... predicted normals along dim -3 for
            maps / dim -1 for `(N, 3)`; need not be unit length (normalised here).
        target: same shape, true unit normals (zero vectors = invalid).
        valid: boolean mask with the shape of ``pred`` minus its vector dimension; default: target
            pixels with a non-zero vector.

    Returns:
        `(M,)` float errors in ``[0, 180]`` for the M valid pixels.
    """
    if pred.shape != target.shape:
        raise GeosegError(
            f"pred/target normals: expected the same shape, got {tuple(pred.shape)} and "
            f"{tuple(target.shape)}"
        )
    dim = -1 if (pred.ndim == 2 and pred.shape[-1] == 3) else -3
    if pred.shape[dim] != 3:
        raise GeosegError(f"normals: expected 3 components, got shape {tuple(pred.shape)}")
    pred = pred.double()
    target = target.double()
    tnorm = vector_length(target, dim)
    mask = tnorm > 0.5 if valid is None else valid.bool() & (tnorm > 1e-6)
    cos = (pred * target).sum(dim) / (vector_length(pred, dim) * tnorm).clamp_min(1e-12)
    ang = torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))
    return ang[mask].float()


def normal_scores(
    errors_deg: torch.Tensor, thresholds: Sequence[float] = ANGLE_THRESHOLDS_DEG
) -> dict[str, float]:
    """Mean, median and within-threshold shares of angular errors.

    Args:
        errors_deg: `(M,)` angular errors in degrees.

    Returns:
        ``{"angle_mean", "angle_median", "within_11_25", "within_22_5", "within_30"}`` (NaN when
        M == 0; shares in ``[0, 1]``).
    """
    e = errors_deg.reshape(-1).double()
    out = {
        "angle_mean": float(e.mean()) if e.numel() else math.nan,
        "angle_median": float(e.quantile(0.5)) if e.numel() else math.nan,
    }
    for th in thresholds:
        out[_within_key(th)] = float((e <= th).double().mean()) if e.numel() else math.nan
    return out


def _within_key(th: float) -> str:
    return "within_" + f"{th:g}".replace(".", "_")


# ----------------------------------------------------------------------------- building filter
def building_filter_scores(
    pred_building: torch.Tensor, accepted: torch.Tensor, true_building: torch.Tensor
) -> dict[str, float]:
    """False positives removed and false rejections added by a building filter (thesis §4.2.4).

    A filter looks at the pixels the argmax calls building and accepts some of them.

    Args:
        pred_building: `(N,)` bool, argmax class is building.
        accepted: `(N,)` bool, kept by the filter (must imply ``pred_building``).
        true_building: `(N,)` bool, ground truth is building (ignore pixels removed beforehand).

    Returns:
        Counts ``fp_argmax``, ``fp_filter`` (accepted but not building), ``fr_argmax``,
        ``fr_filter`` (building but not accepted), ``n_building``, and the shares
        ``fp_removed = 1 - fp_filter / fp_argmax`` and
        ``extra_false_rejections = (fr_filter - fr_argmax) / n_building`` (the thesis's "x % more
        false rejections", relative to the true building pixels).
    """
    pred_building = pred_building.reshape(-1).bool()
    accepted = accepted.reshape(-1).bool() & pred_building
    true_building = true_building.reshape(-1).bool()
    if not (pred_building.shape == accepted.shape == true_building.shape):
        raise GeosegError(
            "pred_building/accepted/true_building: expected the same number of pixels"
        )
    fp_argmax = int((pred_building & ~true_building).sum())
    fp_filter = int((accepted & ~true_building).sum())
    fr_argmax = int((~pred_building & true_building).sum())
    fr_filter = int((~accepted & true_building).sum())
    n_building = int(true_building.sum())
    return {
        "fp_argmax": fp_argmax,
        "fp_filter": fp_filter,
        "fr_argmax": fr_argmax,
        "fr_filter": fr_filter,
        "n_building": n_building,
        "fp_removed": 1.0 - fp_filter / fp_argmax if fp_argmax else math.nan,
        "extra_false_rejections": (fr_filter - fr_argmax) / n_building if n_building else math.nan,
    }


# ----------------------------------------------------------------------------- meters
def _as_outputs(outputs: Any) -> Mapping[str, torch.Tensor]:
    return outputs if isinstance(outputs, Mapping) else {"logits": outputs}


class Meter:
    """Base class: accumulators live in ``self.state`` (a dict of tensors) so that they can be
    summed across processes with :meth:`reduce_`."""

    def __init__(self) -> None:
        self.state: dict[str, torch.Tensor] = {}
        self.reset()

    def reset(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def update(self, outputs: Any, batch: Mapping[str, Any]) -> None:  # pragma: no cover
        raise NotImplementedError

    def compute(self) -> dict[str, float]:  # pragma: no cover
        raise NotImplementedError

    def reduce_(self, fn: Callable[[torch.Tensor], Any]) -> None:
        """Apply an in-place reduction (e.g. ``dist.all_reduce``) to every accumulator."""
        for key in sorted(self.state):
            fn(self.state[key])


class SegmentationMeter(Meter):
    """Confusion-matrix accumulator: ``outputs[output_key]`` `(B, C, H, W)` logits vs
    ``batch[target_key]`` `(B, H, W)` labels; computes :func:`segmentation_scores` (mean IoU over
    ``classes``, the classes the dataset labels; default all)."""

    def __init__(
        self,
        num_classes: int = NUM_CLASSES,
        *,
        output_key: str = "logits",
        target_key: str = "labels",
        ignore_index: int = IGNORE_INDEX,
        class_names: Sequence[str] | None = None,
        classes: Sequence[int] | None = None,
    ) -> None:
        self.num_classes = num_classes
        self.classes = None if classes is None else tuple(classes)
        self.output_key = output_key
        self.target_key = target_key
        self.ignore_index = ignore_index
        self.class_names = class_names
        super().__init__()

    def reset(self) -> None:
        """Zero the confusion matrix."""
        self.state = {"cm": torch.zeros(self.num_classes, self.num_classes, dtype=torch.int64)}

    def update(self, outputs: Any, batch: Mapping[str, Any]) -> None:
        """Add a batch; ``outputs`` is the model's dict (or its logits tensor)."""
        logits = _as_outputs(outputs)[self.output_key]
        target = batch[self.target_key]
        cm = confusion_matrix(
            logits.argmax(1), target, self.num_classes, ignore_index=self.ignore_index
        )
        self.state["cm"] = self.state["cm"].to(cm.device) + cm

    def compute(self) -> dict[str, float]:
        """:func:`segmentation_scores` of the accumulated matrix."""
        return segmentation_scores(self.state["cm"].cpu(), self.class_names, classes=self.classes)


class NormalsMeter(Meter):
    """Angular-error accumulator over valid pixels (optionally of one class only).

    Errors are binned in a histogram of ``bin_deg`` degrees so that the median is mergeable
    across batches and processes (exact to within half a bin); mean and threshold shares are
    exact.

    Args:
        output_key: key of the `(B, 3, H, W)` predicted normals in the model's outputs.
        target_key: key of the `(B, 3, H, W)` true normals in the batch (zero = invalid).
        only_class: when set, only pixels with ``batch[labels_key] == only_class`` count (e.g.
            building pixels, :data:`~geoseg.classes.BUILDING`).
        prefix: prepended to the result keys (e.g. ``"building_"``).
    """

    def __init__(
        self,
        *,
        output_key: str = "normals",
        target_key: str = "normals",
        labels_key: str = "labels",
        only_class: int | None = None,
        prefix: str = "",
        bin_deg: float = 0.05,
        thresholds: Sequence[float] = ANGLE_THRESHOLDS_DEG,
    ) -> None:
        self.output_key = output_key
        self.target_key = target_key
        self.labels_key = labels_key
        self.only_class = only_class
        self.prefix = prefix
        self.bin_deg = bin_deg
        self.thresholds = tuple(thresholds)
        self.n_bins = int(math.ceil(180.0 / bin_deg))
        super().__init__()

    def reset(self) -> None:
        """Zero the accumulators."""
        self.state = {
            "hist": torch.zeros(self.n_bins, dtype=torch.int64),
            "sum": torch.zeros((), dtype=torch.float64),
            "within": torch.zeros(len(self.thresholds), dtype=torch.int64),
        }

    def update(self, outputs: Any, batch: Mapping[str, Any]) -> None:
        """Add a batch of predicted vs true normals."""
        pred = _as_outputs(outputs)[self.output_key]
        target = batch[self.target_key]
        valid = None
        if self.only_class is not None:
            valid = (batch[self.labels_key] == self.only_class) & (vector_length(target, -3) > 0.5)
        err = angular_error_deg(pred, target, valid)
        dev = err.device
        idx = (err / self.bin_deg).long().clamp(0, self.n_bins - 1)
        self.state["hist"] = self.state["hist"].to(dev) + torch.bincount(idx, minlength=self.n_bins)
        self.state["sum"] = self.state["sum"].to(dev) + err.double().sum()
        within = torch.stack([(err <= th).sum() for th in self.thresholds]) if err.numel() else 0
        self.state["within"] = self.state["within"].to(dev) + within

    def compute(self) -> dict[str, float]:
        """Mean, median (histogram) and threshold shares, keys prefixed with ``prefix``."""
        hist = self.state["hist"].cpu().double()
        n = float(hist.sum())
        out: dict[str, float] = {}
        if n == 0:
            out["angle_mean"] = out["angle_median"] = math.nan
            out.update({_within_key(th): math.nan for th in self.thresholds})
        else:
            cdf = hist.cumsum(0)
            k = int(torch.searchsorted(cdf, torch.tensor(n / 2, dtype=torch.float64)))
            before = float(cdf[k - 1]) if k > 0 else 0.0
            frac = (n / 2 - before) / max(float(hist[k]), 1.0)
            out["angle_mean"] = float(self.state["sum"]) / n
            out["angle_median"] = (k + frac) * self.bin_deg
            for th, count in zip(self.thresholds, self.state["within"].cpu().tolist()):
                out[_within_key(th)] = count / n
        out["n_pixels"] = n
        return {self.prefix + k: v for k, v in out.items()}


class MeterCollection(Meter):
    """Several meters behind one ``reset/update/compute/reduce_`` interface (merged results)."""

    def __init__(self, *meters: Meter) -> None:
        self.meters = meters
        super().__init__()

    def reset(self) -> None:
        """Reset every meter."""
        for m in self.meters:
            m.reset()

    def update(self, outputs: Any, batch: Mapping[str, Any]) -> None:
        """Update every meter."""
        for m in self.meters:
            m.update(outputs, batch)

    def compute(self) -> dict[str, float]:
        """Merged results (later meters win on key clashes)."""
        out: dict[str, float] = {}
        for m in self.meters:
            out.update(m.compute())
        return out

    def reduce_(self, fn: Callable[[torch.Tensor], Any]) -> None:
        """Reduce every meter's accumulators."""
        for m in self.meters:
            m.reduce_(fn)


def building_normals_meter() -> NormalsMeter:
    """Angular errors on building pixels only, keys prefixed ``building_`` (targets of
    bench/accuracy_seg.py)."""
    return NormalsMeter(only_class=BUILDING, prefix="building_")
