"""Weight averaging of label networks fine-tuned from one ancestor, written as a finished run.

Two fine-tunings of one network (here: the shipped recipe of ``seg_real`` and the same recipe on
cities with parked cars) land near each other in weight space, and a weighted mean of their
weights can keep much of what each was good at (a "model soup": Wortsman et al., "Model soups",
ICML 2022). Every floating-point tensor of the sources' state dicts is averaged with the given
weights, the batch-norm running statistics included: recomputing them on synthetic training
frames instead cost ``seg_real`` 0.02-0.04 of CamVid building IoU (docs/lessons.md).
Integer buffers (batch-norm step counts) come from the heaviest source.

The result is evaluated on the validation set of ``--config`` (a ``geoseg train seg`` config;
its metrics go into the card, as a trained run's best epoch's do) and written as a run folder:
``model.pt``, ``model.onnx`` (when the config's ``export`` is on) and a model card with the
training frames' colour statistics and the sources (files, SHA-256, weights, the commands, epochs
and minutes of the runs they come from, the last two summed as the card's own; a source that is
itself an average keeps its own sources). :mod:`training.ship` ships it.

Usage::

    python -m training.average runs/seg_real_avg runs/seg_real_480b:0.8 \\
        runs/seg_real_480b_narrowmix:0.2 --config configs/seg_real_480.yaml

A source is a run directory (its ``model.pt``, else ``best.pt``, else ``last.pt``) or a weights
file, with ``:WEIGHT`` (default 1); the weights are normalised to sum to one.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shlex
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from geoseg.config import load_config
from geoseg.errors import GeosegError
from geoseg.integrity import file_sha256
from geoseg.models.registry import get_model
from training import common, frame_data
from training import distributed as dd
from training.loop import evaluate
from training.metrics import SegmentationMeter
from training.seg import SegConfig

logger = logging.getLogger(__name__)

MODEL_NAME = "enet"  # the seg trainer's network: what --config's validation set measures


@dataclass(frozen=True)
class Source:
    """One network to average: its weights file and its (unnormalised) weight."""

    path: Path
    weight: float = 1.0


def parse_source(text: str) -> Source:
    """``PATH`` or ``PATH:WEIGHT`` -> :class:`Source`.

    Raises:
        GeosegError: a weight that is not a finite number >= 0.
    """
    path, sep, tail = text.rpartition(":")
    if not sep or "/" in tail:  # no weight given (or a colon inside the path)
        return Source(Path(text))
    try:
        weight = float(tail)
    except ValueError:
        raise GeosegError(f"{text!r}: the weight after ':' must be a number") from None
    if not math.isfinite(weight) or weight < 0:
        raise GeosegError(f"{text!r}: the weight must be a finite number >= 0")
    return Source(Path(path), weight)


def average_states(
    states: Sequence[Mapping[str, torch.Tensor]], weights: Sequence[float]
) -> dict[str, torch.Tensor]:
    """Weighted mean of state dicts of one architecture.

    Args:
        states: ``K`` state dicts with the same tensor names, shapes and dtypes.
        weights: ``K`` finite weights >= 0 with a positive sum (normalised here).

    Returns:
        A state dict: floating-point tensors ``sum_k w_k * states[k] / sum_k w_k`` (computed in
        float64, stored in their own dtype); other tensors those of the heaviest state.

    Raises:
        GeosegError: no states, a weight count that differs, bad weights, or states of
            different architectures (the message names the first differing tensors).
    """
    if not states:
        raise GeosegError("nothing to average: no state dicts")
    if len(weights) != len(states):
        raise GeosegError(f"{len(weights)} weights for {len(states)} state dicts")
    w = [float(x) for x in weights]
    if not all(math.isfinite(x) and x >= 0 for x in w) or sum(w) <= 0:
        raise GeosegError(f"averaging weights must be finite, >= 0, with a positive sum: {w}")
    first = states[0]
    for k, state in enumerate(states[1:], start=1):
        if set(state) != set(first):
            odd = sorted(set(state) ^ set(first))
            raise GeosegError(f"state {k} has other tensors than state 0: {', '.join(odd[:3])}")
        bad = [
            n for n, t in first.items() if (t.shape, t.dtype) != (state[n].shape, state[n].dtype)
        ]
        if bad:
            raise GeosegError(f"state {k} differs from state 0 in shape or dtype: {bad[:3]}")
    total = sum(w)
    heaviest = states[max(range(len(w)), key=w.__getitem__)]
    out: dict[str, torch.Tensor] = {}
    for name, tensor in first.items():
        if tensor.is_floating_point():
            mean = sum(wk / total * s[name].double() for wk, s in zip(w, states, strict=True))
            out[name] = mean.to(tensor.dtype)
        else:
            out[name] = heaviest[name].clone()
    return out


def _describe_source(source: Source, file: Path, checkpoint: Mapping[str, Any]) -> dict[str, Any]:
    entry: dict[str, Any] = {
        "file": str(file),
        "weight": source.weight,
        "sha256": file_sha256(file),
    }
    if checkpoint.get("epoch") is not None:
        entry["epoch"] = int(checkpoint["epoch"])
    card = file.parent / common.CARD_JSON
    if card.is_file():  # the run the weights come from: how long it trained, and how it was made
        run = json.loads(card.read_text())
        entry.update({k: run.get(k) for k in ("epochs", "train_minutes", "command")})
        if run.get("averaged_from"):  # an average of averages keeps its whole ancestry
            entry["averaged_from"] = run["averaged_from"]
    return entry


def average_runs(
    out_dir: str | Path,
    sources: Sequence[Source],
    cfg: SegConfig,
    *,
    command: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Average ``sources`` (ENet label networks of one architecture) into the run ``out_dir``.

    Args:
        out_dir: the new run directory.
        sources: the networks and their weights.
        cfg: the seg config whose validation set measures the result and whose training frames
            give the card's colour statistics.
        command: the command line, for the card.
        overwrite: replace an existing run's results in ``out_dir``.

    Returns:
        ``out_dir``.

    Raises:
        GeosegError: a source that is not an ENet checkpoint, sources of different
            architectures, bad weights, ``out_dir`` holding a run (without ``overwrite``).
    """
    out_dir = Path(out_dir)
    if (out_dir / common.MODEL_FILE).exists() and not overwrite:
        raise GeosegError(f"{out_dir} already holds {common.MODEL_FILE} (pass --overwrite)")
    if len(sources) < 2:
        raise GeosegError(f"averaging needs at least two sources, got {len(sources)}")
    files = [common.resolve_weights_file(s.path) for s in sources]
    loaded = [common.load_state(f, expected_model=MODEL_NAME) for f in files]
    configs = [dict(ckpt.get("model_config") or {}) for _, ckpt in loaded]
    if any(c != configs[0] for c in configs[1:]):
        raise GeosegError(f"the sources' model_config differ: {configs}")
    state = average_states([s for s, _ in loaded], [s.weight for s in sources])

    torch.set_num_threads(dd.cpu_threads_per_process(cfg.cpu_threads, cfg.data.num_workers))
    model = get_model(MODEL_NAME, **configs[0])
    model.load_state_dict(state)
    val_set = frame_data.build_frame_dataset(cfg.data, "val")
    common.prerender_frames(cfg.data, val_set)
    meter = SegmentationMeter(model.num_classes, classes=frame_data.dataset_classes(val_set))
    scores = evaluate(model, common.make_val_loader(cfg, val_set), meter, device="cpu")
    metrics = {f"val_{k}": v for k, v in scores.items()}
    logger.info("averaged %d networks: val_miou %.4f", len(sources), metrics.get("val_miou", 0))

    from training.colour_stats import card_entry

    described = [_describe_source(s, f, c) for s, f, (_, c) in zip(sources, files, loaded)]
    extra: dict[str, Any] = {
        "averaged_from": described,
        **card_entry(cfg.data, frames=common.COLOUR_STAT_FRAMES),
    }
    for key, kind in (("epochs", int), ("train_minutes", int | float)):
        values = [d.get(key) for d in described]
        if all(isinstance(v, kind) for v in values):  # the runs averaged, not their ancestors
            extra[key] = round(sum(values), 3)
    out_dir.mkdir(parents=True, exist_ok=True)
    return common.finalize_run(
        out_dir,
        model,
        kind="average",
        cfg=cfg,
        model_name=MODEL_NAME,
        model_config=configs[0],
        metrics=metrics,
        data_summary=common.describe_data(cfg.data),
        command=command,
        export=cfg.export,
        example_size=cfg.data.size,
        extra_card=extra,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="the averaged run's directory")
    parser.add_argument(
        "sources", nargs="+", metavar="SOURCE[:WEIGHT]", help="run directories or weights files"
    )
    parser.add_argument(
        "--config", required=True, type=Path, help="seg config: validation set, colour statistics"
    )
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a key of --config (repeatable)",
    )  # fmt: skip
    parser.add_argument("--overwrite", action="store_true", help="replace out_dir's results")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    command = "python -m training.average " + shlex.join(sys.argv[1:] if argv is None else argv)
    try:
        sources = [parse_source(s) for s in args.sources]
        cfg = load_config(SegConfig, args.config, overrides=args.overrides)
        out = average_runs(args.out_dir, sources, cfg, command=command, overwrite=args.overwrite)
    except GeosegError as err:
        sys.stderr.write(f"error: {err}\n")
        return 2
    card = json.loads((out / common.CARD_JSON).read_text())
    sys.stdout.write(
        f"wrote {out} (val_miou {card['metrics'].get('val_miou', float('nan')):.4f})\n"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
