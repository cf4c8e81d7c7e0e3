"""Fit the Dirichlet false-positive filter on the trained naive CNN (thesis §4.2.2, §4.2.4.1).

Three disjoint sets of frames:

1. **fit** (``fit_frames`` frames of ``fit_split``, the training cities by default): the naive
   CNN runs densely; the softmax vectors of the pixels whose ground truth is building (the
   thesis's ``D_build``, ~2e6 of them; with ``fit_pixels: accepted`` only those the argmax also
   calls building, the population the filter will see) are kept, uniformly subsampled to
   ``max_fit_pixels``, and the :class:`~geoseg.dirichlet.DirichletFilter` is fitted on them
   (seconds). With ``window > 1`` every map is box-averaged first
   (:meth:`~geoseg.dirichlet.DirichletFilter.smooth`), for both filters.
2. **calibration** (the first ``calib_frames`` validation frames, an unseen city): the threshold
   is the one that adds ``false_rejection_rate`` false rejections, as a share of all true
   building pixels, to the argmax's, i.e. rejects that many of the true building pixels the
   argmax calls building
   (:meth:`~geoseg.dirichlet.DirichletFilter.threshold_for_false_rejection`). The baseline
   :class:`~geoseg.dirichlet.MaxProbabilityFilter` is calibrated on the same pixels at the same
   rate.
3. **evaluation** (the next ``eval_frames`` validation frames): both filters are measured with
   :func:`~training.metrics.building_filter_scores`: share of the argmax's building false
   positives removed, and extra false rejections relative to the true building pixels.

Outputs in ``out_dir``: ``dirichlet.json`` (the filter, loadable with
:func:`geoseg.dirichlet.load_filter`), ``max_probability.json`` (the baseline) and
``metrics.json`` (flat: ``dirichlet_fp_removed``, ``dirichlet_extra_false_rejections``,
``maxprob_fp_removed_same_rejections``, ``maxprob_extra_false_rejections``, ``winner``, fit
time...). A finished run (all three files present) is not redone unless ``overwrite``.

Usage::

    geoseg train dirichlet --config configs/dirichlet.yaml --set naive_checkpoint=runs/naive
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Subset
from tqdm.auto import tqdm

from geoseg.atomic import atomic_write
from geoseg.classes import BUILDING, IGNORE_INDEX, NUM_CLASSES
from geoseg.config import check_range, to_dict
from geoseg.dirichlet import DirichletFilter, MaxProbabilityFilter
from geoseg.errors import ConfigError, GeosegError
from geoseg.models.registry import get_model
from geoseg.output_dir import prepare_output_dir, record_outputs
from training import common, frame_data
from training import distributed as dd
from training.config import DataConfig
from training.metrics import building_filter_scores

logger = logging.getLogger(__name__)

FILTER_FILE = "dirichlet.json"
BASELINE_FILE = "max_probability.json"
METRICS_FILE = "metrics.json"


@dataclass
class DirichletConfig:
    """The Dirichlet fitting stage.

    Attributes:
        naive_checkpoint: the trained naive CNN (``model.pt``, a training checkpoint or a naive
            run directory); required.
        out_dir: output directory.
        device: ``auto``, ``cpu``, ``cuda``...
        seed: subsampling seed.
        data: frames (only ``source``, ``size``, ``cache_dir``, ``synth``/``root`` are used).
        fit_split: split of the fitting frames (``train``: the naive CNN's cities).
        fit_frames: frames whose true-building pixels fit ``alpha``.
        max_fit_pixels: subsample the fitting vectors to at most this many (~2e6 in §4.2.2).
        calib_frames: validation frames choosing the thresholds.
        eval_frames: further validation frames measuring both filters.
        false_rejection_rate: the false rejections each filter may add on top of the argmax's,
            as a share of all true building pixels of the calibration frames (the thesis's
            "15 % more false rejections" and the metric of
            :func:`~training.metrics.building_filter_scores`).
        lam: barrier weight of eq. 4.7.
        eps: probability floor before every logarithm (fit and scoring; see
            :mod:`geoseg.dirichlet`).
        temperature: the filter models ``softmax(ln p / T)`` (:class:`DirichletFilter`).
        window: odd box side over which both filters average the probability maps before
            scoring (1 = per pixel, the thesis).
        fit_pixels: ``true_building`` (the thesis's ``D_build``) or ``accepted`` (true building
            pixels the argmax also calls building).
        batch_size: frames per dense forward pass.
        band_rows: rows per band in the dense forward pass (bounds memory).
        progress: tqdm bars.
        overwrite: redo a finished run.
    """

    naive_checkpoint: Path | None = None
    out_dir: Path = Path("runs/dirichlet")
    device: str = "auto"
    seed: int = 0
    data: DataConfig = field(default_factory=DataConfig)
    fit_split: str = "train"
    fit_frames: int = 96
    max_fit_pixels: int = 2_000_000
    calib_frames: int = 24
    eval_frames: int = 24
    false_rejection_rate: float = 0.15
    lam: float = 1.0
    eps: float = 1e-30
    temperature: float = 1.0
    window: int = 1
    fit_pixels: str = "true_building"
    batch_size: int = 2
    band_rows: int | None = 64
    progress: bool = True
    overwrite: bool = False

    def __post_init__(self) -> None:
        if self.fit_split not in ("train", "val"):
            raise ConfigError(f"fit_split: expected train or val, got {self.fit_split!r}")
        for key in ("fit_frames", "calib_frames", "eval_frames", "batch_size", "max_fit_pixels"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{key}: expected >= 1, got {getattr(self, key)}")
        if self.fit_pixels not in ("true_building", "accepted"):
            raise ConfigError(
                f"fit_pixels: expected true_building or accepted, got {self.fit_pixels!r}"
            )
        if isinstance(self.window, bool) or self.window < 1 or self.window % 2 == 0:
            raise ConfigError(f"window: expected an odd int >= 1, got {self.window}")
        if not self.temperature > 0:
            raise ConfigError(f"temperature: expected > 0, got {self.temperature}")
        if self.seed < 0:
            raise ConfigError(f"seed: expected >= 0, got {self.seed}")
        if self.band_rows is not None and self.band_rows < 1:
            raise ConfigError(f"band_rows: expected >= 1 or null, got {self.band_rows}")
        check_range("lam", self.lam, 0.0)
        check_range("eps", self.eps, 0.0, 1.0 / NUM_CLASSES, low_open=True, high_open=True)
        if not 0.0 <= self.false_rejection_rate < 1.0:
            raise ConfigError(
                f"false_rejection_rate: expected a number in [0, 1), got {self.false_rejection_rate}"
            )
        self.out_dir = Path(self.out_dir)
        if self.naive_checkpoint is not None:
            self.naive_checkpoint = Path(self.naive_checkpoint)

    def as_dict(self) -> dict[str, Any]:
        """Plain-data form."""
        return to_dict(self)


CONFIG_CLASS = DirichletConfig


def dense_probabilities(
    model: torch.nn.Module,
    dataset: Any,
    indices: Sequence[int],
    *,
    device: torch.device,
    batch_size: int = 2,
    band_rows: int | None = 64,
    progress: bool = True,
    desc: str = "dense",
) -> Any:
    """Yield ``(probs (B, H, W, C) float32 NumPy, labels (B, H, W) int64 NumPy)`` per batch of
    frames ``indices`` of ``dataset`` (normalised images), from the naive CNN run densely."""
    loader = torch.utils.data.DataLoader(
        Subset(dataset, list(indices)), batch_size=batch_size, shuffle=False
    )
    model.eval().to(device)
    with torch.inference_mode():
        for batch in tqdm(loader, desc=desc, leave=False, disable=not progress):
            log_probs = model.dense(batch["image"].to(device), band_rows=band_rows)
            probs = log_probs.float().exp().permute(0, 2, 3, 1).cpu().numpy()
            yield probs, batch["labels"].numpy()


def _collect_true_building(
    batches: Any, filt: DirichletFilter, *, only_argmax_building: bool = False
) -> np.ndarray:
    """``(N, K)`` vectors, from ``filt.smooth``'s maps, of the true building pixels of
    ``batches`` (only those whose per-pixel argmax is building when asked)."""
    out = []
    for probs, labels in batches:
        mask = labels == BUILDING
        if only_argmax_building:
            mask &= probs.argmax(-1) == BUILDING
        out.append(filt.smooth(probs)[mask].astype(np.float32))
    return np.concatenate(out) if out else np.zeros((0, 8), np.float32)


def main(cfg: DirichletConfig, *, command: str | None = None) -> Path:
    """Fit, calibrate and evaluate the filter as ``cfg`` says; returns ``cfg.out_dir``.

    Raises:
        GeosegError: no ``naive_checkpoint`` or one of another architecture, too few validation
            frames, no building pixel to fit on.
    """
    out = Path(cfg.out_dir)
    outputs = [out / FILTER_FILE, out / BASELINE_FILE, out / METRICS_FILE]
    if dd.is_main_process():  # refuse a folder of other files before any work
        prepare_output_dir(
            out,
            producer="train",
            overwrite=cfg.overwrite,
            option="out_dir",
            adopt=lambda folder: all(p.is_file() for p in outputs),
        )
        record_outputs(out, [p.name for p in outputs])
    if all(p.is_file() for p in outputs) and not cfg.overwrite:
        logger.info("%s: already fitted (overwrite=true redoes it)", out)
        return out
    model = _load_naive(cfg)
    device = dd.resolve_device(cfg.device)
    fit_set = frame_data.build_frame_dataset(cfg.data, cfg.fit_split, augment=False)
    val_set = frame_data.build_frame_dataset(cfg.data, "val", augment=False)
    need = cfg.calib_frames + cfg.eval_frames
    if len(val_set) < need:
        raise GeosegError(
            f"calib_frames + eval_frames = {need} but the validation split has {len(val_set)} "
            "frames (raise data.synth.val.frames)"
        )
    if cfg.fit_split == "val" and len(val_set) < need + cfg.fit_frames:
        raise GeosegError("fit_split=val: the validation split is too short for fit + calib + eval")
    fit_start = need if cfg.fit_split == "val" else 0
    fit_idx = range(fit_start, fit_start + min(cfg.fit_frames, len(fit_set) - fit_start))
    kw = dict(device=device, batch_size=cfg.batch_size, band_rows=cfg.band_rows,
              progress=cfg.progress)  # fmt: skip

    dirichlet, fit_probs, inference_s, fit_s = _fit(cfg, model, fit_set, fit_idx, kw)

    baseline, calib = _calibrate(cfg, model, val_set, kw, dirichlet)

    evaluation = dense_probabilities(
        model, val_set, range(cfg.calib_frames, need), desc="evaluation", **kw
    )
    d_scores, m_scores = score_filters(evaluation, [dirichlet, baseline])

    metrics = _metrics(
        cfg, command, dirichlet, baseline, d_scores, m_scores, fit_probs, calib, fit_s, inference_s
    )
    if dd.is_main_process():
        dirichlet.save(out / FILTER_FILE)
        baseline.save(out / BASELINE_FILE)
        atomic_write(out / METRICS_FILE, json.dumps(_finite(metrics), indent=1, default=str))
    logger.info(
        "Dirichlet removes %.1f %% of building false positives (+%.1f %% false rejections); "
        "max-probability at the same rate removes %.1f %% (+%.1f %%): %s wins",
        100 * d_scores["fp_removed"],
        100 * d_scores["extra_false_rejections"],
        100 * m_scores["fp_removed"],
        100 * m_scores["extra_false_rejections"],
        metrics["winner"],
    )
    return out


def _load_naive(cfg: DirichletConfig) -> Any:
    """The naive CNN of ``cfg.naive_checkpoint``."""
    if cfg.naive_checkpoint is None:
        raise GeosegError(
            "naive_checkpoint: the dirichlet stage needs the trained naive CNN; set it to a naive "
            "run directory or model file (e.g. --set naive_checkpoint=runs/naive)"
        )
    state, ckpt = common.load_state(
        cfg.naive_checkpoint, expected_model="naive_cnn", option="naive_checkpoint"
    )
    model_config = dict(ckpt.get("model_config") or {})
    model = get_model("naive_cnn", **model_config)
    model.load_state_dict(state)
    return model


def _fit(cfg: DirichletConfig, model: Any, fit_set: Any, fit_idx: range, kw: dict) -> tuple:
    """``(filter, fit pixels (N, K), inference s, fit s)``: the Dirichlet filter fitted on the
    true building pixels of the fit frames."""
    dirichlet = DirichletFilter(
        lam=cfg.lam, eps=cfg.eps, temperature=cfg.temperature, window=cfg.window
    )
    t0 = time.perf_counter()
    fit_probs = _collect_true_building(
        dense_probabilities(model, fit_set, fit_idx, desc="fit frames", **kw),
        dirichlet,
        only_argmax_building=cfg.fit_pixels == "accepted",
    )
    inference_s = time.perf_counter() - t0
    if len(fit_probs) < 2:
        which = "accepted " if cfg.fit_pixels == "accepted" else ""
        raise GeosegError(
            f"fit frames: only {len(fit_probs)} {which}true building pixels; need more (raise "
            "fit_frames" + (", or fit_pixels: true_building for a weak network)" if which else ")")
        )
    if len(fit_probs) > cfg.max_fit_pixels:
        rng = np.random.default_rng(cfg.seed)
        fit_probs = fit_probs[np.sort(rng.choice(len(fit_probs), cfg.max_fit_pixels, False))]
    t0 = time.perf_counter()
    dirichlet.fit(fit_probs.astype(np.float64))
    fit_s = time.perf_counter() - t0
    logger.info("Dirichlet fitted on %d pixels in %.2f s", len(fit_probs), fit_s)
    return dirichlet, fit_probs, inference_s, fit_s


def _calibrate(
    cfg: DirichletConfig, model: Any, val_set: Any, kw: dict, dirichlet: DirichletFilter
) -> tuple:
    """``(baseline, calibration pixels)``: both filters' thresholds set on the calibration
    frames for ``cfg.false_rejection_rate``."""
    calib_all, calib_accepted = [], []
    for probs, labels in dense_probabilities(
        model, val_set, range(cfg.calib_frames), desc="calibration", **kw
    ):
        truth = labels == BUILDING
        smoothed = dirichlet.smooth(probs)
        calib_all.append(smoothed[truth])
        calib_accepted.append(smoothed[truth & (probs.argmax(-1) == BUILDING)])
    calib_all, calib = np.concatenate(calib_all), np.concatenate(calib_accepted)
    if len(calib_all) == 0:
        raise GeosegError("calibration frames: no true building pixel; raise calib_frames")
    if len(calib) == 0:
        logger.warning(
            "calibration frames: no true building pixel is predicted building (an untrained "
            "network?); calibrating on all %d true building pixels",
            len(calib_all),
        )
        calib = calib_all
    baseline = MaxProbabilityFilter(window=cfg.window).fit()
    # the rate is relative to all true building pixels; the filters only see the accepted ones
    rate = min(cfg.false_rejection_rate * len(calib_all) / len(calib), 0.999)
    dirichlet.threshold_for_false_rejection(calib, rate)
    baseline.threshold_for_false_rejection(calib, rate)
    return baseline, calib


def _metrics(
    cfg: DirichletConfig,
    command: str | None,
    dirichlet: DirichletFilter,
    baseline: MaxProbabilityFilter,
    d_scores: dict[str, Any],
    m_scores: dict[str, Any],
    fit_probs: np.ndarray,
    calib: np.ndarray,
    fit_s: float,
    inference_s: float,
) -> dict[str, Any]:
    """The run's ``metrics.json``."""
    metrics: dict[str, Any] = {
        "dirichlet_fp_removed": d_scores["fp_removed"],
        "dirichlet_extra_false_rejections": d_scores["extra_false_rejections"],
        "maxprob_fp_removed_same_rejections": m_scores["fp_removed"],
        "maxprob_extra_false_rejections": m_scores["extra_false_rejections"],
        "winner": filter_winner(d_scores, m_scores),
        "false_rejection_rate": cfg.false_rejection_rate,
        "dirichlet_threshold_log_density": dirichlet.threshold,
        "maxprob_threshold": baseline.threshold,
        "alpha": dirichlet.alpha.tolist(),
        "n_fit_pixels": int(len(fit_probs)),
        "n_calib_pixels": int(len(calib)),
        "fit_seconds": fit_s,
        "fit_inference_seconds": inference_s,
        "eval_counts_dirichlet": {
            k: d_scores[k] for k in d_scores if k.startswith(("fp_", "fr_", "n_"))
        },
        "eval_counts_maxprob": {
            k: m_scores[k] for k in m_scores if k.startswith(("fp_", "fr_", "n_"))
        },
        "naive_checkpoint": str(cfg.naive_checkpoint),
        "command": command or "python -c 'from training.dirichlet_fit import main; main(cfg)'",
        "config": cfg.as_dict(),
    }
    return metrics


def _finite(value: Any) -> Any:
    """NaN / infinity → None (strict JSON), recursively."""
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def score_filters(maps: Any, filters: Sequence[Any]) -> list[dict[str, Any]]:
    """:func:`~training.metrics.building_filter_scores` of each of ``filters`` (sharing one
    smoothing window) over ``maps``: ``(probs (..., H, W, K), labels (..., H, W))`` pairs, a
    frame or a batch each (ignored pixels left out); one dict per filter, in order."""
    pred_b, true_b, keep = [], [], [[] for _ in filters]
    for probs, labels in maps:
        valid = labels != IGNORE_INDEX
        argmax = probs.argmax(-1)[valid]
        scored = filters[0].smooth(probs)[valid]  # the filters share the window: smooth once
        pred_b.append(argmax == BUILDING)
        true_b.append(labels[valid] == BUILDING)
        for kept, flt in zip(keep, filters):
            kept.append(flt.filter(scored, argmax))
    pred = torch.from_numpy(np.concatenate(pred_b))
    truth = torch.from_numpy(np.concatenate(true_b))
    return [building_filter_scores(pred, torch.from_numpy(np.concatenate(k)), truth) for k in keep]


def filter_winner(d: dict[str, Any], m: dict[str, Any]) -> str:
    """The filter removing more false positives (ties: fewer extra rejections)."""
    a = (d["fp_removed"], -d["extra_false_rejections"])
    b = (m["fp_removed"], -m["extra_false_rejections"])
    if any(isinstance(v, float) and v != v for v in a + b):
        return "undefined"
    return "dirichlet" if a > b else "max_probability" if b > a else "tie"
