"""``geoseg localize``: relocalise query images against a georeferenced image base (§5.1).

A thin command over :class:`geoseg.reloc.localizer.Localizer` (the algorithm, its options and its
outputs are documented there). By default it uses the shipped networks: the learned embedding
(``geoseg/weights/reloc`` on the ``seg`` trunk) for retrieval and the relative-pose head
(``geoseg/weights/relpose``) for the relative poses, their distances and the position.
``--embedding layer21`` gives the raw layer-21 matching of §5.1.1, ``--embedding thumbnail`` a
grey-thumbnail placeholder (tests, no weights); ``--relative-pose essential`` the ORB/SIFT
essential-matrix baseline (intrinsics from ``BASE/camera.json``, else ``--focal``, else an
assumed focal length of ``max(W, H)`` pixels; queries must have the intrinsics' image size).

The base is a folder made by ``geoseg base build`` (or any folder with ``poses.csv``, see
:mod:`geoseg.reloc.image_base`). Query GPS (``--gps``): a CSV with columns ``image, x, y`` (world frame
of the base, metres; ``image`` is the query's file name or the path as given).

Prints a table; ``--out FILE`` writes the same as JSON, atomically; an existing file is replaced
only when an earlier ``geoseg localize`` wrote it (``--overwrite`` replaces any file).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import textwrap
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    _add_inputs(parser)
    _add_networks(parser)
    _add_ranking(parser)
    _add_matching(parser)
    _add_sequence(parser)
    _add_run(parser)


def _add_inputs(parser: argparse.ArgumentParser) -> None:
    """The queries, the base, the queries' GPS and the number of matches."""
    parser.add_argument("queries", nargs="+", type=Path, metavar="QUERY_IMAGE", help="query images")
    parser.add_argument(
        "--base",
        required=True,
        type=Path,
        help="image base folder (made by geoseg base build: images + poses.csv)",
    )
    parser.add_argument(
        "--gps", type=Path, help="CSV of query positions: image, x, y (world frame, metres)"
    )
    parser.add_argument("--radius", type=float, help="GPS window radius in metres (needs --gps)")
    parser.add_argument("--k", type=int, default=3, help="matches per query (default 3)")


def _add_networks(parser: argparse.ArgumentParser) -> None:
    """The embedding, the relative poses and the networks' weights and input size."""
    parser.add_argument(
        "--embedding",
        choices=["learned", "layer21", "thumbnail"],
        default="learned",
        help="retrieval embedding: the shipped learned one (default), raw layer-21 features, or "
        "a grey-thumbnail placeholder for tests (finds near-duplicates only)",
    )
    parser.add_argument(
        "--relative-pose",
        choices=["head", "essential"],
        default="head",
        help="relative poses: the shipped relative-pose head (default) or the essential-matrix "
        "baseline",
    )
    parser.add_argument(
        "--model",
        type=Path,
        help="trunk giving layer-21 features (.onnx or checkpoint; default: shipped seg)",
    )
    parser.add_argument(
        "--reloc-head", type=Path, help="embedding head checkpoint (default: shipped reloc)"
    )
    parser.add_argument(
        "--relpose-head",
        type=Path,
        help="relative-pose head checkpoint (default: shipped relpose)",
    )
    parser.add_argument(
        "--network-size",
        default="320x240",
        help="resize every image to WxH before the networks (default 320x240, the shipped "
        "networks' size); 'none' keeps the images' size",
    )


def _add_ranking(parser: argparse.ArgumentParser) -> None:
    """Re-ranking and the absolute position."""
    parser.add_argument(
        "--gps-sigma",
        type=float,
        help="GPS noise per axis in metres: re-rank by the predicted distance fused with the "
        "fix's distance to each match (needs --gps and a distance head); with --sequence, the "
        "route filter's Gaussian GPS likelihood",
    )
    parser.add_argument(
        "--distance-rel-sigma",
        type=float,
        default=None,
        help="relative error of the head's predicted distance, for --gps-sigma (default 0.3)",
    )
    parser.add_argument(
        "--appearance-weight",
        type=float,
        help="re-rank by log(distance) + this x the embedding distance (default 0.5 with "
        "--reloc-head, chosen on the validation city; 0 otherwise: distance only)",
    )
    parser.add_argument(
        "--no-rerank",
        action="store_true",
        help="keep the appearance order even when the relative-pose head predicts distances",
    )
    parser.add_argument(
        "--position-k",
        type=int,
        help="matches used for the absolute position, best first (default: all --k)",
    )
    parser.add_argument(
        "--structure",
        action="store_true",
        help="place each query on the base's points, triangulated from neighbouring base images "
        "(PnP; cached under BASE/cache/): centimetres where enough points match, else the "
        "relative poses' position; needs the base's camera.json, and queries from that camera",
    )
    parser.add_argument(
        "--min-agreeing-rays",
        type=int,
        default=2,
        help="ranged rays that must agree for the position to come from them; otherwise the "
        "best match's position (default 2; 1: always the rays' fit)",
    )


def _add_matching(parser: argparse.ArgumentParser) -> None:
    """Options of the raw-feature embedding and of the essential-matrix baseline."""
    parser.add_argument(
        "--pool",
        type=int,
        nargs=2,
        metavar=("H", "W"),
        help="average-pool layer-21 features to H x W before matching (default: full map)",
    )
    parser.add_argument(
        "--features",
        choices=["orb", "sift"],
        default="orb",
        help="keypoints of the essential-matrix baseline (default orb)",
    )
    parser.add_argument(
        "--focal", type=float, help="focal length in pixels when the base has no camera.json"
    )


def _add_sequence(parser: argparse.ArgumentParser) -> None:
    """The queries as one drive (the route filter)."""
    parser.add_argument(
        "--sequence",
        choices=["filter", "smooth"],
        help="the queries are one drive in this order: rank by the route filter's posterior "
        "(causal 'filter' or whole-drive 'smooth')",
    )
    parser.add_argument(
        "--step-m",
        type=float,
        help="with --sequence: metres driven between consecutive queries (default: the base's "
        "median spacing)",
    )
    parser.add_argument(
        "--appearance-scale",
        type=float,
        help="with --sequence: tau of the appearance likelihood exp(-d / tau) (default: 0.29 x "
        "the median query-base distance, chosen for the shipped embedding head on the "
        "validation city)",
    )


def _add_run(parser: argparse.ArgumentParser) -> None:
    """Device, cache and output."""
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="torch device")
    parser.add_argument(
        "--no-cache", action="store_true", help="do not read/write cached embeddings"
    )
    parser.add_argument("--out", type=Path, help="write the results as JSON to this file")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out file that geoseg localize did not write",
    )


# ============================================================================ inputs


def _read_query_gps(path: Path, queries: list[Path]) -> list[tuple[float, float]]:
    from geoseg.errors import GeosegError

    if not path.is_file():
        raise GeosegError(f"--gps: {path}: no such file")
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in (reader.fieldnames or [])]
            reader.fieldnames = header
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise GeosegError(f"--gps: {path}: unreadable ({err})") from None
    missing = [c for c in ("image", "x", "y") if c not in header]
    if missing:
        raise GeosegError(f"--gps: {path}: missing column(s) {missing}; expected image, x, y")
    table: dict[str, tuple[float, float]] = {}
    for i, row in enumerate(rows):
        try:
            xy = (float(row["x"]), float(row["y"]))
        except (TypeError, ValueError):
            raise GeosegError(
                f"--gps: {path} row {i + 2}: x, y are not numbers ({row.get('x')!r}, "
                f"{row.get('y')!r})"
            ) from None
        if not all(math.isfinite(v) for v in xy):
            raise GeosegError(f"--gps: {path} row {i + 2}: x, y are not finite")
        name = (row.get("image") or "").strip()
        if name in table:
            raise GeosegError(f"--gps: {path} row {i + 2}: image {name!r} is listed twice")
        table[name] = xy
    out = []
    for q in queries:
        for key in (str(q), q.as_posix(), q.name):
            if key in table:
                out.append(table[key])
                break
        else:
            raise GeosegError(
                f"--gps: query {q} has no row in {path}; the GPS window (--radius) needs a "
                "position for every query"
            )
    return out


def _is_localize_output(path: Path) -> bool:
    """True when ``path`` is a JSON result an earlier ``geoseg localize`` wrote."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(doc, dict) and {"base", "queries", "relative_pose_method"} <= set(doc)


# ============================================================================ output


def _clean(x: Any) -> Any:
    """NumPy -> JSON-ready Python, NaN/inf -> None."""
    import numpy as np

    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, np.generic):
        return _clean(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _fmt_vec(v) -> str:
    if v is None:
        return "-"
    return "(" + ", ".join(f"{c:+.2f}" for c in v) + ")"


def _print_table(result: dict[str, Any]) -> None:
    print(
        f"base {result['base']} ({result['base_size']} images), embedding "
        f"{result['embedding']}, relative pose {result['relative_pose_method']}"
        + (f", GPS window {result['gps_window_m']} m" if result["gps_window_m"] else "")
    )
    header = f"{'query':<24} {'rank':>4}  {'base image':<24} {'appearance':>14}  relative pose"
    print(header)
    print("-" * len(header))
    legend = (
        "rank: the order used (by the predicted distance, nearest first, when the head predicts "
        "one); appearance: embedding distance (lower = more alike) and its own rank; 'm away': "
        "the predicted distance to that base camera. position: 'ranged rays' = each match's "
        "predicted direction and distance, fitted robustly (n/k: the matches that agree); "
        "'best match' = they did not agree, the best match's camera position; 'on the base's "
        "points' (--structure) = PnP on the points the matches see"
    )
    print(textwrap.fill(legend, width=len(header) + 20))
    for q in result["queries"]:
        name = Path(q["image"]).name
        if not q["matches"]:
            print(f"{name[:24]:<24} {'-':>4}  {'(no candidate)':<24}")
        for m in q["matches"]:
            rp = m["relative_pose"]
            if rp["ok"]:
                pose = f"rot {rp['rotation_deg']:5.1f} deg, dir {_fmt_vec(rp['t_dir_ab'])}"
                if rp.get("distance_m") is not None:
                    pose += f", {rp['distance_m']:.1f} m away"
            else:
                pose = f"failed: {rp['reason']}"
            if m.get("sequence_probability") is not None:
                pose = f"p {m['sequence_probability']:.3f}, {pose}"
            seen = f"{m['distance']:.4g} (#{m.get('appearance_rank', m['rank'])})"
            print(
                f"{name[:24]:<24} {m['rank']:>4}  {Path(m['image']).name[:24]:<24} "
                f"{seen:>14}  {pose}"
            )
            name = ""
        pos = q["position"]
        if pos["degenerate"]:
            print(f"{'':<24} position: degenerate ({pos['reason']})")
        else:
            x, y, z = pos["xyz"]
            if pos["method"] == "structure":
                how = f"on the base's points: {pos['n_inliers']}/{pos['n_matches']} PnP inliers"
            else:
                how = f"{pos['n_inliers']}/{pos['n_rays']} {pos['method']}"
            print(f"{'':<24} position: x {x:.2f}  y {y:.2f}  z {z:.2f} m ({how})")


# ============================================================================ run


def _parse_size(text: str) -> tuple[int, int] | None:
    from geoseg.errors import GeosegError

    if text.lower() == "none":
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise GeosegError(f"--network-size: expected WxH or none, got {text!r}") from None
    if w < 8 or h < 8:
        raise GeosegError(f"--network-size: expected sides >= 8, got {text!r}")
    return w, h


def _config(args: argparse.Namespace):
    """The :class:`LocalizerConfig` of the arguments, with the errors naming the flags."""
    from geoseg.errors import GeosegError, check_positive
    from geoseg.reloc.localizer import LocalizerConfig

    if isinstance(args.k, bool) or args.k < 1:
        raise GeosegError(f"--k: expected an int >= 1, got {args.k}")
    gps_likelihood = args.sequence is not None and args.gps_sigma is not None
    if (args.radius is None) != (args.gps is None) and not (gps_likelihood and args.gps):
        raise GeosegError(
            "--gps and --radius: the GPS window needs both (or neither; with --sequence, "
            "--gps and --gps-sigma weigh the fixes without a window)"
        )
    if args.radius is not None:
        check_positive("--radius", args.radius)
    if args.distance_rel_sigma is not None:
        if args.gps_sigma is None or args.sequence is not None:
            raise GeosegError(
                "--distance-rel-sigma: only with --gps-sigma, to fuse a distance head's "
                "distances with the GPS (not with --sequence)"
            )
        check_positive("--distance-rel-sigma", args.distance_rel_sigma)
    if args.gps_sigma is not None:
        if args.gps is None:
            raise GeosegError("--gps-sigma: needs --gps (the query positions)")
        check_positive("--gps-sigma", args.gps_sigma)
    weight = args.appearance_weight
    if weight is None:
        weight = 0.5 if args.embedding == "learned" else 0.0
    else:
        check_positive("--appearance-weight", weight, strict=False)
    if args.position_k is not None and (isinstance(args.position_k, bool) or args.position_k < 1):
        raise GeosegError(f"--position-k: expected an int >= 1, got {args.position_k}")
    if args.pool is not None and (args.embedding != "layer21" or min(args.pool) < 1):
        raise GeosegError("--pool: needs --embedding layer21 and two sizes >= 1")
    if args.sequence is None and (args.step_m is not None or args.appearance_scale is not None):
        raise GeosegError("--step-m/--appearance-scale: only with --sequence")
    if args.sequence is not None and args.appearance_weight is not None:
        raise GeosegError(
            "--appearance-weight: weighs the distance re-ranking, which --sequence replaces"
        )
    if args.step_m is not None:
        check_positive("--step-m", args.step_m, strict=False)
    if args.appearance_scale is not None:
        check_positive("--appearance-scale", args.appearance_scale)
    if args.focal is not None:
        check_positive("--focal", args.focal)
        if args.relative_pose != "essential":
            raise GeosegError("--focal: only with --relative-pose essential")
    for flag, value, needs in (
        ("--model", args.model, args.embedding != "thumbnail" or args.relative_pose == "head"),
        ("--reloc-head", args.reloc_head, args.embedding == "learned"),
        ("--relpose-head", args.relpose_head, args.relative_pose == "head"),
    ):
        if value is not None and not needs:
            raise GeosegError(f"{flag}: not used with these --embedding/--relative-pose choices")
    return LocalizerConfig(
        k=args.k,
        radius_m=args.radius,
        gps_sigma_m=args.gps_sigma,
        distance_rel_sigma=0.3 if args.distance_rel_sigma is None else args.distance_rel_sigma,
        appearance_weight=weight,
        rerank=not args.no_rerank,
        position_k=args.position_k,
        min_agreeing_rays=args.min_agreeing_rays,
        sequence=args.sequence,
        step_m=args.step_m,
        appearance_scale=args.appearance_scale,
    )


def run(args: argparse.Namespace) -> int:
    from geoseg.errors import GeosegError
    from geoseg.reloc.image_base import load_image_base, read_rgb
    from geoseg.reloc.localizer import Localizer

    config = _config(args)
    network_size = _parse_size(args.network_size)
    if args.out is not None:
        from geoseg.output_dir import prepare_output_file

        prepare_output_file(args.out, overwrite=args.overwrite, owned=_is_localize_output)
    base = load_image_base(args.base)
    queries: list[Path] = list(args.queries)
    gps = _read_query_gps(args.gps, queries) if args.gps is not None else None
    images = [read_rgb(q) for q in queries]
    try:
        localizer = Localizer.from_base(
            base,
            embedding=args.embedding,
            relative_pose=args.relative_pose,
            trunk=args.model,
            reloc_head=args.reloc_head,
            relpose_head=args.relpose_head,
            network_size=network_size,
            pool=None if args.pool is None else tuple(args.pool),
            features=args.features,
            focal=args.focal,
            device=args.device,
            cache=not args.no_cache,
            config=config,
            structure=args.structure,
        )
    except GeosegError as err:
        msg = str(err)
        for name, flag in (
            ("reloc_head:", "--reloc-head:"),
            ("relpose_head:", "--relpose-head:"),
            ("focal:", "--focal:"),
        ):
            msg = msg.replace(name, flag, 1) if msg.startswith(name) else msg
        raise GeosegError(msg) from None
    if (
        args.gps_sigma is not None
        and args.sequence is None
        and args.relative_pose == "head"
        and not _predicts_distance(localizer)
    ):
        raise GeosegError("--gps-sigma: needs a --relpose-head that predicts distances")
    if args.gps_sigma is not None and args.sequence is None and args.relative_pose != "head":
        raise GeosegError("--gps-sigma: needs a --relpose-head that predicts distances")
    results = localizer.localize(images, gps=gps, names=[str(q) for q in queries])
    result = _clean(
        {
            "base": str(args.base),
            "base_size": len(base),
            "k": args.k,
            "gps_window_m": args.radius,
            "sequence": args.sequence,
            "embedding": localizer.embedding_name,
            "relative_pose_method": localizer.relative_pose_name,
            "intrinsics": getattr(localizer.relative_pose, "k_source", None),
            "queries": [r.to_dict() for r in results],
        }
    )
    _print_table(result)
    if args.out is not None:
        from geoseg.atomic import atomic_write, write_error

        try:
            atomic_write(args.out, json.dumps(result, indent=2) + "\n")
        except OSError as err:
            raise write_error(args.out, err, what="--out") from None
        print(f"results written to {args.out}")
    return 0


def _predicts_distance(localizer) -> bool:
    head = getattr(localizer.relative_pose, "head", None)
    return bool(getattr(head, "predict_distance", False))
