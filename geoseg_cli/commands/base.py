"""``geoseg base build``: an image base for ``geoseg localize`` from a folder of geotagged images.

Example (a rendered drive is one such folder)::

    geoseg render --out out/summer --frames 60 --condition summer_day --rig tram
    geoseg base build out/summer --out out/base
    geoseg localize out/winter/rgb/000010.png --base out/base

``SRC`` is a ``geoseg render`` output, an existing image base, or any folder of images with
``--positions CSV`` (``image, x, y[, z, heading_deg, timestamp]``; see
:mod:`geoseg.reloc.base_build`). The base (images, ``poses.csv``, ``camera.json``) is written to
``--out`` and the base images' embeddings are computed with the shipped networks and cached
there (``--embedding`` as in ``geoseg localize``; ``--no-embed`` skips them).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    p = sub.add_parser("build", help="build an image base from a folder of geotagged images")
    p.add_argument("src", type=Path, metavar="SRC", help="render output, image base or images")
    p.add_argument("--out", type=Path, required=True, help="the image base folder to write")
    p.add_argument(
        "--positions",
        type=Path,
        help="CSV image, x, y[, z, heading_deg, timestamp] (metres, x east, y north) for a "
        "plain folder of images",
    )
    p.add_argument(
        "--camera-height",
        type=float,
        default=1.5,
        help="camera above the positions' z, metres (default 1.5; with --positions)",
    )
    p.add_argument(
        "--embedding",
        choices=["learned", "layer21", "thumbnail"],
        default="learned",
        help="embedding to compute and cache (default: the shipped learned one)",
    )
    p.add_argument("--no-embed", action="store_true", help="write the base only")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="torch device")
    p.add_argument(
        "--overwrite", action="store_true", help="write into a folder of other files (kept)"
    )


def run(args: argparse.Namespace) -> int:
    import math

    from geoseg.errors import GeosegError
    from geoseg.reloc.base_build import build_image_base
    from geoseg.reloc.image_base import load_image_base

    if not math.isfinite(args.camera_height) or args.camera_height < 0:
        raise GeosegError(
            f"--camera-height: expected a finite number >= 0, got {args.camera_height}"
        )
    if args.positions is None and args.camera_height != 1.5:
        raise GeosegError("--camera-height: only with --positions")
    out = build_image_base(
        args.src,
        args.out,
        positions=args.positions,
        camera_height_m=args.camera_height,
        overwrite=args.overwrite,
    )
    base = load_image_base(out)
    print(f"image base {out}: {len(base)} images")
    if not args.no_embed:
        from geoseg.reloc.networks import load_trunk, make_embedder

        trunk = None if args.embedding == "thumbnail" else load_trunk(None, args.device)
        embedder, name, _ = make_embedder(args.embedding, trunk, device=args.device)
        base.embeddings(embedder)  # computed once, cached under BASE/cache/
        print(f"embeddings ({name}) cached in {out / 'cache'}")
    return 0
