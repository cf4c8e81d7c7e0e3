"""Accuracy of the trained segmentation side on a held-out synthetic city.

Evaluates, on frames of the evaluation city (an unseen seed) under every condition including
one never trained on (:mod:`training.evaluate_seg`):

- ENet labels (``--seg``): mIoU over the 8 classes (target >= 0.80), building IoU (>= 0.90);
- the joint network's normals (``--normals``) on building pixels: median angular error
  (<= 10 degrees), share within 11.25 degrees (>= 60 %), mean error, 22.5/30 degree shares;
- the naive CNN + Dirichlet filter (``--naive``, ``--dirichlet``, thesis §4.2.4.1): building
  false positives removed (>= 70 %) for extra false rejections (<= 15 %), beside the
  max-probability threshold adding the same false rejections (which wins is printed).

Prints a Markdown table (each figure beside its target), writes ``accuracy_seg.json`` (flat:
figure → number, the training minutes of each model from its run's records and, for a
fine-tuned one, the weights it started from (``init_checkpoint_<kind>``; the 45-min budget
judges from-scratch runs only), and the provenance keys of ``bench/provenance.py``) and two PNG
panels
(``accuracy_seg_fig4_20.png``: RGB | labels | normals | ground truth; ``accuracy_seg_fig4_8.png``:
argmax building | after the filter | ground truth) into ``--out``.

Defaults point at the shipped weights, ``geoseg/weights/{seg,normals,naive,dirichlet}`` (run
directories as ``geoseg train`` writes them); ``--seg none`` (etc.) skips a part. Untrained,
random or tiny-config models, or a smoke-sized evaluation (< 320x240 or < 16 frames), are
refused for ``bench/results`` unless ``--allow-untrained``, so that no smoke run passes for a
figure; the JSON then lists why under ``untrained``.

Usage::

    python bench/accuracy_seg.py                       # shipped weights, 48 frames, 320x240
    python bench/accuracy_seg.py --seg runs/seg --normals runs/normals \\
        --naive runs/naive --dirichlet runs/dirichlet --frames 48 --cache-dir ~/.cache/geoseg
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = ROOT / "bench" / "results"
WEIGHTS = ROOT / "geoseg" / "weights"
KINDS = ("seg", "normals", "naive", "dirichlet")
NAME = "accuracy_seg"
TRAIN_BUDGET_MIN = 45  # CPU minutes per model trained from scratch (not for fine-tunes)

if str(ROOT) not in sys.path:  # `python bench/accuracy_seg.py` from a checkout
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402

SPLIT = (
    "report: the held-out synthetic city (world seed 1000, every condition; `sun_low` never "
    "trained on), on which no network was trained"
)


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` → ``(H, W)``."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--size: expected WxH such as 320x240, got {text!r}"
        ) from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"--size: expected positive sizes, got {text!r}")
    return h, w


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for kind in KINDS:
        parser.add_argument(
            f"--{kind}",
            default=str(WEIGHTS / kind),
            help=f"{kind} run directory or file ('none' skips it; default: {WEIGHTS / kind})",
        )
    # 48 frames (8 per condition), the published figures' count: 24 flattered some networks by
    # ~0.01 of mIoU against 48 and ~0.03 against 96
    parser.add_argument("--frames", type=int, default=48, help="held-out frames (default 48)")
    parser.add_argument("--size", type=parse_size, default=(240, 320), help="WxH (default 320x240)")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="output directory")
    parser.add_argument("--cache-dir", type=Path, default=None, help="frame cache directory")
    parser.add_argument("--batch-size", type=int, default=2)
    parser.add_argument("--panel-frames", type=int, default=4, help="frames in the PNG panels")
    parser.add_argument("--device", default="cpu", help="torch device of .pt models")
    parser.add_argument(
        "--allow-untrained",
        action="store_true",
        help="write into bench/results even for untrained models or a smoke-sized run",
    )
    parser.add_argument("--no-progress", action="store_true")
    return parser


def _fmt(value: Any, percent: bool = False) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, str):
        return value
    return f"{100 * value:.1f} %" if percent else f"{value:.3f}"


def markdown_table(figures: dict[str, Any]) -> str:
    """Each figure beside its issue-4 target."""
    from training.evaluate_seg import check_targets

    met = check_targets(figures)
    mark = {True: "yes", False: "**no**", None: "n/a"}
    rows = [
        ("mIoU (8 classes)", "miou", ">= 0.80", False),
        ("building IoU", "building_iou", ">= 0.90", False),
        ("mIoU, held-out condition only", "miou_heldout_condition", "", False),
        ("normals, building: median error (deg)", "normals_building_median_deg", "<= 10", False),
        ("normals, building: within 11.25 deg", "normals_building_within_11_25", ">= 60 %", True),
        ("normals, building: mean error (deg)", "normals_building_mean_deg", "", False),
        ("normals, building: within 22.5 deg", "normals_building_within_22_5", "", True),
        ("normals, building: within 30 deg", "normals_building_within_30", "", True),
        ("Dirichlet: building FP removed", "dirichlet_fp_removed", ">= 70 %", True),
        (
            "Dirichlet: extra false rejections",
            "dirichlet_extra_false_rejections",
            "<= 15 %",
            True,
        ),
        (
            "max-probability, same rejections: FP removed",
            "maxprob_fp_removed_same_rejections",
            "(baseline)",
            True,
        ),
        ("max-probability, own threshold: FP removed", "maxprob_fp_removed_calibrated", "", True),
        ("filter winner", "filter_winner", "", False),
    ]
    lines = ["| figure | value | target | met |", "|---|---|---|---|"]
    for label, key, target, pct in rows:
        if key not in figures:
            continue
        lines.append(
            f"| {label} | {_fmt(figures[key], pct)} | {target} | "
            f"{mark[met[key]] if key in met else ''} |"
        )
    for kind in KINDS:
        key = f"train_minutes_{kind}"
        if key in figures:
            minutes = figures[key]
            init = figures.get(f"init_checkpoint_{kind}")
            if init is not None:  # the budget is the from-scratch recipes'
                target, ok = f"(fine-tuned from {init})", ""
            else:
                target = f"<= {TRAIN_BUDGET_MIN}"
                ok = mark[None] if minutes is None else mark[minutes <= TRAIN_BUDGET_MIN]
            lines.append(
                f"| training wall time, {kind} (min) | {_fmt(minutes)} | {target} | {ok} |"
            )
    return "\n".join(lines)


def _machine() -> str:
    """What :func:`provenance.machine` does not say: torch's version, the load at the end."""
    import torch

    return f"torch {torch.__version__}, load {os.getloadavg()[0]:.1f} at the end"


def _is_results_dir(out: Path) -> bool:
    return out.resolve() == RESULTS_DIR.resolve()


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    import logging

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from geoseg.errors import GeosegError
    from training import evaluate_seg as ev
    from training import figures as figs

    paths = {k: getattr(args, k) for k in KINDS}
    paths = {k: Path(v) for k, v in paths.items() if str(v).lower() != "none"}
    if not paths:
        print("nothing to evaluate: every model is 'none'", file=sys.stderr)
        return 2
    if ("naive" in paths) != ("dirichlet" in paths):
        print("--naive and --dirichlet go together (or both 'none')", file=sys.stderr)
        return 2
    missing = [f"--{k} {p}" for k, p in paths.items() if not p.exists()]
    if missing:
        shipped = any(p.resolve().is_relative_to(WEIGHTS.resolve()) for p in paths.values())
        hint = (
            f"\nThe shipped weights ({WEIGHTS}) are not there yet: train them with "
            "`geoseg train seg|normals|naive|dirichlet --config configs/<name>.yaml`, then "
            "point the options at the run directories (or pass 'none' to skip a part)."
            if shipped
            else ""
        )
        print("missing models:\n  " + "\n  ".join(missing) + hint, file=sys.stderr)
        return 2

    cfg = ev.EvalConfig(
        frames=args.frames,
        size=args.size,
        cache_dir=args.cache_dir,
        batch_size=args.batch_size,
        panel_frames=args.panel_frames,
        progress=not args.no_progress,
    )
    records = {k: ev.model_record(p, k) for k, p in paths.items()}
    reasons = ev.untrained_reasons(records, cfg)
    if reasons and _is_results_dir(args.out) and not args.allow_untrained:
        print(
            "refusing to write figures into bench/results: these are not trained models or not "
            "a full evaluation:\n  - "
            + "\n  - ".join(reasons)
            + "\n(--allow-untrained writes anyway, marked as such; --out DIR writes elsewhere)",
            file=sys.stderr,
        )
        return 3

    meta = provenance(
        SPLIT, command=" ".join(["python", "bench/accuracy_seg.py", *map(shlex.quote, argv)])
    )
    t0 = time.perf_counter()
    try:
        models: dict[str, Any] = {}
        for kind in ("seg", "normals", "naive"):
            if kind in paths:
                models[kind] = ev.load_predictor(paths[kind], device=args.device)
        dirichlet = maxprob = None
        if "dirichlet" in paths:
            dirichlet, maxprob = ev.load_filters(paths["dirichlet"])
        result = ev.evaluate(
            cfg,
            seg=models.get("seg"),
            normals=models.get("normals"),
            naive=models.get("naive"),
            dirichlet=dirichlet,
            maxprob=maxprob,
        )
    except GeosegError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    figures: dict[str, Any] = dict(result.figures)
    figures["eval_seconds"] = round(time.perf_counter() - t0, 1)
    for kind in KINDS:
        if kind in records:
            minutes = records[kind].train_minutes
            figures[f"train_minutes_{kind}"] = None if minutes is None else round(minutes, 2)
            if records[kind].init_checkpoint is not None:
                figures[f"init_checkpoint_{kind}"] = records[kind].init_checkpoint
    for kind, p in paths.items():
        figures[f"model_{kind}"] = str(p)
    if reasons:
        figures["untrained"] = "; ".join(reasons)
    figures.update(meta)
    figures["machine"] += f", {_machine()}"

    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    if result.panels:
        if "seg" in paths or "normals" in paths:
            written.append(
                figs.labels_normals_figure(result.panels, args.out / f"{NAME}_fig4_20.png")
            )
        if "naive" in paths:
            written.append(figs.filter_figure(result.panels, args.out / f"{NAME}_fig4_8.png"))
    out_json = args.out / f"{NAME}.json"
    tmp = out_json.with_name(f".{out_json.name}.tmp")
    tmp.write_text(json.dumps({k: _json_safe(v) for k, v in figures.items()}, indent=1) + "\n")
    os.replace(tmp, out_json)
    written.append(out_json)

    print(f"## Segmentation accuracy, held-out city ({figures['conditions']})\n")
    print(markdown_table(figures))
    if "filter_winner" in figures:
        print(
            f"\nAt the same extra false rejections, {figures['filter_winner']} removes more "
            "building false positives."
        )
    unrecorded = [k for k in KINDS if k in records and records[k].train_minutes is None]
    if unrecorded:
        print(f"\nnote: no training wall time recorded for: {', '.join(unrecorded)}")
    if reasons:
        print("\n**Not a published figure** (untrained or smoke run): " + "; ".join(reasons))
    print("\nwrote " + ", ".join(str(p) for p in written))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
