"""Accuracy of the trained segmentation side on held-out synthetic cities.

Evaluates, on one render of each report city (``bench/splits.py``'s ``SEG_REPORT_CITIES``:
cities no network was trained or selected on) under every condition including one never
trained on (:mod:`training.evaluate_seg`):

- ENet labels (``--seg``): mIoU over the 8 classes (target >= 0.80), building IoU (>= 0.90);
- the joint network's normals (``--normals``) on building pixels: median angular error
  (<= 10 degrees), share within 11.25 degrees (>= 60 %), mean error, 22.5/30 degree shares;
- the naive CNN + Dirichlet filter (``--naive``, ``--dirichlet``, thesis §4.2.4.1): building
  false positives removed (>= 70 %) for extra false rejections (<= 15 %), beside the
  max-probability threshold adding the same false rejections (which wins is printed).

Each figure is the mean over the renders, its sample standard deviation beside it as
``<key>_std`` (counts such as ``frames`` and pixels are summed instead), every render's own
figures under ``per_render`` (keyed by the city's seed), so that each figure comes with its
spread over cities rather than one city's luck. Targets are judged on the means.

Prints a Markdown table (each figure's mean ± std beside its target, then the figures of each
render), writes ``accuracy_seg.json`` (figure → number, the training minutes of each model from
its run's records and, for a fine-tuned one, the weights it started from
(``init_checkpoint_<kind>``; the 45-min budget judges from-scratch runs only), ``per_render``,
and the provenance keys of ``bench/provenance.py``) and two PNG panels of the first render
(``accuracy_seg_fig4_20.png``: RGB | labels | normals | ground truth; ``accuracy_seg_fig4_8.png``:
argmax building | after the filter | ground truth) into ``--out``.

Defaults point at the shipped weights, ``geoseg/weights/{seg,normals,naive,dirichlet}`` (run
directories as ``geoseg train`` writes them); ``--seg none`` (etc.) skips a part. Untrained,
random or tiny-config models, a smoke-sized evaluation (< 320x240 or < 16 frames a render) or
a city that trained, validated or tuned a network are refused for ``bench/results`` unless
``--allow-untrained``, so that no smoke run passes for a figure; the JSON then lists why under
``untrained``.

Usage::

    python bench/accuracy_seg.py         # shipped weights, 5 report cities x 48 frames, 320x240
    python bench/accuracy_seg.py --seg runs/seg --normals runs/normals \\
        --naive runs/naive --dirichlet runs/dirichlet --cities 1001,1002 --cache-dir ~/.cache/geoseg
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shlex
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

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
from splits import SEG_REPORT_CITIES, SEG_TUNING_CITY  # noqa: E402

#: per-render figures copied, not averaged: the same in every render
SAME = ("eval_width", "eval_height", "dirichlet_threshold_log_density")
#: per-render strings the summary builds itself (:func:`mean_and_spread`)
STRINGS = ("eval_seeds", "conditions", "filter_winner")


def split_line(cities: tuple[int, ...], frames: int) -> str:
    """The ``split`` of a run over ``cities`` (``bench/provenance.py``)."""
    seeds = ", ".join(str(c) for c in cities)
    if cities == SEG_REPORT_CITIES:
        what = (
            f"report: one render of each of the held-out synthetic cities {seeds} "
            "(bench/splits.py's SEG_REPORT_CITIES), on which no network was trained or selected"
        )
    elif set(cities) <= set(SEG_REPORT_CITIES):
        what = f"report subset: cities {seeds} of bench/splits.py's SEG_REPORT_CITIES"
    else:
        what = f"not report data: cities {seeds}, not all in bench/splits.py's SEG_REPORT_CITIES"
    return f"{what}; {frames} frames a render over every condition (`sun_low` never trained on)"


def tuned_cities(cities: tuple[int, ...]) -> list[str]:
    """Why some of ``cities`` cannot back a published figure (empty: none can be faulted)."""
    from geoseg.data.synthetic import TRAIN_SEEDS, VAL_SEEDS

    seen = {SEG_TUNING_CITY: "recipes were chosen on", **{s: "validates" for s in VAL_SEEDS}}
    seen.update({s: "trains the networks" for s in TRAIN_SEEDS})
    return [f"city {c} {seen[c]} (bench/splits.py)" for c in cities if c in seen]


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


def parse_cities(text: str) -> tuple[int, ...]:
    """``"1001,1002"`` → ``(1001, 1002)`` (distinct seeds, in the given order)."""
    try:
        cities = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--cities: expected comma-separated world seeds, got {text!r}"
        ) from None
    if not cities or len(set(cities)) != len(cities):
        raise argparse.ArgumentTypeError(f"--cities: expected distinct seeds, got {text!r}")
    return cities


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
    parser.add_argument("--frames", type=int, default=48, help="frames a render (default 48)")
    parser.add_argument(
        "--cities",
        type=parse_cities,
        default=SEG_REPORT_CITIES,
        help="comma-separated world seeds, one render each (default: bench/splits.py's "
        f"SEG_REPORT_CITIES, {','.join(map(str, SEG_REPORT_CITIES))})",
    )
    parser.add_argument("--size", type=parse_size, default=(240, 320), help="WxH (default 320x240)")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="output directory")
    parser.add_argument("--cache-dir", type=Path, default=None, help="frame cache directory")
    parser.add_argument("--batch-size", type=int, default=2)
    parser.add_argument(
        "--panel-frames", type=int, default=4, help="frames in the PNG panels (first render)"
    )
    parser.add_argument("--device", default="cpu", help="torch device of .pt models")
    parser.add_argument(
        "--allow-untrained",
        action="store_true",
        help="write into bench/results even for untrained models or a smoke-sized run",
    )
    parser.add_argument("--no-progress", action="store_true")
    return parser


def _fmt(value: Any, percent: bool = False, std: Any = None) -> str:
    """A figure, ``± std`` after it when the std is a number."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, str):
        return value
    spread = isinstance(std, int | float) and math.isfinite(std)
    if percent:
        return f"{100 * value:.1f} ± {100 * std:.1f} %" if spread else f"{100 * value:.1f} %"
    return f"{value:.3f} ± {std:.3f}" if spread else f"{value:.3f}"


def mean_and_spread(per_render: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The summary of the renders' figures (the module docstring).

    Args:
        per_render: city seed → that render's figures (:attr:`training.evaluate_seg.EvalResult.figures`).

    Returns:
        Flat figures in the first render's key order: a float figure's mean with ``<key>_std``
        (sample standard deviation, 0 for one render; NaN where a render's is undefined), an
        integer count's sum, :data:`SAME` keys copied, the cities as ``eval_seeds``, the
        conditions' frame counts summed, ``filter_winner`` judged on the means with
        ``filter_winner_renders`` (winner → renders won).
    """
    from training.dirichlet_fit import filter_winner

    renders = list(per_render.values())
    out: dict[str, Any] = {}
    for key, first in renders[0].items():
        values = [r.get(key) for r in renders]
        if key in SAME or key in STRINGS:
            out[key] = first
        elif all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            out[key] = sum(values)
        elif all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
            arr = np.asarray(values, dtype=float)
            out[key] = float(arr.mean())
            out[f"{key}_std"] = float(arr.std(ddof=1)) if arr.size > 1 else 0.0
    out["eval_seeds"] = ",".join(per_render)
    counts: Counter[str] = Counter()
    for r in renders:
        counts.update({c: int(n) for c, n in (p.split(":") for p in r["conditions"].split(","))})
    out["conditions"] = ",".join(f"{c}:{n}" for c, n in sorted(counts.items()))
    if "filter_winner" in out:

        def scores(removed: str, rejected: str) -> dict[str, Any]:
            return {"fp_removed": out[removed], "extra_false_rejections": out[rejected]}

        out["filter_winner"] = filter_winner(
            scores("dirichlet_fp_removed", "dirichlet_extra_false_rejections"),
            scores("maxprob_fp_removed_same_rejections", "maxprob_extra_false_rejections_same"),
        )
        won = Counter(r["filter_winner"] for r in renders)
        out["filter_winner_renders"] = ",".join(f"{w}:{n}" for w, n in sorted(won.items()))
    return out


#: the columns of :func:`per_render_table`: (heading, key, percent)
PER_RENDER_COLUMNS = (
    ("mIoU", "miou", False),
    ("building IoU", "building_iou", False),
    ("normals median (deg)", "normals_building_median_deg", False),
    ("Dirichlet FP removed", "dirichlet_fp_removed", True),
    ("extra false rejections", "dirichlet_extra_false_rejections", True),
)


def per_render_table(per_render: dict[str, dict[str, Any]]) -> str:
    """The headline figures of each render, one row a city."""
    cols = [c for c in PER_RENDER_COLUMNS if any(c[1] in r for r in per_render.values())]
    lines = ["| city | " + " | ".join(c[0] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for city, r in per_render.items():
        cells = [_fmt(r.get(key), pct) for _, key, pct in cols]
        lines.append(f"| {city} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown_table(figures: dict[str, Any]) -> str:
    """Each figure (mean ± std where the std is there) beside its issue-4 target."""
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
            f"| {label} | {_fmt(figures[key], pct, figures.get(f'{key}_std'))} | {target} | "
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
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
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
    reasons = ev.untrained_reasons(records, cfg) + tuned_cities(args.cities)
    if reasons and _is_results_dir(args.out) and not args.allow_untrained:
        print(
            "refusing to write figures into bench/results: these are not trained models, not "
            "a full evaluation or not report cities:\n  - "
            + "\n  - ".join(reasons)
            + "\n(--allow-untrained writes anyway, marked as such; --out DIR writes elsewhere)",
            file=sys.stderr,
        )
        return 3

    meta = provenance(
        split_line(args.cities, args.frames),
        command=" ".join(["python", "bench/accuracy_seg.py", *map(shlex.quote, argv)]),
    )
    t0 = time.perf_counter()
    per_render: dict[str, dict[str, Any]] = {}
    seconds: dict[str, float] = {}
    panels: list[Any] = []
    try:
        models: dict[str, Any] = {}
        for kind in ("seg", "normals", "naive"):
            if kind in paths:
                models[kind] = ev.load_predictor(paths[kind], device=args.device)
        dirichlet = maxprob = None
        if "dirichlet" in paths:
            dirichlet, maxprob = ev.load_filters(paths["dirichlet"])
        for n, city in enumerate(args.cities):
            t_city = time.perf_counter()
            city_cfg = dataclasses.replace(
                cfg,
                synth={"test": {"seeds": [city]}},
                panel_frames=cfg.panel_frames if n == 0 else 0,  # the panels show one render
            )
            result = ev.evaluate(
                city_cfg,
                seg=models.get("seg"),
                normals=models.get("normals"),
                naive=models.get("naive"),
                dirichlet=dirichlet,
                maxprob=maxprob,
            )
            per_render[str(city)] = dict(result.figures)
            seconds[str(city)] = round(time.perf_counter() - t_city, 1)
            panels += result.panels
    except GeosegError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    figures: dict[str, Any] = mean_and_spread(per_render)
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
    figures["renders"] = len(per_render)
    figures["frames_per_render"] = args.frames
    for city, secs in seconds.items():
        per_render[city]["eval_seconds"] = secs
    figures["per_render"] = per_render
    figures.update(meta)
    figures["machine"] += f", {_machine()}"

    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    if panels:
        if "seg" in paths or "normals" in paths:
            written.append(figs.labels_normals_figure(panels, args.out / f"{NAME}_fig4_20.png"))
        if "naive" in paths:
            written.append(figs.filter_figure(panels, args.out / f"{NAME}_fig4_8.png"))
    out_json = args.out / f"{NAME}.json"
    tmp = out_json.with_name(f".{out_json.name}.tmp")
    tmp.write_text(json.dumps(_json_safe(figures), indent=1) + "\n")
    os.replace(tmp, out_json)
    written.append(out_json)

    print(
        f"## Segmentation accuracy, {len(per_render)} held-out cities x {args.frames} frames "
        f"({figures['conditions']}): mean ± std\n"
    )
    print(markdown_table(figures))
    print("\n### Each render\n\n" + per_render_table(per_render))
    if "filter_winner" in figures:
        print(
            f"\nAt the same extra false rejections, {figures['filter_winner']} removes more "
            f"building false positives on the means (renders won: "
            f"{figures['filter_winner_renders']})."
        )
    unrecorded = [k for k in KINDS if k in records and records[k].train_minutes is None]
    if unrecorded:
        print(f"\nnote: no training wall time recorded for: {', '.join(unrecorded)}")
    if reasons:
        print(
            "\n**Not a published figure** (untrained, smoke run or tuning city): "
            + "; ".join(reasons)
        )
    print("\nwrote " + ", ".join(str(p) for p in written))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
