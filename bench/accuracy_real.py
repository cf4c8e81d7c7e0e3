"""Accuracy on real street images: CamVid's validation split, 7 classes mapped to geoseg's.

Measures, on the 101 CamVid val frames (``geoseg.data.camvid``: terrain has no CamVid
counterpart, so the mean IoU covers road, sidewalk, building, vegetation, vehicle, object, sky),
at 320x240 and at the native 480x360:

- ``zero_shot_*``: the shipped synthetic-only ``seg`` weights (ONNX, as served), without and
  with the Reinhard colour transfer onto the training set's statistics
  (``*_colour_transfer``; :mod:`geoseg.colour_transfer`, statistics from the model card), and
  with its variant that shifts the colour means only (``*_colour_transfer_means``).
  Targets: ``zero_shot_miou`` >= 0.55, ``zero_shot_building_iou`` >= 0.70.
- ``finetuned_*``: ENet fine-tuned from the shipped weights on CamVid train
  (``configs/seg_camvid.yaml``: a fixed number of epochs, see ``finetune_*``), beside
  ``scratch_*``: the same recipe and budget from a random initialisation; target
  ``finetuned_miou`` >= 0.72. ``finetuned_minus_scratch_miou`` is what the synthetic
  pretraining brings.

Per-class IoU, pixel accuracy and milliseconds per image (network only; the colour transfer's
own cost separately) for each. A panel of val frames (RGB | truth | zero-shot | fine-tuned |
normals of the shipped joint network, or of ``--normals``) goes to ``accuracy_real_panel.png``;
CamVid has no normals, so ``normals_building_level``, ``normals_building_facing_street`` and
``normals_road_level`` say how plausible that network's normals are by the labels
(:func:`normals_plausibility`). With ``--model`` a naive CNN and ``--dirichlet`` its filter,
``dirichlet_fp_removed`` / ``dirichlet_extra_false_rejections`` (and ``maxprob_*`` for the
max-probability baseline beside it) score the filter on the CamVid building predictions
(:func:`filter_figures`).
Published context, not the same protocol: ENet reports 51.3 % class-average IoU over CamVid's
11 classes on its test split (Paszke et al. 2016).

``--split train`` measures a synthetic-only ``--model`` on CamVid's train split instead
(``accuracy_real_<tag>_train.json``): weights that never trained on CamVid can be compared and
chosen there, leaving val to measure the one chosen.

The fine-tuning runs are stages (``<runs>/from_shipped``, ``<runs>/from_scratch``): evaluated
when they exist, trained first only with ``--full`` (each is ``geoseg train seg --config
configs/seg_camvid.yaml``, minutes to an hour on a CPU).

Usage::

    python bench/accuracy_real.py                       # zero-shot + existing fine-tuning runs
    python bench/accuracy_real.py --full                # also trains the missing runs
    python bench/accuracy_real.py --camvid /data/camvid --runs runs/accuracy_real
    python bench/accuracy_real.py --model runs/seg_realism --tag realism   # another model
    python bench/accuracy_real.py --model geoseg/weights/seg_real --tag seg_real --normals normals_real
    python bench/accuracy_real.py --model geoseg/weights/naive_real --tag naive_real \
        --dirichlet dirichlet_real --normals normals_real
    python bench/accuracy_real.py --model runs/candidate --tag candidate --split train
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
NAME = "accuracy_real"
DEFAULT_CAMVID = Path(os.environ.get("GEOSEG_CAMVID", "/work/shared/data/camvid"))
FINETUNE_CONFIG = ROOT / "configs" / "seg_camvid.yaml"
SIZES = {"": (240, 320), "_native": None}  # key suffix -> (H, W) or None = as stored
TARGETS = {"zero_shot_miou": 0.55, "zero_shot_building_iou": 0.70, "finetuned_miou": 0.72}
PANEL_FRAMES = 4
MEANS = "_colour_transfer_means"  # the colour transfer shifting the means only

if str(ROOT) not in sys.path:  # `python bench/accuracy_real.py` from a checkout
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--camvid", type=Path, default=DEFAULT_CAMVID, help="CamVid folder")
    parser.add_argument(
        "--runs", type=Path, default=ROOT / "runs" / NAME, help="fine-tuning run folders"
    )
    parser.add_argument("--full", action="store_true", help="train missing fine-tuning runs")
    parser.add_argument("--frames", type=int, default=0, help="val frames (0 = all 101)")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="output directory")
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        help="zero-shot figures of this synthetic-only model instead of the shipped seg "
        "(model.pt, model.onnx or a run folder); no fine-tuning; writes "
        f"{NAME}_<tag>.json and a panel beside the shipped weights' predictions",
    )
    parser.add_argument("--tag", default="model", help="output name suffix with --model")
    parser.add_argument(
        "--split",
        choices=("val", "train"),
        default="val",
        help="CamVid split measured (default val); train only with --model, to choose among "
        "synthetic-only models without looking at val",
    )
    parser.add_argument(
        "--normals",
        default="normals",
        help="the joint network whose normals the panel shows (shipped name or path; "
        "e.g. normals_real beside --model seg_real)",
    )
    parser.add_argument(
        "--dirichlet",
        default=None,
        help="with --model (a naive CNN): also score this false-positive filter folder or "
        "shipped name (e.g. dirichlet_real) on its CamVid building pixels",
    )
    return parser


def load_segmenter(path: Path) -> Any:
    """A :class:`~geoseg.infer.Segmenter` from a model.onnx, a model.pt or a run folder."""
    from geoseg.infer import Segmenter

    if path.is_dir():
        path = path / "model.pt"
    if path.suffix == ".onnx":
        return Segmenter.from_onnx(path)
    return Segmenter.from_checkpoint(path)


# ----------------------------------------------------------------------------- evaluation
def filter_figures(name: str, model: Any, images: list, labels: list) -> dict[str, Any]:
    """The building false-positive filters of folder or shipped name ``name`` (its Dirichlet
    filter and max-probability baseline) on ``model``'s probabilities at 320x240, as
    ``geoseg train dirichlet`` scores them on its evaluation city
    (:func:`training.dirichlet_fit.score_filters`): the share of the argmax's building false
    positives each removes and the false rejections it adds, as a share of the true building
    pixels; beside them the share of the argmax's building pixels that are false."""
    from geoseg.dirichlet import load_filter
    from geoseg.pretrained import path_or_shipped
    from training.dirichlet_fit import score_filters

    folder = path_or_shipped(name)
    filters = [load_filter(folder / "dirichlet.json"), load_filter(folder / "max_probability.json")]

    def maps():
        for image, truth in zip(images, labels):
            image, truth = resize_pair(image, truth, (240, 320))
            yield model(image).probabilities[0].transpose(1, 2, 0), truth

    figures: dict[str, Any] = {"dirichlet_filter": name}
    scored = score_filters(maps(), filters)
    for key, scores in zip(("dirichlet", "maxprob"), scored):
        figures[f"{key}_fp_removed"] = scores["fp_removed"]
        figures[f"{key}_extra_false_rejections"] = scores["extra_false_rejections"]
    argmax = scored[0]  # the argmax's counts: the same in every filter's scores
    predicted = argmax["fp_argmax"] + argmax["n_building"] - argmax["fr_argmax"]
    figures["building_fp_argmax_share"] = argmax["fp_argmax"] / max(predicted, 1)
    return figures


def load_frames(
    root: Path, limit: int, split: str = "val"
) -> tuple[list[Any], list[Any], tuple[int, ...]]:
    """``split``'s frames as uint8 RGB `(H, W, 3)` and geoseg labels `(H, W)`, and the labelled
    classes."""
    from geoseg.data.camvid import CamVidDataset

    dataset = CamVidDataset(root, split)
    count = len(dataset) if limit <= 0 else min(limit, len(dataset))
    images = [dataset.load_image(i) for i in range(count)]
    labels = [dataset.load_labels(i) for i in range(count)]
    return images, labels, dataset.labelled_classes


def resize_pair(image: Any, labels: Any, size: tuple[int, int] | None) -> tuple[Any, Any]:
    """Image by area averaging, labels by nearest neighbour, to ``size`` = (H, W)."""
    import cv2

    if size is None:
        return image, labels
    h, w = size
    small = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    small_labels = cv2.resize(labels.astype("uint8"), (w, h), interpolation=cv2.INTER_NEAREST)
    return small, small_labels.astype(labels.dtype)


def evaluate(segmenter: Any, images: list, labels: list, classes, size) -> dict[str, float]:
    """mIoU over ``classes``, per-class IoU, pixel accuracy, ms per image (network call)."""
    import torch

    from training.metrics import confusion_matrix, segmentation_scores

    cm = torch.zeros(8, 8, dtype=torch.int64)
    net_s = 0.0
    transfer_s = 0.0
    transfer = segmenter.colour_transfer
    for image, truth in zip(images, labels):
        image, truth = resize_pair(image, truth, size)
        t0 = time.perf_counter()
        if transfer is not None:
            image = transfer(image)
        t1 = time.perf_counter()
        segmenter.colour_transfer = None  # timed apart
        result = segmenter(image)
        segmenter.colour_transfer = transfer
        net_s += time.perf_counter() - t1
        transfer_s += t1 - t0
        cm += confusion_matrix(
            torch.from_numpy(result.labels[0].astype("int64")), torch.from_numpy(truth)
        )
    scores = segmentation_scores(cm, classes=classes)
    scores["ms_per_image"] = 1000.0 * net_s / len(images)
    if transfer is not None:
        scores["transfer_ms_per_image"] = 1000.0 * transfer_s / len(images)
    return scores


def normals_plausibility(normals_net: Any, images: list, labels: list) -> dict[str, float]:
    """What CamVid's labels say of camera-frame normals (it has no normals): the share of
    building pixels whose normal is within 20 deg of horizontal, of those in the image's outer
    quarters whose normal faces the street (left quarter +x, right quarter -x: facades along a
    street seen from it), and of road pixels within 20 deg of vertical, at 320x240."""
    import numpy as np

    from geoseg.classes import BUILDING, ROAD

    level = np.sin(np.radians(20.0))
    counts = np.zeros(6)  # building level, building; facing, outer building; road level, road
    for image, truth in zip(images, labels):
        image, truth = resize_pair(image, truth, (240, 320))
        nx, ny = normals_net(image).normals[0][:2]  # x right, y down
        building, road = truth == BUILDING, truth == ROAD
        quarter = truth.shape[1] // 4
        left, right = building.copy(), building.copy()
        left[:, quarter:] = False
        right[:, : 3 * quarter] = False
        counts += [
            (np.abs(ny[building]) < level).sum(), building.sum(),
            (nx[left] > 0).sum() + (nx[right] < 0).sum(), left.sum() + right.sum(),
            (np.abs(ny[road]) > np.cos(np.radians(20.0))).sum(), road.sum(),
        ]  # fmt: skip
    return {
        "normals_building_level": counts[0] / counts[1],
        "normals_building_facing_street": counts[2] / counts[3],
        "normals_road_level": counts[4] / counts[5],
    }


def normals_figures(name: str, images: list, labels: list, figures: dict[str, Any]) -> Any:
    """Load the joint network ``name`` (shipped name or path), put its
    :func:`normals_plausibility` into ``figures``; returns the network for the panel.

    Raises:
        SystemExit: the network gives no normals.
    """
    from geoseg.pretrained import path_or_shipped

    net = load_segmenter(path_or_shipped(name, "model.onnx"))
    if net(images[0]).normals is None:
        raise SystemExit(f"--normals {name}: this network gives no normals (a joint one does)")
    figures["normals_model"] = name
    figures.update(normals_plausibility(net, images, labels))
    return net


def finetune(run_dir: Path, camvid: Path, init: str | None) -> Path:
    """Stage: the run in ``run_dir`` (trained with configs/seg_camvid.yaml when missing)."""
    from geoseg.config import load_config
    from training.seg import SegConfig, main

    overrides = [
        f"out_dir={run_dir}",
        f"data.root={camvid}",
        f"init_checkpoint={init if init else 'null'}",
        "export=false",
        "progress=false",
    ]
    cfg = load_config(SegConfig, FINETUNE_CONFIG, overrides=overrides)
    return main(
        cfg,
        command=f"geoseg train seg --config {FINETUNE_CONFIG.name} "
        + " ".join(f"--set {o}" for o in overrides),
    )


def run_facts(run_dir: Path) -> dict[str, float]:
    """Epochs, optimizer steps and wall minutes of a fine-tuning run (from its records)."""
    rows = json.loads((run_dir / "metrics.json").read_text())
    return {
        "epochs": rows[-1]["epoch"],
        "steps": rows[-1]["global_step"],
        "minutes": sum(float(r.get("time_s") or 0.0) for r in rows) / 60.0,
    }


# ----------------------------------------------------------------------------- panel
def write_panel(
    path: Path, images, labels, segmenters: dict[str, Any], normals_net, normals_name: str
) -> None:
    """Rows of val frames: RGB | truth | each segmenter's labels | normals of ``normals_net``."""
    import cv2
    import numpy as np

    from geoseg.classes import colorize
    from geoseg.infer import normals_to_rgb

    picks = np.linspace(0, len(images) - 1, PANEL_FRAMES).round().astype(int)
    rows = []
    for i in picks:
        image, truth = resize_pair(images[i], labels[i], (240, 320))
        tiles = [image, colorize(truth)]
        tiles += [colorize(seg(image).labels[0]) for seg in segmenters.values()]
        normals = normals_net(image).normals
        if normals is not None:
            tiles.append(normals_to_rgb(normals[0]))
        rows.append(np.concatenate(tiles, axis=1))
    panel = np.concatenate(rows, axis=0)
    titles = ["RGB", "truth", *segmenters, f"normals ({normals_name})"]
    header = np.full((28, panel.shape[1], 3), 255, np.uint8)
    for k, title in enumerate(titles):
        cv2.putText(header, title, (320 * k + 6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate([header, panel]), cv2.COLOR_RGB2BGR))


# ----------------------------------------------------------------------------- output
def markdown_table(figures: dict[str, Any]) -> str:
    lines = ["| figure | 320x240 | 480x360 (native) | target |", "|---|---|---|---|"]
    stems = [
        "zero_shot_miou",
        "zero_shot_miou_colour_transfer",
        "zero_shot_building_iou",
        "zero_shot_building_iou_colour_transfer",
        "zero_shot_miou" + MEANS,
        "zero_shot_building_iou" + MEANS,
        "zero_shot_pixel_acc",
        "zero_shot_pixel_acc_colour_transfer",
        "zero_shot_pixel_acc" + MEANS,
        "finetuned_miou",
        "scratch_miou",
        "finetuned_minus_scratch_miou",
        "finetuned_building_iou",
        "zero_shot_ms_per_image",
        "finetuned_ms_per_image",
    ]
    for stem in stems:
        low = figures.get(stem)
        if low is None:
            continue
        native = figures.get(_native_key(stem))
        target = TARGETS.get(stem.partition("_colour_transfer")[0])
        lines.append(
            f"| {stem} | {_fmt(low)} | {_fmt(native)} | {'>= ' + str(target) if target else ''} |"
        )
    return "\n".join(lines)


def _native_key(stem: str) -> str:
    head, sep, tail = stem.partition("_colour_transfer")
    return head + "_native" + sep + tail


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def _machine() -> str:
    """What :func:`provenance.machine` does not say: torch's version, the load at the end."""
    import torch

    return f"torch {torch.__version__}, load {os.getloadavg()[0]:.1f} at the end"


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _put(figures: dict[str, Any], prefix: str, suffix: str, scores: dict[str, float]) -> None:
    """``{prefix}_{metric}{suffix}`` keys; mIoU and building IoU also under the issue's names."""
    for key, value in scores.items():
        figures[f"{prefix}_{key}{suffix}"] = value
    figures[f"{prefix}_building_iou{suffix}"] = scores["iou_building"]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.split != "val" and args.model is None:
        parser.error("--split train: only with --model (the fine-tuning runs train on it)")
    # split: CamVid's split measured ("val": the published one; "train": for choosing among
    # synthetic-only models, never trained on)
    meta = provenance(args.split, command=shlex.join(["python", "bench/accuracy_real.py", *argv]))

    from geoseg.infer import Segmenter, colour_transfer_for
    from geoseg.pretrained import pretrained_file

    images, labels, classes = load_frames(args.camvid, args.frames, args.split)
    figures: dict[str, Any] = {"frames": len(images), "classes": len(classes)}
    seg_onnx = pretrained_file("seg", "model.onnx")
    if args.model is not None:
        return evaluate_model(args, meta, images, labels, classes)
    shipped = Segmenter.from_onnx(seg_onnx)
    transfer = colour_transfer_for(seg_onnx)
    transfer_means = colour_transfer_for(seg_onnx, match_std=False)
    variants = (("", None), ("_colour_transfer", transfer), (MEANS, transfer_means))
    for size_key, size in SIZES.items():
        for ct_key, ct in variants:
            shipped.colour_transfer = ct
            scores = evaluate(shipped, images, labels, classes, size)
            _put(figures, "zero_shot", size_key + ct_key, scores)
    shipped.colour_transfer = None

    tuned: dict[str, Segmenter] = {}
    for prefix, init in (("finetuned", str(pretrained_file("seg").parent)), ("scratch", None)):
        run_dir = args.runs / ("from_shipped" if init else "from_scratch")
        if not (run_dir / "model.pt").is_file():
            if not args.full:
                print(f"{run_dir}: no fine-tuning run (--full trains it); skipped")
                continue
            finetune(run_dir, args.camvid, init)
        tuned[prefix] = Segmenter.from_checkpoint(run_dir / "model.pt")
        for size_key, size in SIZES.items():
            _put(figures, prefix, size_key, evaluate(tuned[prefix], images, labels, classes, size))
        for key, value in run_facts(run_dir).items():
            figures[f"{prefix}_train_{key}"] = value
    for size_key in SIZES:
        a, b = figures.get(f"finetuned_miou{size_key}"), figures.get(f"scratch_miou{size_key}")
        if a is not None and b is not None:
            figures[f"finetuned_minus_scratch_miou{size_key}"] = a - b

    args.out.mkdir(parents=True, exist_ok=True)
    panel_segmenters = {"zero-shot (shipped seg)": shipped}
    if "finetuned" in tuned:
        panel_segmenters["fine-tuned from shipped"] = tuned["finetuned"]
    normals_net = normals_figures(args.normals, images, labels, figures)
    write_panel(
        args.out / f"{NAME}_panel.png", images, labels, panel_segmenters, normals_net, args.normals
    )

    figures.update(meta)
    figures["machine"] += f", {_machine()}"
    print(markdown_table(figures))
    _write_json(args.out / f"{NAME}.json", figures)
    print(f"wrote {args.out / f'{NAME}.json'} and {args.out / f'{NAME}_panel.png'}")
    return 0


def evaluate_model(args, meta: dict[str, str], images, labels, classes) -> int:
    """``--model``: the zero-shot figures (with and without colour transfer, both sizes) of
    another synthetic-only model, and a panel beside the shipped weights."""
    from geoseg.errors import GeosegError
    from geoseg.infer import Segmenter, colour_transfer_for
    from geoseg.pretrained import pretrained_file

    model = load_segmenter(args.model)
    card_path = args.model / "model.pt" if args.model.is_dir() else args.model
    variants = [("", None)]
    try:
        variants += [
            ("_colour_transfer", colour_transfer_for(card_path)),
            (MEANS, colour_transfer_for(card_path, match_std=False)),
        ]
    except GeosegError as err:  # no model card with colour statistics: no transfer figures
        print(f"{args.model}: no colour transfer ({err})")
    figures: dict[str, Any] = {
        "frames": len(images),
        "classes": len(classes),
        "model": str(args.model),
        "split": args.split,
    }
    for size_key, size in SIZES.items():
        for ct_key, ct in variants:
            model.colour_transfer = ct
            _put(
                figures,
                "zero_shot",
                size_key + ct_key,
                evaluate(model, images, labels, classes, size),
            )
    model.colour_transfer = None
    if args.dirichlet is not None:
        figures.update(filter_figures(args.dirichlet, model, images, labels))
    args.out.mkdir(parents=True, exist_ok=True)
    shipped = Segmenter.from_onnx(pretrained_file("seg", "model.onnx"))
    normals_net = normals_figures(args.normals, images, labels, figures)
    name = f"{NAME}_{args.tag}" + ("" if args.split == "val" else f"_{args.split}")
    panel = args.out / f"{name}_panel.png"
    segmenters = {"shipped seg": shipped, str(args.model): model}
    write_panel(panel, images, labels, segmenters, normals_net, args.normals)
    figures.update(meta)
    figures["machine"] += f", {_machine()}"
    print(markdown_table(figures))
    _write_json(args.out / f"{name}.json", figures)
    print(f"wrote {args.out / f'{name}.json'} and {panel}")
    return 0


def _write_json(path: Path, figures: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps({k: _json_safe(v) for k, v in figures.items()}, indent=1) + "\n")
    os.replace(tmp, path)


if __name__ == "__main__":
    raise SystemExit(main())
