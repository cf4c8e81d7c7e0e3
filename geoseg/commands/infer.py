"""``geoseg infer``: segment images (and predict normals) with a checkpoint or an ONNX file.

Without ``--model`` it uses the shipped joint labels + normals network (:mod:`geoseg.pretrained`).

For each input image ``NAME.ext`` it writes to ``--out``: ``NAME_labels.png`` (colour label map),
``NAME_overlay.png`` (labels blended over the image) and, when the model predicts normals,
``NAME_normals.png`` (RGB = ``(n + 1) / 2 * 255``, camera frame). Inputs from several folders
keep their folders below the inputs' common folder (``a/x.png`` and ``b/x.png`` give
``OUT/a/x_*.png`` and ``OUT/b/x_*.png``), so no result overwrites another; two inputs that would
still write the same names (``x.png`` and ``x.jpg``) are refused before any work.

An unreadable input does not stop the batch: every other image is processed, then the command
lists every input it could not process and exits with status 2.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

logger = logging.getLogger(__name__)

PRODUCER = "infer"
SUFFIXES = ("_labels.png", "_overlay.png", "_normals.png")


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
    parser.add_argument(
        "--colour-transfer",
        choices=["off", "image", "sequence"],
        default="off",
        help="map the inputs' colours onto the training images' (Reinhard et al. 2001; the "
        "statistics in the model card beside --model): 'image' each input from its own "
        "statistics, 'sequence' all inputs from their pooled statistics (default: off)",
    )
    parser.add_argument(
        "--colour-means-only",
        action="store_true",
        help="with --colour-transfer: shift the colour means only (keep the inputs' contrast "
        "and saturation) instead of matching means and standard deviations",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="write into an --out folder that holds files geoseg infer did not write (they "
        "are kept, unless an output of the same name is written)",
    )


def output_stems(images: list[Path]) -> dict[Path, str]:
    """The output name stem of each input, relative to ``--out`` (POSIX).

    Inputs are placed below their common folder: ``a/x.png``, ``b/x.png`` -> ``a/x``, ``b/x``;
    inputs of one folder keep bare stems. The same file given twice is processed once.

    Raises:
        GeosegError: two different inputs would write the same outputs (e.g. ``x.png`` and
            ``x.jpg`` in one folder).
    """
    from geoseg.errors import GeosegError

    unique: dict[Path, Path] = {}
    for image in images:
        unique.setdefault(Path(os.path.abspath(image)), image)
    if len(unique) < len(images):
        logger.warning(
            "%d input(s) given more than once: processed once", len(images) - len(unique)
        )
    parents = [p.parent for p in unique]
    root = Path(os.path.commonpath(parents)) if parents else Path(".")
    stems: dict[Path, str] = {}
    taken: dict[str, Path] = {}
    for absolute, given in unique.items():
        stem = (absolute.parent.relative_to(root) / absolute.stem).as_posix()
        if stem in taken:
            raise GeosegError(
                f"{taken[stem]} and {given} would both write {stem}_labels.png: rename one of "
                "them or run them separately"
            )
        taken[stem] = given
        stems[given] = stem
    return stems


def _earlier_infer(folder: Path) -> bool:
    """True when ``folder`` only holds outputs of an older ``geoseg infer`` (no marker)."""
    files = [p for p in folder.rglob("*") if p.is_file()]
    return bool(files) and all(p.name.endswith(SUFFIXES) for p in files)


def _colour_transfer(args: argparse.Namespace, images: list[Path]):
    """The ``--colour-transfer`` map for the model of ``args`` (sequence: over the readable
    inputs; an unreadable one is reported later, where it is processed)."""
    import cv2

    from geoseg.infer import colour_transfer_for

    sequence = []
    if args.colour_transfer == "sequence":
        for path in images:
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is not None:
                sequence.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    return colour_transfer_for(
        args.model,
        mode=args.colour_transfer,
        sequence=sequence,
        match_std=not args.colour_means_only,
    )


def run(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from geoseg.atomic import atomic_imwrite
    from geoseg.classes import colorize
    from geoseg.errors import GeosegError
    from geoseg.export import available_providers
    from geoseg.infer import Segmenter, normals_to_rgb
    from geoseg.output_dir import prepare_output_dir, record_outputs

    if not 0.0 <= args.alpha <= 1.0:
        raise GeosegError(f"--alpha: expected a value in [0, 1], got {args.alpha}")
    stems = output_stems(list(args.images))
    if args.model is None:
        from geoseg.pretrained import pretrained_file

        args.model = pretrained_file("normals", "model.onnx")
    if str(args.model).lower().endswith(".onnx"):
        segmenter = Segmenter.from_onnx(args.model, providers=available_providers(args.device))
    else:
        segmenter = Segmenter.from_checkpoint(args.model, device=args.device)
    if args.colour_transfer != "off":
        segmenter.colour_transfer = _colour_transfer(args, list(stems))
    out = prepare_output_dir(
        args.out, producer=PRODUCER, overwrite=args.overwrite, adopt=_earlier_infer
    )
    # recorded once, up front (the normals file only exists for a model predicting normals)
    record_outputs(out, [stem + suffix for stem in stems.values() for suffix in SUFFIXES])

    failed: list[str] = []
    for image_path, stem in stems.items():
        bgr = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        if bgr is None:
            reason = "no such file" if not image_path.exists() else "not a readable image"
            failed.append(f"{image_path} ({reason})")
            logger.error("%s: %s; skipped", image_path, reason)
            continue
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        try:
            result = segmenter(rgb)
        except GeosegError as err:
            failed.append(f"{image_path} ({err})")
            logger.error("%s: %s; skipped", image_path, err)
            continue
        colours = colorize(result.labels[0])
        overlay = (args.alpha * colours + (1.0 - args.alpha) * rgb).round().astype(np.uint8)
        images = {"labels": colours, "overlay": overlay}
        if result.normals is not None:
            images["normals"] = normals_to_rgb(result.normals[0])
        names = {kind: f"{stem}_{kind}.png" for kind in images}
        for kind, picture in images.items():
            (out / names[kind]).parent.mkdir(parents=True, exist_ok=True)
            atomic_imwrite(out / names[kind], cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
        print(f"{image_path}: {'/'.join(images)} → {out / Path(stem).parent}")
    if failed:
        raise GeosegError(
            f"{len(failed)} of {len(stems)} input(s) could not be processed (the others were "
            "written): " + "; ".join(failed)
        )
    return 0
