"""``geoseg infer``: segment images (and predict normals) with a checkpoint or an ONNX file.

Without ``--model`` it uses the shipped joint labels + normals network (:mod:`geoseg.pretrained`).

For each input image ``NAME.ext`` it writes to ``--out``: ``NAME_labels.png`` (colour label map),
``NAME_overlay.png`` (labels blended over the image) and, when the model predicts normals,
``NAME_normals.png`` (RGB = ``(n + 1) / 2 * 255``, camera frame).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

logger = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", type=Path, help="input images (PNG, JPEG, ...)")
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        help="model: .onnx file or torch checkpoint (default: the shipped labels + normals "
        "network, geoseg/weights/normals/model.onnx)",
    )
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument(
        "--device", default="cpu", choices=["cpu", "cuda"], help="device (checkpoint or ONNX)"
    )
    parser.add_argument(
        "--alpha", type=float, default=0.5, help="overlay opacity of the label colours"
    )


def run(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from geoseg.classes import colorize
    from geoseg.errors import GeosegError
    from geoseg.export import available_providers
    from geoseg.infer import Segmenter, normals_to_rgb

    if not 0.0 <= args.alpha <= 1.0:
        raise GeosegError(f"--alpha: expected a value in [0, 1], got {args.alpha}")
    if args.model is None:
        from geoseg.pretrained import pretrained_file

        args.model = pretrained_file("normals", "model.onnx")
    if str(args.model).lower().endswith(".onnx"):
        segmenter = Segmenter.from_onnx(args.model, providers=available_providers(args.device))
    else:
        segmenter = Segmenter.from_checkpoint(args.model, device=args.device)
    args.out.mkdir(parents=True, exist_ok=True)

    def write(path: Path, rgb: np.ndarray) -> None:
        if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise GeosegError(f"{path}: could not write the image")

    for image_path in args.images:
        bgr = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise GeosegError(f"{image_path}: missing or unreadable image")
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        result = segmenter(rgb)
        colours = colorize(result.labels[0])
        overlay = (args.alpha * colours + (1.0 - args.alpha) * rgb).round().astype(np.uint8)
        stem = args.out / image_path.stem
        write(stem.with_name(stem.name + "_labels.png"), colours)
        write(stem.with_name(stem.name + "_overlay.png"), overlay)
        written = ["labels", "overlay"]
        if result.normals is not None:
            write(stem.with_name(stem.name + "_normals.png"), normals_to_rgb(result.normals[0]))
            written.append("normals")
        print(f"{image_path}: {'/'.join(written)} → {args.out}")
    return 0
