"""The joint network for real photographs (``street``): real labels, monochrome cameras, normals.

Measures one joint network (default: the ``street`` run, ``runs/street``, else the installed
``street`` weights; ``--model`` another) and writes ``bench/results/accuracy_real_<tag>.json``:

- ``real_labels_miou``, ``real_labels_building_iou``: CamVid val (101 frames, 7 classes mapped
  to geoseg's, ``geoseg.data.camvid``) at the native 480x360; targets >= 0.75 and >= 0.85.
  Also at 320x240 (``*_320x240``) and per class. CamVid val reports only: the recipe's choices
  (the epoch kept) were made on the sequence of CamVid train held out for them
  (``training.camvid_holdout``: 0001TP), whose figures are ``select_*``.
- ``grayscale_miou``, ``grayscale_miou_ratio``: the same frames turned grey (BT.601 luma) and
  given to the network as single-channel images, as a monochrome camera's; target ratio to the
  colour figure >= 0.95.
- ``normals_median_deg_heldout``: median angular error of the normals on building pixels of the
  held-out synthetic city (``training.evaluate_seg``: unseen seed, every condition, the held-out
  one included), beside ``normals_real``'s measured in the same run
  (``normals_real_median_deg_heldout``); target: no worse. ``*_all_median_deg_heldout``: over
  every valid pixel.
- With ``--kitti`` (default: the shared clips when present): the network as the SLAM's bridge
  runs it (``slam_bridge.bridge.builder.network_outputs``, maps checked by ``check_network``) on
  frames of the grayscale KITTI clips, read single-channel; a panel
  ``accuracy_real_<tag>_kitti_panel.png`` (grey | labels | normals) and the share of pixels per
  class (``kitti_share_*``) for a look.

Panel of CamVid val frames: ``accuracy_real_<tag>_panel.png`` (RGB | truth | labels | labels of
the grey frame | normals).

Usage::

    python bench/accuracy_real_street.py                    # runs/street or the installed street
    python bench/accuracy_real_street.py --model runs/other --tag other
    python bench/accuracy_real_street.py --heldout-frames 8 --frames 10   # a smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = ROOT / "bench" / "results"
DEFAULT_CAMVID = Path(os.environ.get("GEOSEG_CAMVID", "/work/shared/data/camvid"))
DEFAULT_KITTI = Path(os.environ.get("GEOSEG_KITTI_CLIPS", "/work/shared/data/kitti_clips"))
DEFAULT_HOLDOUT = ROOT / "runs" / "camvid_holdout"
TARGETS = {
    "real_labels_miou": (">=", 0.75),
    "real_labels_building_iou": (">=", 0.85),
    "grayscale_miou_ratio": (">=", 0.95),
}
PANEL_FRAMES = 4
KITTI_FRAMES = (0, 25, 50)
LUMA = (0.299, 0.587, 0.114)

if str(ROOT) not in sys.path:  # `python bench/accuracy_real_street.py` from a checkout
    sys.path.insert(0, str(ROOT))
if str(ROOT / "bench") not in sys.path:
    sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=None, help="run folder, model.pt or .onnx")
    parser.add_argument("--tag", default="street", help="output name: accuracy_real_<tag>.json")
    parser.add_argument("--camvid", type=Path, default=DEFAULT_CAMVID)
    parser.add_argument(
        "--holdout",
        type=Path,
        default=DEFAULT_HOLDOUT,
        help="training.camvid_holdout folder (its select split is scored too, when present)",
    )
    parser.add_argument("--kitti", type=Path, default=DEFAULT_KITTI, help="KITTI clips folder")
    parser.add_argument("--frames", type=int, default=0, help="CamVid val frames (0 = all)")
    parser.add_argument("--heldout-frames", type=int, default=24, help="held-out city frames")
    parser.add_argument("--reference", default="normals_real", help="normals to compare with")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR)
    return parser


def default_model() -> Path:
    """``runs/street`` when it holds a finished run, else the installed ``street`` weights."""
    from geoseg.pretrained import pretrained_dir

    run = ROOT / "runs" / "street"
    return run if (run / "model.pt").is_file() else pretrained_dir("street")


def to_grey(image: Any) -> Any:
    """`(H, W, 3)` uint8 RGB → `(H, W)` uint8 BT.601 luma (a monochrome camera's frame)."""
    import numpy as np

    luma = image.astype(np.float32) @ np.asarray(LUMA, np.float32)
    return luma.round().clip(0, 255).astype(np.uint8)


def label_figures(segmenter: Any, root: Path, split: str, limit: int) -> dict[str, float]:
    """Colour and grey figures of ``root``'s ``split`` at native size and 320x240."""
    from accuracy_real import evaluate, load_frames

    images, labels, classes = load_frames(root, limit, split)
    grey = [to_grey(im) for im in images]
    out: dict[str, float] = {"frames": len(images)}
    for suffix, size in (("", None), ("_320x240", (240, 320))):
        colour = evaluate(segmenter, images, labels, classes, size)
        mono = evaluate(segmenter, grey, labels, classes, size)
        for key, value in colour.items():
            out[f"{key}{suffix}"] = value
        out[f"grayscale_miou{suffix}"] = mono["miou"]
        out[f"grayscale_building_iou{suffix}"] = mono["iou_building"]
        out[f"grayscale_miou_ratio{suffix}"] = mono["miou"] / colour["miou"]
    return out


def normals_figures(model: Path, reference: str, frames: int) -> dict[str, float]:
    """Building and all-pixel median angular errors on the held-out synthetic city, of
    ``model`` and ``reference`` on the same frames."""
    from geoseg.pretrained import path_or_shipped
    from training.evaluate_seg import EvalConfig, evaluate, load_predictor

    cfg = EvalConfig(frames=frames, size=(240, 320), progress=False)
    out: dict[str, float] = {"heldout_frames": frames}
    for prefix, path in (("normals", model), (f"{reference}", path_or_shipped(reference))):
        figures = evaluate(cfg, normals=load_predictor(path)).figures
        out[f"{prefix}_median_deg_heldout"] = figures["normals_building_median_deg"]
        out[f"{prefix}_mean_deg_heldout"] = figures["normals_building_mean_deg"]
        out[f"{prefix}_within_11_25_heldout"] = figures["normals_building_within_11_25"]
        out[f"{prefix}_all_median_deg_heldout"] = figures["normals_all_median_deg"]
    return out


def _header(titles: list[str], tile_w: int, width: int) -> Any:
    import cv2
    import numpy as np

    header = np.full((28, width, 3), 255, np.uint8)
    for k, title in enumerate(titles):
        cv2.putText(
            header, title, (tile_w * k + 6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1
        )
    return header


def camvid_panel(path: Path, segmenter: Any, root: Path) -> None:
    """Rows of CamVid val frames: RGB | truth | labels | labels of the grey frame | normals."""
    import cv2
    import numpy as np
    from accuracy_real import load_frames, resize_pair

    from geoseg.classes import colorize
    from geoseg.infer import normals_to_rgb

    images, labels, _ = load_frames(root, 0, "val")
    rows = []
    for i in np.linspace(0, len(images) - 1, PANEL_FRAMES).round().astype(int):
        image, truth = resize_pair(images[i], labels[i], (240, 320))
        colour, mono = segmenter(image), segmenter(to_grey(image))
        tiles = [image, colorize(truth), colorize(colour.labels[0]), colorize(mono.labels[0])]
        tiles.append(normals_to_rgb(colour.normals[0]))
        rows.append(np.concatenate(tiles, axis=1))
    panel = np.concatenate(rows, axis=0)
    titles = ["RGB", "truth", "labels", "labels (grey input)", "normals"]
    out = np.concatenate([_header(titles, 320, panel.shape[1]), panel])
    cv2.imwrite(str(path), cv2.cvtColor(out, cv2.COLOR_RGB2BGR))


def kitti_figures(path: Path, model: Path, clips: Path) -> dict[str, float]:
    """The bridge's network on grey KITTI frames read single-channel (``(H, W)`` uint8)."""
    import cv2
    import numpy as np

    from geoseg.classes import CLASS_NAMES, colorize
    from geoseg.infer import normals_to_rgb
    from slam_bridge.bridge.builder import check_network, network_outputs

    out: dict[str, float] = {}
    rows, counts = [], np.zeros(len(CLASS_NAMES))
    for clip in sorted(p for p in clips.iterdir() if (p / "image_0").is_dir()):
        files = sorted((clip / "image_0").glob("*.jpg")) + sorted((clip / "image_0").glob("*.png"))
        first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
        H, W = first.shape[:2]
        size = (round(W * 192 / H), 192)  # (W, H): the clip's aspect ratio, 192 rows
        network = network_outputs("bayes", model, 1, size)
        check_network(network, (W, H), needs_normals=True)  # as build_bridge does
        for index in KITTI_FRAMES:
            grey = cv2.imread(str(files[min(index, len(files) - 1)]), cv2.IMREAD_UNCHANGED)
            if grey.ndim != 2:
                raise SystemExit(f"{clip}: expected single-channel frames, got {grey.shape}")
            probs, normals = network(grey)
            labels = probs.argmax(axis=2)
            counts += np.bincount(labels.ravel(), minlength=len(CLASS_NAMES))
            small = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
            tiles = [np.repeat(small[..., None], 3, axis=2), colorize(labels.astype(np.uint8))]
            tiles.append(normals_to_rgb(normals.transpose(2, 0, 1)))
            rows.append(np.concatenate([cv2.resize(t, (640, 192)) for t in tiles], axis=1))
        out[f"kitti_frames_{clip.name}"] = len(KITTI_FRAMES)
    for k, name in enumerate(CLASS_NAMES):
        out[f"kitti_share_{name}"] = float(counts[k] / counts.sum())
    panel = np.concatenate(rows, axis=0)
    titles = ["grey frame (KITTI image_0)", "labels", "normals"]
    image = np.concatenate([_header(titles, 640, panel.shape[1]), panel])
    cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return out


def _machine() -> str:
    """What :func:`provenance.machine` does not say: library versions, the load at the end."""
    import onnxruntime
    import torch

    return (
        f"torch {torch.__version__}, onnxruntime {onnxruntime.__version__}, load "
        f"{os.getloadavg()[0]:.1f} at the end (a shared machine)"
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    meta = provenance(
        "CamVid val (reported only; selection on CamVid train's held-out 0001TP: select_*); "
        "normals: the held-out synthetic city (training.evaluate_seg test split)",
        command="python bench/accuracy_real_street.py"
        + "".join(f" {shlex.quote(a)}" for a in (argv or sys.argv[1:])),
    )
    import torch
    from accuracy_real import load_segmenter

    torch.set_num_threads(1)
    model = args.model or default_model()
    segmenter = load_segmenter(Path(model))
    figures: dict[str, Any] = {"model": str(model)}
    val = label_figures(segmenter, args.camvid, "val", args.frames)
    figures["real_labels_miou"] = val["miou"]
    figures["real_labels_building_iou"] = val["iou_building"]
    figures["grayscale_miou"] = val["grayscale_miou"]
    figures["grayscale_miou_ratio"] = val["grayscale_miou_ratio"]
    figures.update({f"val_{k}": v for k, v in val.items()})
    if (args.holdout / "select").is_dir():
        sel = label_figures(segmenter, args.holdout, "select", 0)
        figures.update({f"select_{k}": v for k, v in sel.items()})
    figures.update(normals_figures(Path(model), args.reference, args.heldout_frames))
    ref = figures[f"{args.reference}_median_deg_heldout"]
    TARGETS["normals_median_deg_heldout"] = ("<=", ref)
    args.out.mkdir(parents=True, exist_ok=True)
    camvid_panel(args.out / f"accuracy_real_{args.tag}_panel.png", segmenter, args.camvid)
    if args.kitti.is_dir():
        kitti_panel = args.out / f"accuracy_real_{args.tag}_kitti_panel.png"
        figures.update(kitti_figures(kitti_panel, Path(model), args.kitti))
    for key, (op, target) in TARGETS.items():
        value = figures[key]
        figures[f"{key}_met"] = bool(value >= target if op == ">=" else value <= target)
    figures.update(meta)
    figures["machine"] += f", {_machine()}"
    lines = ["| figure | value | target |", "|---|---|---|"]
    for key in (*TARGETS, "grayscale_miou", "val_miou_320x240", "select_miou"):
        if key in figures:
            target = TARGETS.get(key)
            tgt = f"{target[0]} {target[1]:.3f}" if target else ""
            lines.append(f"| {key} | {figures[key]:.3f} | {tgt} |")
    sys.stdout.write("\n".join(lines) + "\n")
    path = args.out / f"accuracy_real_{args.tag}.json"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(figures, indent=1, default=float) + "\n")
    os.replace(tmp, path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
