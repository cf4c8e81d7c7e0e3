"""``geoseg infer``: segment images (and predict normals) with a checkpoint or an ONNX file.

Without ``--model`` it uses the joint labels + normals network for real photographs
(:func:`geoseg.pretrained.real_photo_network`: ``street``, trained on real labelled frames, when
installed, else the shipped ``normals_real``); ``--model normals`` picks the synthetic city's,
``--model PATH`` any other. Grey images (monochrome cameras) are read as three equal channels.

For each input image ``NAME.ext`` it writes to ``--out``:

* ``NAME_classes.png``: class ids (uint8, one channel, :data:`geoseg.classes.CLASS_NAMES`
  order: 0 road ... 7 terrain), the file to compute with;
* ``NAME_labels.png``: the class ids coloured with :data:`geoseg.classes.PALETTE`;
* ``NAME_overlay.png``: those colours blended over the image (``--alpha``);
* when the model predicts normals: ``NAME_normals.npy`` (``(3, H, W)`` float32 unit vectors in
  the camera frame, x right, y down, z forward; NaN where invalid: the pixels labelled sky)
  and ``NAME_normals.png`` (RGB = ``(n + 1) / 2 * 255``; black where invalid);
* with ``--probabilities``: ``NAME_probabilities.npy`` (``(8, H, W)`` float16 class
  probabilities).

``legend.json`` (class ids, names and colours, and the normal-colour code) and
``legend.png`` (the class colours and the normal-colour sphere, the key to the pictures) sit
beside them.
Inputs from several folders keep their folders below the inputs' common folder (``a/x.png``
and ``b/x.png`` give ``OUT/a/x_*`` and ``OUT/b/x_*``), so no result overwrites another; two
inputs that would still write the same names (``x.png`` and ``x.jpg``) are refused before any
work.

An unreadable input does not stop the batch: every other image is processed, then the command
lists every input it could not process and exits with status 2. When none of the inputs exists,
it says so before writing anything.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path

logger = logging.getLogger(__name__)

PRODUCER = "infer"
SUFFIXES = (
    "_classes.png",
    "_labels.png",
    "_overlay.png",
    "_normals.png",
    "_normals.npy",
    "_probabilities.npy",
)
LEGEND = "legend.json"
LEGEND_PICTURE = "legend.png"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", type=Path, help="input images (PNG, JPEG, ...)")
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        help="model: .onnx file, torch checkpoint or the name of shipped weights (street, "
        "normals_real, normals, seg, naive, ...; default: the labels + normals network for real "
        "photographs, street when installed, else normals_real)",
    )
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument(
        "--device", default="cpu", choices=["cpu", "cuda"], help="device (checkpoint or ONNX)"
    )
    parser.add_argument(
        "--alpha", type=float, default=0.5, help="overlay opacity of the label colours"
    )
    parser.add_argument(
        "--probabilities",
        action="store_true",
        help="also write the class probabilities (NAME_probabilities.npy, (8, H, W) float16)",
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
    return bool(files) and all(p.name.endswith(SUFFIXES) or p.name == LEGEND for p in files)


def legend() -> dict:
    """What the output files' values and colours mean (written as ``legend.json``)."""
    from geoseg.classes import CLASS_NAMES, PALETTE

    return {
        "classes": [
            {"id": i, "name": name, "rgb": PALETTE[i].tolist()}
            for i, name in enumerate(CLASS_NAMES)
        ],
        "normals": "unit vectors in the camera frame (x right, y down, z forward); PNG colour "
        "= (n + 1) / 2 * 255 per axis (red x, green y, blue z): a surface facing the camera "
        "(normal -z) is olive (128, 128, 0), the road (normal up, -y) purple (128, 0, 128), a "
        "wall on the right facing left (-x) teal (0, 128, 128); black = invalid (sky)",
    }


def masked_normals(normals, labels):
    """Normals ``(3, H, W)`` with NaN where ``labels`` ``(H, W)`` is sky (no surface)."""
    import numpy as np

    from geoseg.classes import SKY

    out = np.asarray(normals, dtype=np.float32).copy()
    out[:, np.asarray(labels) == SKY] = np.nan
    return out


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

    from geoseg.atomic import atomic_imwrite, atomic_output, atomic_write
    from geoseg.classes import colorize
    from geoseg.errors import GeosegError
    from geoseg.export import available_providers
    from geoseg.infer import Segmenter, normals_to_rgb
    from geoseg.legends import class_legend, normal_key
    from geoseg.output_dir import prepare_output_dir, record_outputs
    from geoseg.pretrained import path_or_shipped, real_photo_network

    if not 0.0 <= args.alpha <= 1.0:
        raise GeosegError(f"--alpha: expected a value in [0, 1], got {args.alpha}")
    stems = output_stems(list(args.images))
    if not any(path.is_file() for path in stems):
        shown = ", ".join(str(path) for path in list(stems)[:3])
        raise GeosegError(
            f"none of the {len(stems)} input(s) exists ({shown}{', ...' if len(stems) > 3 else ''})"
            ": nothing was written"
        )
    args.model = path_or_shipped(args.model or real_photo_network(), "model.onnx")
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
    record_outputs(
        out,
        [LEGEND, LEGEND_PICTURE]
        + [stem + suffix for stem in stems.values() for suffix in SUFFIXES],
    )
    atomic_write(out / LEGEND, json.dumps(legend(), indent=1) + "\n")
    key = np.concatenate([class_legend(), normal_key()], axis=1)
    atomic_imwrite(out / LEGEND_PICTURE, cv2.cvtColor(key, cv2.COLOR_RGB2BGR))

    failed: list[str] = []
    written_any = False
    for image_path, stem in stems.items():
        # a missing file is named here: cv2.imread would print its own raw warning first
        bgr = cv2.imread(str(image_path), cv2.IMREAD_COLOR) if image_path.is_file() else None
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
        labels = result.labels[0].astype(np.uint8)
        colours = colorize(labels)
        overlay = (args.alpha * colours + (1.0 - args.alpha) * rgb).round().astype(np.uint8)
        images = {"labels": colours, "overlay": overlay}
        arrays = {}
        if result.normals is not None:
            normals = masked_normals(result.normals[0], labels)
            picture = normals_to_rgb(np.nan_to_num(normals, nan=0.0))
            picture[np.isnan(normals[0])] = 0
            images["normals"] = picture
            arrays["normals"] = normals
        if args.probabilities:
            arrays["probabilities"] = result.probabilities[0].astype(np.float16)
        (out / stem).parent.mkdir(parents=True, exist_ok=True)
        atomic_imwrite(out / f"{stem}_classes.png", labels)
        for kind, picture in images.items():
            atomic_imwrite(out / f"{stem}_{kind}.png", cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
        for kind, array in arrays.items():
            with atomic_output(out / f"{stem}_{kind}.npy", "wb") as f:
                np.save(f, array)
        written = ["classes", *images, *(f"{k}.npy" for k in arrays)]
        written_any = True
        print(f"{image_path}: {'/'.join(written)} → {out / Path(stem).parent}")
    if failed:
        others = "the others were written" if written_any else f"only the legend is in {out}"
        raise GeosegError(
            f"{len(failed)} of {len(stems)} input(s) could not be processed ({others}): "
            + "; ".join(failed)
        )
    return 0
