"""Accuracy of the segmentation side on a held-out synthetic city (figures: docs/results.md).

Evaluation data: the ``test`` split of :func:`geoseg.data.synthetic.synthetic_config`, the
evaluation city :data:`~geoseg.data.synthetic.EVAL_SEEDS` (never used for training or
validation) under every condition, including :data:`~geoseg.data.synthetic.HELDOUT_CONDITIONS`
(never trained on). :func:`heldout_indices` picks the frames round robin over the conditions,
the held-out conditions first, so that even two frames hold one of them.

Four figures groups, each computed when its model is given (:func:`evaluate`):

- **labels** (ENet, ``seg``): mIoU over the 8 classes, building IoU, pixel accuracy, per-class
  IoU (:func:`training.metrics.segmentation_scores`), also on the held-out condition alone;
- **normals** (the joint network, ``normals``): angular error on ground-truth building pixels
  (mean, median, shares within 11.25/22.5/30 degrees; :func:`training.metrics.building_normals_meter`)
  and on all valid pixels;
- **filter** (naive CNN ``naive`` + Dirichlet filter ``dirichlet``, thesis §4.2.4.1): with the
  filter's stored threshold (calibrated on the validation city by
  :mod:`training.dirichlet_fit`), the share of the argmax's building false positives it removes
  and the extra false rejections it adds (:func:`training.metrics.building_filter_scores`).
  Beside it, the max-probability baseline with its threshold set on these same frames so that it
  adds exactly as many false rejections as the Dirichlet filter did
  (``maxprob_fp_removed_same_rejections``: matching on the test frames favours the baseline, so a
  Dirichlet win is conservative), and, when given, the baseline with its own stored threshold
  (``maxprob_*_calibrated``).

Models are any callables mapping RGB uint8 images ``(B, H, W, 3)`` to a
:class:`geoseg.infer.SegmentationResult` (:class:`geoseg.infer.Segmenter`, or a stub);
:func:`load_predictor` opens a run directory, a ``model.pt``, a training checkpoint or an ONNX
file. :func:`model_record` reads what a run recorded about its training (model card, wall time)
and :func:`untrained_reasons` says why a model or an evaluation must not back a published figure.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from geoseg.classes import BUILDING, IGNORE_INDEX, NUM_CLASSES
from geoseg.dirichlet import DirichletFilter, MaxProbabilityFilter, load_filter
from geoseg.errors import GeosegError
from geoseg.infer import SegmentationResult, Segmenter

logger = logging.getLogger(__name__)

Predictor = Callable[[np.ndarray], SegmentationResult]

MIN_PUBLISHED_SIZE_HW: tuple[int, int] = (240, 320)  # published figures at >= 320x240
MIN_PUBLISHED_FRAMES = 16  # fewer held-out frames: a smoke run
MIN_TRAIN_FRAMES = 64  # fewer training frames: a tiny test config
FILTER_FILE = "dirichlet.json"
BASELINE_FILE = "max_probability.json"

# (figure key, comparison, target) of the accuracy benchmark; ``>=`` / ``<=``.
TARGETS: tuple[tuple[str, str, float], ...] = (
    ("miou", ">=", 0.80),
    ("building_iou", ">=", 0.90),
    ("normals_building_median_deg", "<=", 10.0),
    ("normals_building_within_11_25", ">=", 0.60),
    ("dirichlet_fp_removed", ">=", 0.70),
    ("dirichlet_extra_false_rejections", "<=", 0.15),
)


@dataclass
class EvalConfig:
    """What the held-out evaluation renders and how it batches.

    Attributes:
        frames: held-out frames evaluated.
        size: ``(H, W)`` of the frames (at least 240x320 for published figures).
        cache_dir: on-disk frame cache (None: render every frame).
        synth: ``data.synth``-like overrides of the ``test`` split (e.g. ``{"world": {...}}``).
        batch_size: frames per forward pass.
        panel_frames: the first frames kept for the figure panels (:mod:`training.figures`).
        pool_factor: candidate frames per evaluated frame that :func:`heldout_indices` draws its
            balanced selection from.
        progress: tqdm bar.
    """

    frames: int = 24
    size: tuple[int, int] = (240, 320)
    cache_dir: Path | None = None
    synth: dict[str, Any] = field(default_factory=dict)
    batch_size: int = 2
    panel_frames: int = 4
    pool_factor: int = 8
    progress: bool = True

    def __post_init__(self) -> None:
        if self.frames < 1 or self.batch_size < 1 or self.pool_factor < 1:
            raise GeosegError(
                f"frames / batch_size / pool_factor: expected >= 1, got {self.frames}, "
                f"{self.batch_size}, {self.pool_factor}"
            )
        if self.panel_frames < 0:
            raise GeosegError(f"panel_frames: expected >= 0, got {self.panel_frames}")
        if len(self.size) != 2 or min(int(s) for s in self.size) < 1:
            raise GeosegError(f"size: expected positive (H, W), got {self.size!r}")
        self.size = (int(self.size[0]), int(self.size[1]))
        if self.cache_dir is not None:
            self.cache_dir = Path(self.cache_dir)


@dataclass
class PanelFrame:
    """One held-out frame's images for the figure panels (None where no model predicted it).

    Attributes:
        index: dataset index.
        condition: rendering condition.
        rgb: `(H, W, 3)` uint8 image.
        labels_true: `(H, W)` int64 ground-truth class ids.
        normals_true: `(3, H, W)` float32 ground-truth unit normals (zero where invalid).
        labels_pred: `(H, W)` uint8 predicted class ids (``seg``).
        normals_pred: `(3, H, W)` float32 predicted normals (``normals``).
        building_argmax: `(H, W)` bool, the naive CNN's argmax is building.
        building_filtered: `(H, W)` bool, kept by the Dirichlet filter.
    """

    index: int
    condition: str
    rgb: np.ndarray
    labels_true: np.ndarray
    normals_true: np.ndarray
    labels_pred: np.ndarray | None = None
    normals_pred: np.ndarray | None = None
    building_argmax: np.ndarray | None = None
    building_filtered: np.ndarray | None = None


@dataclass
class EvalResult:
    """:func:`evaluate`'s output.

    Attributes:
        figures: flat mapping figure name → number (or a short string: ``filter_winner``,
            ``conditions``); NaN where undefined.
        panels: the first ``panel_frames`` frames, for :mod:`training.figures`.
    """

    figures: dict[str, Any]
    panels: list[PanelFrame]


# ----------------------------------------------------------------------------- data
def heldout_dataset(cfg: EvalConfig) -> Any:
    """The held-out city's :class:`~geoseg.data.synthetic.SyntheticDataset` (``test`` split,
    images in [0, 1], no augmentation), long enough for :func:`heldout_indices` to choose from."""
    from geoseg.data.synthetic import SyntheticDataset, synthetic_config

    synth = dict(cfg.synth)
    test = dict(synth.pop("test", None) or {})
    test.setdefault("frames", max(64, cfg.frames * cfg.pool_factor))
    synth["test"] = test
    config = synthetic_config(synth, split="test")
    return SyntheticDataset(config, size=cfg.size, cache_dir=cfg.cache_dir)


def heldout_indices(dataset: Any, n: int) -> list[int]:
    """``n`` frame indices balanced over the dataset's conditions, held-out conditions first.

    Round robin over the conditions (those of ``config.heldout_conditions`` first, then the
    others in config order), taking each condition's earliest unused index (no rendering: the
    draws come from ``dataset.spec``). Deterministic.

    Args:
        dataset: a :class:`~geoseg.data.synthetic.SyntheticDataset`.
        n: frames wanted.

    Returns:
        Up to ``n`` indices (fewer only when the dataset is shorter), in round-robin order.
    """
    conds = list(dataset.config.conditions)
    held = [c for c in conds if c in set(dataset.config.heldout_conditions)]
    order = held + [c for c in conds if c not in held]
    queues: dict[str, list[int]] = {c: [] for c in order}
    for i in range(len(dataset)):
        queues[dataset.spec(i).condition].append(i)
    picked: list[int] = []
    while len(picked) < n and any(queues.values()):
        for c in order:
            if queues[c] and len(picked) < n:
                picked.append(queues[c].pop(0))
    if len(picked) < n:
        logger.warning("held-out set: only %d of %d frames available", len(picked), n)
    if held and not any(dataset.spec(i).condition in held for i in picked):
        logger.warning("held-out set: no frame of the held-out conditions %s", held)
    return picked


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    """`(3, H, W)` float in [0, 1] → `(H, W, 3)` uint8 (exact for images decoded from uint8)."""
    return (image.clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()


# ----------------------------------------------------------------------------- models
def load_predictor(path: str | os.PathLike, *, device: str | torch.device = "cpu") -> Segmenter:
    """A :class:`~geoseg.infer.Segmenter` from a run directory, a model/training checkpoint or
    an ONNX file.

    A run directory gives its ``model.pt`` (else ``best.pt``, ``last.pt``, ``model.onnx``).

    Raises:
        GeosegError: nothing usable at ``path`` (the message names it).
    """
    from training import common

    path = Path(path)
    if path.is_dir() and not any((path / n).is_file() for n in ("model.pt", "best.pt", "last.pt")):
        if (path / "model.onnx").is_file():
            path = path / "model.onnx"
    if path.suffix.lower() == ".onnx":
        if not path.is_file():
            raise GeosegError(f"{path}: no such ONNX file")
        return Segmenter.from_onnx(path)
    file = common.resolve_weights_file(path)
    state, ckpt = common.load_state(file)
    if "state_dict" in ckpt:  # a geoseg model checkpoint (model.pt)
        return Segmenter.from_checkpoint(file, device=device)
    return _segmenter_from_state(file, state, ckpt, device)


def _segmenter_from_state(
    file: Path, state: Mapping[str, torch.Tensor], ckpt: Mapping[str, Any], device: Any
) -> Segmenter:
    """A Segmenter over a training checkpoint's weights (best.pt / last.pt)."""
    from geoseg.models.registry import get_model
    from training.frame_data import NORMALIZATION

    name = ckpt.get("model_name")
    if name not in ("enet", "joint", "naive_cnn"):
        raise GeosegError(f"{file}: holds a {name!r} model, not a segmentation network")
    model = get_model(name, **dict(ckpt.get("model_config") or {}))
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise GeosegError(f"{file}: weights do not match {name!r} ({str(err)[:300]})") from None
    return Segmenter.from_module(
        model, device=device, normalization=NORMALIZATION, model_name=name, source=file
    )


def load_filters(
    path: str | os.PathLike,
) -> tuple[DirichletFilter, MaxProbabilityFilter | None]:
    """The Dirichlet filter (and the max-probability baseline when saved beside it) of a
    ``dirichlet`` run directory or a ``dirichlet.json`` file.

    Raises:
        GeosegError: no filter, not a Dirichlet filter, or no calibrated threshold.
    """
    path = Path(path)
    file = path / FILTER_FILE if path.is_dir() else path
    filt = load_filter(file)
    if not isinstance(filt, DirichletFilter):
        raise GeosegError(f"{file}: holds a {filt.kind!r} filter, expected 'dirichlet'")
    if filt.threshold is None:
        raise GeosegError(f"{file}: the filter has no threshold (run the dirichlet stage)")
    base_file = file.parent / BASELINE_FILE
    baseline = None
    if base_file.is_file():
        b = load_filter(base_file)
        baseline = b if isinstance(b, MaxProbabilityFilter) and b.threshold is not None else None
    return filt, baseline


# ----------------------------------------------------------------------------- training records
@dataclass
class ModelRecord:
    """What a run recorded about how a model was trained.

    Attributes:
        path: the path given.
        run_dir: the directory holding the weights (and the card).
        train_minutes: training wall time in minutes (None: not recorded).
        epochs: epochs trained (None: unknown).
        train_frames: training frames of the synthetic data (None: unknown).
        size_hw: ``(H, W)`` of the training frames (None: unknown).
        init_checkpoint: the weights it was fine-tuned from (None: trained from scratch).
        source: where the numbers came from (``model_card.json``, ``metrics.json``...).
    """

    path: Path
    run_dir: Path
    train_minutes: float | None = None
    epochs: int | None = None
    train_frames: int | None = None
    size_hw: tuple[int, int] | None = None
    init_checkpoint: str | None = None
    source: str | None = None


def _history_minutes(metrics_json: Path) -> tuple[float, int] | None:
    if not metrics_json.is_file():
        return None
    try:
        rows = json.loads(metrics_json.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if not isinstance(rows, list):
        return None
    seconds = sum(float(r.get("time_s") or 0.0) for r in rows if isinstance(r, dict))
    return seconds / 60.0, len(rows)


def model_record(path: str | os.PathLike, kind: str) -> ModelRecord:
    """Read the training record of a ``seg``, ``normals``, ``naive`` or ``dirichlet`` run.

    - seg/normals/naive: ``model_card.json`` beside the weights (``train_minutes``, the sum of
      the epochs' ``time_s``; ``epochs``; the data's size and training frames), else the run's
      per-epoch ``metrics.json``. A seg run's encoder-first stage (``encoder/metrics.json``) is
      added to its minutes.
    - dirichlet: the stage's ``metrics.json`` (``fit_seconds + fit_inference_seconds``: the
      dense pass over the fitting frames and the fit; the calibration and evaluation passes are
      not recorded).

    Args:
        path: run directory or file.
        kind: ``seg``, ``normals``, ``naive`` or ``dirichlet``.

    Returns:
        A :class:`ModelRecord` (fields None where nothing was recorded).
    """
    if kind not in ("seg", "normals", "naive", "dirichlet"):
        raise GeosegError(f"kind: expected seg, normals, naive or dirichlet, got {kind!r}")
    path = Path(path)
    run_dir = path if path.is_dir() else path.parent
    rec = ModelRecord(path=path, run_dir=run_dir)
    if kind == "dirichlet":
        metrics = run_dir / "metrics.json"
        if metrics.is_file():
            try:
                data = json.loads(metrics.read_text())
            except (OSError, json.JSONDecodeError):
                data = {}
            secs = [data.get("fit_seconds"), data.get("fit_inference_seconds")]
            if isinstance(data, dict) and any(isinstance(s, int | float) for s in secs):
                rec.train_minutes = sum(float(s) for s in secs if isinstance(s, int | float)) / 60
                rec.epochs = 1
                rec.source = str(metrics)
        return rec
    card_file = run_dir / "model_card.json"
    card: dict[str, Any] = {}
    if card_file.is_file():
        try:
            card = json.loads(card_file.read_text())
        except (OSError, json.JSONDecodeError) as err:
            logger.warning("%s: unreadable model card (%s)", card_file, err)
    if card:
        rec.source = str(card_file)
        if isinstance(card.get("train_minutes"), int | float):
            rec.train_minutes = float(card["train_minutes"])
        if isinstance(card.get("epochs"), int):
            rec.epochs = int(card["epochs"])
        run_config = card.get("config")
        init = run_config.get("init_checkpoint") if isinstance(run_config, dict) else None
        if isinstance(init, str) and init:
            rec.init_checkpoint = init
        data = card.get("data") or {}
        size = data.get("size_hw")
        if isinstance(size, list) and len(size) == 2:
            rec.size_hw = (int(size[0]), int(size[1]))
        train = data.get("train") or {}
        if isinstance(train.get("frames"), int):
            rec.train_frames = int(train["frames"])
    else:
        hist = _history_minutes(run_dir / "metrics.json")
        if hist is not None:
            rec.train_minutes, rec.epochs = hist
            rec.source = str(run_dir / "metrics.json")
    if kind == "seg":
        enc = _history_minutes(run_dir / "encoder" / "metrics.json")
        if enc is not None and rec.train_minutes is not None:
            rec.train_minutes += enc[0]
    return rec


def untrained_reasons(
    records: Mapping[str, ModelRecord], cfg: EvalConfig, frames_evaluated: int | None = None
) -> list[str]:
    """Why these models / this evaluation must not back a published figure (empty: none).

    A model counts as untrained or random when its run recorded no training (no model card nor
    history), zero epochs, or a tiny test configuration (frames smaller than 240x320 or fewer
    than :data:`MIN_TRAIN_FRAMES` training frames); the evaluation counts as a smoke run below
    240x320 or :data:`MIN_PUBLISHED_FRAMES` frames.
    """
    reasons = []
    for kind, rec in records.items():
        if kind == "dirichlet":
            if rec.source is None:
                reasons.append(f"{kind}: {rec.run_dir} holds no fit record (metrics.json)")
            continue
        if rec.source is None:
            reasons.append(f"{kind}: {rec.run_dir} holds no model card or training history")
            continue
        if not rec.epochs:
            reasons.append(f"{kind}: trained for {rec.epochs} epochs")
        if rec.size_hw is not None and (
            rec.size_hw[0] < MIN_PUBLISHED_SIZE_HW[0] or rec.size_hw[1] < MIN_PUBLISHED_SIZE_HW[1]
        ):
            reasons.append(f"{kind}: trained on {rec.size_hw[1]}x{rec.size_hw[0]} frames")
        if rec.train_frames is not None and rec.train_frames < MIN_TRAIN_FRAMES:
            reasons.append(f"{kind}: trained on {rec.train_frames} frames")
    h, w = cfg.size
    if h < MIN_PUBLISHED_SIZE_HW[0] or w < MIN_PUBLISHED_SIZE_HW[1]:
        reasons.append(f"evaluated at {w}x{h} (< 320x240)")
    n = cfg.frames if frames_evaluated is None else frames_evaluated
    if n < MIN_PUBLISHED_FRAMES:
        reasons.append(f"only {n} held-out frames (< {MIN_PUBLISHED_FRAMES})")
    return reasons


def check_targets(figures: Mapping[str, Any]) -> dict[str, bool | None]:
    """Each :data:`TARGETS` key → met (None when the figure is missing or NaN)."""
    out: dict[str, bool | None] = {}
    for key, op, target in TARGETS:
        value = figures.get(key)
        if not isinstance(value, int | float) or not math.isfinite(value):
            out[key] = None
        else:
            out[key] = value >= target if op == ">=" else value <= target
    return out


# ----------------------------------------------------------------------------- evaluation
def _check_result(name: str, res: SegmentationResult, shape: tuple[int, int, int]) -> None:
    b, h, w = shape
    if res.labels.shape != (b, h, w) or res.probabilities.shape != (b, NUM_CLASSES, h, w):
        raise GeosegError(
            f"{name}: expected labels {(b, h, w)} and probabilities {(b, NUM_CLASSES, h, w)}, "
            f"got {res.labels.shape} and {res.probabilities.shape}"
        )


def evaluate(
    cfg: EvalConfig,
    *,
    seg: Predictor | None = None,
    normals: Predictor | None = None,
    naive: Predictor | None = None,
    dirichlet: DirichletFilter | None = None,
    maxprob: MaxProbabilityFilter | None = None,
    dataset: Any = None,
    indices: Sequence[int] | None = None,
) -> EvalResult:
    """Measure the given models on the held-out frames.

    Args:
        cfg: frames, size, batching.
        seg: label model (ENet): labels figures.
        normals: normals model (joint network): normals figures.
        naive: the naive CNN (dense probabilities); needs ``dirichlet``.
        dirichlet: the fitted, calibrated filter; needs ``naive``.
        maxprob: the max-probability baseline with its own stored threshold (optional; same
            ``window`` as ``dirichlet``).
        dataset: override of :func:`heldout_dataset` (samples ``{"image": (3, H, W) in [0, 1],
            "labels": (H, W), "normals": (3, H, W), "condition"}``).
        indices: override of :func:`heldout_indices`.

    Returns:
        :class:`EvalResult`.

    Raises:
        GeosegError: no model, ``naive`` without ``dirichlet`` (or the reverse), a model output
            of the wrong shape or without normals.
    """
    _check_models(seg, normals, naive, dirichlet, maxprob)
    from geoseg.data.synthetic import HELDOUT_CONDITIONS
    from training.metrics import (
        NormalsMeter,
        building_normals_meter,
        confusion_matrix,
    )

    if dataset is None:
        dataset = heldout_dataset(cfg)
    if indices is None:
        indices = heldout_indices(dataset, cfg.frames)
    indices = list(indices)
    if not indices:
        raise GeosegError("evaluate: no held-out frame to evaluate")
    config = getattr(dataset, "config", None)
    held = set(getattr(config, "heldout_conditions", HELDOUT_CONDITIONS))

    cm_all = torch.zeros(NUM_CLASSES, NUM_CLASSES, dtype=torch.int64)
    cm_held = torch.zeros_like(cm_all)
    cm_naive = torch.zeros_like(cm_all)
    n_meter_b, n_meter_all = building_normals_meter(), NormalsMeter()
    filt: dict[str, list[np.ndarray]] = {"pred": [], "keep": [], "truth": []}
    tb_probs: list[np.ndarray] = []  # argmax-building true-building vectors (baseline matching)
    fp_probs: list[np.ndarray] = []  # argmax-building, not building
    conditions: Counter[str] = Counter()
    panels: list[PanelFrame] = []

    batches = [indices[i : i + cfg.batch_size] for i in range(0, len(indices), cfg.batch_size)]
    for batch_idx in tqdm(batches, desc="held-out", leave=False, disable=not cfg.progress):
        samples = [dataset[i] for i in batch_idx]
        images = np.stack([_to_uint8(s["image"]) for s in samples])
        labels = torch.stack([torch.as_tensor(s["labels"]).long() for s in samples])
        gt_normals = torch.stack([torch.as_tensor(s["normals"]).float() for s in samples])
        conds = [str(s.get("condition", "")) for s in samples]
        conditions.update(conds)
        shape = tuple(labels.shape)
        res_seg = res_n = res_v = None
        if seg is not None:
            res_seg = seg(images)
            _check_result("seg", res_seg, shape)
            pred = torch.from_numpy(res_seg.labels.astype(np.int64))
            for k, c in enumerate(conds):
                cm = confusion_matrix(pred[k], labels[k])
                cm_all += cm
                if c in held:
                    cm_held += cm
        if normals is not None:
            res_n = res_seg if normals is seg else normals(images)
            if res_n.normals is None:
                raise GeosegError("normals: the model predicts no normals (expected the joint net)")
            if res_n.normals.shape != tuple(gt_normals.shape):
                raise GeosegError(
                    f"normals: expected {tuple(gt_normals.shape)}, got {res_n.normals.shape}"
                )
            out = {"normals": torch.from_numpy(res_n.normals)}
            tgt = {"normals": gt_normals, "labels": labels}
            n_meter_b.update(out, tgt)
            n_meter_all.update(out, tgt)
        keep_maps: list[np.ndarray] = []
        if naive is not None:
            res_v = naive(images)
            _check_result("naive", res_v, shape)
            cm_naive += confusion_matrix(torch.from_numpy(res_v.labels.astype(np.int64)), labels)
            keep_maps = _filter_frames(res_v, labels, dirichlet, filt, tb_probs, fp_probs)
        panels += _panels(
            cfg.panel_frames - len(panels), batch_idx, conds, images, labels, gt_normals,
            res_seg, res_n, res_v, keep_maps,
        )  # fmt: skip

    h, w = shape[1:]
    figures: dict[str, Any] = {
        "frames": len(indices),
        "frames_heldout_condition": sum(conditions[c] for c in held),
        "eval_width": int(w),
        "eval_height": int(h),
        "eval_seeds": ",".join(str(s) for s in getattr(config, "seeds", [])),
        "conditions": ",".join(f"{c}:{n}" for c, n in sorted(conditions.items())),
    }
    if seg is not None:
        figures.update(_segmentation_figures(cm_all, cm_held))
    if normals is not None:
        figures.update(_normals_figures(n_meter_b, n_meter_all))
    if naive is not None:
        figures.update(
            _filter_figures(filt, tb_probs, fp_probs, dirichlet, maxprob, cm_naive)  # type: ignore[arg-type]
        )
    return EvalResult(figures=figures, panels=panels)


def _panels(
    n: int,
    batch_idx: Sequence[int],
    conds: list[str],
    images: np.ndarray,
    labels: torch.Tensor,
    gt_normals: torch.Tensor,
    res_seg: SegmentationResult | None,
    res_n: SegmentationResult | None,
    res_v: SegmentationResult | None,
    keep_maps: list[np.ndarray],
) -> list[PanelFrame]:
    """The first ``n`` (at most) frames of a batch as picture panels."""
    panels: list[PanelFrame] = []
    for k, i in enumerate(batch_idx):
        if len(panels) >= n:
            break
        panels.append(
            PanelFrame(
                index=int(i),
                condition=conds[k],
                rgb=images[k],
                labels_true=labels[k].numpy(),
                normals_true=gt_normals[k].numpy(),
                labels_pred=None if res_seg is None else res_seg.labels[k],
                normals_pred=None if res_n is None else res_n.normals[k],
                building_argmax=None if res_v is None else res_v.labels[k] == BUILDING,
                building_filtered=keep_maps[k] if keep_maps else None,
            )
        )
    return panels


def _check_models(
    seg: Predictor | None,
    normals: Predictor | None,
    naive: Predictor | None,
    dirichlet: DirichletFilter | None,
    maxprob: MaxProbabilityFilter | None,
) -> None:
    """The checks of :func:`evaluate`'s models (see its Raises)."""
    if seg is None and normals is None and naive is None:
        raise GeosegError("evaluate: give at least one of seg, normals, naive")
    if (naive is None) != (dirichlet is None):
        raise GeosegError(
            "naive/dirichlet: the filter figures need both the naive CNN and the filter"
        )
    if dirichlet is not None and dirichlet.threshold is None:
        raise GeosegError("dirichlet: the filter has no threshold")
    if maxprob is not None and dirichlet is not None and maxprob.window != dirichlet.window:
        raise GeosegError(
            f"maxprob: window {maxprob.window} differs from the Dirichlet filter's "
            f"{dirichlet.window}; both must score the same smoothed maps"
        )


def _filter_frames(
    res_v: SegmentationResult,
    labels: torch.Tensor,
    dirichlet: DirichletFilter,
    filt: dict[str, list[np.ndarray]],
    tb_probs: list[np.ndarray],
    fp_probs: list[np.ndarray],
) -> list[np.ndarray]:
    """The Dirichlet filter on a batch of the naive CNN's maps: appends each frame's building
    pixels to ``filt``, ``tb_probs`` and ``fp_probs``; returns the kept maps ``(H, W)``."""
    keep_maps: list[np.ndarray] = []
    for k in range(len(labels)):
        lab = labels[k].numpy()
        probs = res_v.probabilities[k].transpose(1, 2, 0)  # (H, W, C)
        argmax = res_v.labels[k].astype(np.int64)
        smoothed = dirichlet.smooth(probs)  # what both filters score, smoothed once
        keep = dirichlet.filter(
            smoothed.reshape(-1, smoothed.shape[-1]), argmax.reshape(-1)
        ).reshape(argmax.shape)
        keep_maps.append(keep)
        valid = lab != IGNORE_INDEX
        pred_b = (argmax == BUILDING)[valid]
        truth = (lab == BUILDING)[valid]
        filt["pred"].append(pred_b)
        filt["keep"].append(keep[valid])
        filt["truth"].append(truth)
        p = smoothed[valid]
        tb_probs.append(p[pred_b & truth])
        fp_probs.append(p[pred_b & ~truth])
    return keep_maps


def _segmentation_figures(cm_all: torch.Tensor, cm_held: torch.Tensor) -> dict[str, Any]:
    """The label figures of all frames and of the held-out-condition frames."""
    from training.metrics import segmentation_scores

    out: dict[str, Any] = {}
    scores = segmentation_scores(cm_all)
    out["miou"] = scores.pop("miou")
    out["building_iou"] = scores["iou_building"]
    out["pixel_acc"] = scores.pop("pixel_acc")
    out.update(scores)
    held_scores = segmentation_scores(cm_held) if int(cm_held.sum()) else {}
    out["miou_heldout_condition"] = held_scores.get("miou", math.nan)
    out["building_iou_heldout_condition"] = held_scores.get("iou_building", math.nan)
    return out


def _normals_figures(n_meter_b: Any, n_meter_all: Any) -> dict[str, Any]:
    """The normals figures on building pixels and on all pixels."""
    out: dict[str, Any] = {}
    b = n_meter_b.compute()
    a = n_meter_all.compute()
    for src, prefix, tag in ((b, "building_", "building"), (a, "", "all")):
        out[f"normals_{tag}_mean_deg"] = src.get(f"{prefix}angle_mean", math.nan)
        out[f"normals_{tag}_median_deg"] = src.get(f"{prefix}angle_median", math.nan)
        for th in ("11_25", "22_5", "30"):
            out[f"normals_{tag}_within_{th}"] = src.get(f"{prefix}within_{th}", math.nan)
        out[f"normals_{tag}_pixels"] = int(src.get(f"{prefix}n_pixels", 0))
    return out


def _filter_figures(
    filt: Mapping[str, list[np.ndarray]],
    tb_probs: list[np.ndarray],
    fp_probs: list[np.ndarray],
    dirichlet: DirichletFilter,
    maxprob: MaxProbabilityFilter | None,
    cm_naive: torch.Tensor,
) -> dict[str, Any]:
    """The §4.2.4.1 figures from the accumulated masks (see the module docstring)."""
    from training.dirichlet_fit import filter_winner
    from training.metrics import building_filter_scores, segmentation_scores

    pred = torch.from_numpy(np.concatenate(filt["pred"]))
    truth = torch.from_numpy(np.concatenate(filt["truth"]))
    d = building_filter_scores(pred, torch.from_numpy(np.concatenate(filt["keep"])), truth)
    tb = np.concatenate(tb_probs) if tb_probs else np.zeros((0, NUM_CLASSES), np.float32)
    fp = np.concatenate(fp_probs) if fp_probs else np.zeros((0, NUM_CLASSES), np.float32)
    # the baseline adding exactly the Dirichlet filter's extra false rejections on these frames
    extra = d["fr_filter"] - d["fr_argmax"]
    matched = MaxProbabilityFilter(building_class=dirichlet.building_class, window=dirichlet.window)
    if len(tb) == 0 or extra >= len(tb):
        matched.threshold = math.inf  # nothing to keep at that rejection count: reject all
    else:
        matched.threshold_for_false_rejection(tb, extra / len(tb))
    m = _scores_from_groups(matched, tb, fp, d)
    naive_scores = segmentation_scores(cm_naive)
    out: dict[str, Any] = {
        "naive_miou": naive_scores["miou"],
        "naive_building_iou": naive_scores["iou_building"],
        "dirichlet_fp_removed": d["fp_removed"],
        "dirichlet_extra_false_rejections": d["extra_false_rejections"],
        "maxprob_fp_removed_same_rejections": m["fp_removed"],
        "maxprob_extra_false_rejections_same": m["extra_false_rejections"],
        "filter_winner": filter_winner(d, m),
        "filter_fp_argmax": d["fp_argmax"],
        "filter_building_pixels": d["n_building"],
        "dirichlet_threshold_log_density": float(dirichlet.threshold),
        "maxprob_threshold_same_rejections": float(matched.threshold),
    }
    if maxprob is not None:
        c = _scores_from_groups(maxprob, tb, fp, d)
        out["maxprob_fp_removed_calibrated"] = c["fp_removed"]
        out["maxprob_extra_false_rejections_calibrated"] = c["extra_false_rejections"]
    return out


def _scores_from_groups(
    filt: MaxProbabilityFilter, tb: np.ndarray, fp: np.ndarray, ref: Mapping[str, Any]
) -> dict[str, Any]:
    """:func:`~training.metrics.building_filter_scores` of ``filt`` over the argmax-building
    pixels (``tb``: true building, ``fp``: not building), the argmax counts taken from ``ref``."""
    from training.metrics import building_filter_scores

    keep_tb = (
        filt.filter(tb, np.full(len(tb), filt.building_class)) if len(tb) else np.zeros(0, bool)
    )
    keep_fp = (
        filt.filter(fp, np.full(len(fp), filt.building_class)) if len(fp) else np.zeros(0, bool)
    )
    n_fn = ref["fr_argmax"]  # true building the argmax missed
    pred = np.concatenate([np.ones(len(tb) + len(fp), bool), np.zeros(n_fn, bool)])
    keep = np.concatenate([keep_tb, keep_fp, np.zeros(n_fn, bool)])
    truth = np.concatenate([np.ones(len(tb), bool), np.zeros(len(fp), bool), np.ones(n_fn, bool)])
    return building_filter_scores(
        torch.from_numpy(pred), torch.from_numpy(keep), torch.from_numpy(truth)
    )


__all__ = [
    "MIN_PUBLISHED_FRAMES",
    "MIN_PUBLISHED_SIZE_HW",
    "TARGETS",
    "EvalConfig",
    "EvalResult",
    "ModelRecord",
    "PanelFrame",
    "Predictor",
    "check_targets",
    "evaluate",
    "heldout_dataset",
    "heldout_indices",
    "load_filters",
    "load_predictor",
    "model_record",
    "untrained_reasons",
]
