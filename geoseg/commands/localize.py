"""``geoseg localize``: relocalise query images against a georeferenced image base (§5.1).

For each query image: the ``k`` nearest base images (optionally only within ``--radius`` metres
of the query's GPS position), the relative pose to each of them (the relative-pose head when
``--relpose-head`` is given, else the ORB/SIFT essential-matrix baseline), and the query's
absolute position triangulated from the rays base -> query (:func:`geoseg.localize.absolute_position`)
with its degeneracy flag. Prints a table; ``--out`` writes the same as JSON.

A relative-pose head that predicts baselines (``predict_distance``) also gives each match its
distance from the query: the matches are then re-ranked nearest first (``--no-rerank`` keeps
the appearance order; with ``--gps-sigma`` the distance is first fused with the GPS fix's
distance to each match, :func:`geoseg.localize.fuse_gps_distance`; with the learned embedding
``--appearance-weight`` adds the retrieval distance to the log-distance key as a tie-break,
:func:`geoseg.localize.rerank_by_distance`) and the position comes from ranged rays
(:func:`geoseg.localize.locate_from_ranged_rays`), which one match already determines and which
stay determined when the bases are collinear with the query.

Sequence (``--sequence filter|smooth``): the queries are one drive, in the order given, along the
base's route (:mod:`geoseg.route_filter`): each query's matches are the most probable base
images under the route HMM (appearance, motion by ``--step-m`` metres between consecutive
queries, the GPS window when given, and with ``--gps-sigma`` a Gaussian of each fix's distance),
causal (``filter``, what a vehicle knows at that query) or using the whole drive (``smooth``). Each match then carries its ``sequence_probability``; the
posterior already separates neighbouring base images, so the matches keep its order (the
relative-pose head still gives their poses, distances and the position).

Embeddings: ``--model`` (a segmentation checkpoint or ONNX file exposing layer-21 features)
gives the raw layer-21 matching of §5.1.1, ``--model`` + ``--reloc-head`` the learned embedding;
without ``--model`` a normalised grey thumbnail is used, a placeholder baseline that only
finds near-duplicates (see :class:`geoseg.image_base.ThumbnailEmbedder`).

Query GPS (``--gps``): a CSV with columns ``image, x, y`` (world frame of the base, metres;
``image`` is the query's file name or the path as given on the command line).

Intrinsics for the essential-matrix baseline: ``BASE_DIR/camera.json``, else ``--focal``, else
an assumed focal length of ``max(W, H)`` pixels (flagged in the output). Base and query images
are assumed taken with the same camera: every query must have the size the intrinsics hold for
(``camera.json``'s ``image_size``, else the base images' size); a resized query is refused
rather than given confidently wrong poses.

``--out FILE`` is written atomically; an existing file is replaced only when an earlier
``geoseg localize`` wrote it (``--overwrite`` replaces any file).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("queries", nargs="+", type=Path, metavar="QUERY_IMAGE", help="query images")
    parser.add_argument(
        "--base", required=True, type=Path, help="image base directory (images + poses.csv)"
    )
    parser.add_argument(
        "--gps", type=Path, help="CSV of query positions: image, x, y (world frame, metres)"
    )
    parser.add_argument("--radius", type=float, help="GPS window radius in metres (needs --gps)")
    parser.add_argument("--k", type=int, default=3, help="matches per query (default 3)")
    parser.add_argument(
        "--model",
        type=Path,
        help="segmentation network (.onnx or checkpoint) giving layer-21 features; without it, "
        "a placeholder thumbnail embedding is used",
    )
    parser.add_argument(
        "--reloc-head", type=Path, help="trained embedding head checkpoint (needs --model)"
    )
    parser.add_argument(
        "--relpose-head", type=Path, help="trained relative-pose head checkpoint (needs --model)"
    )
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


def _load_head(path: Path, kind: str, device: str):
    from geoseg.errors import GeosegError
    from geoseg.infer import load_model_checkpoint
    from geoseg.models.reloc import RelocHead
    from geoseg.models.relpose import RelPoseHead

    model, _ = load_model_checkpoint(path, map_location=device)
    expected = {"reloc": RelocHead, "relpose": RelPoseHead}[kind]
    if not isinstance(model, expected):
        raise GeosegError(
            f"--{kind}-head: {path} holds a {type(model).__name__}, expected a {expected.__name__}"
        )
    return model.to(device).eval()


def _intrinsics(base, args, image_shape: tuple[int, ...]):
    """``(K, where K comes from, (W, H) it holds for, where that size comes from)``."""
    import numpy as np

    from geoseg.errors import GeosegError, check_positive
    from geoseg.image_base import CAMERA_FILE

    h, w = image_shape[:2]
    if base.K is not None:
        if args.focal is not None:
            raise GeosegError(
                f"--focal: {args.base / CAMERA_FILE} gives the intrinsics; drop --focal (or the file)"
            )
        if base.image_size is not None:
            return base.K, "camera.json", base.image_size, str(args.base / CAMERA_FILE)
        return base.K, "camera.json", (w, h), f"{args.base / CAMERA_FILE} (base image size)"
    if args.focal is not None:
        check_positive("--focal", args.focal)
        f, source = float(args.focal), "--focal"
    else:
        f, source = float(max(w, h)), "assumed"
        logger.warning(
            "no camera.json in the base and no --focal: assuming a focal length of %.0f px "
            "(relative poses of the essential-matrix baseline are approximate)",
            f,
        )
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    return K, source, (w, h), f"{source} focal on the base images' size"


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
    header = f"{'query':<24} {'rank':>4}  {'base image':<24} {'distance':>9}  relative pose"
    print(header)
    print("-" * len(header))
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
            print(
                f"{name[:24]:<24} {m['rank']:>4}  {Path(m['image']).name[:24]:<24} "
                f"{m['distance']:>9.4g}  {pose}"
            )
            name = ""
        pos = q["position"]
        if pos["degenerate"]:
            print(f"{'':<24} position: degenerate ({pos['reason']})")
        else:
            x, y, z = pos["xyz"]
            print(
                f"{'':<24} position: x {x:.2f}  y {y:.2f}  z {z:.2f} m "
                f"({pos['n_inliers']}/{pos['n_rays']} {pos['method']})"
            )


# ============================================================================ run


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from geoseg.errors import GeosegError, check_positive
    from geoseg.essential_baseline import estimate_relative_pose, rotation_error_deg
    from geoseg.image_base import (
        HeadEmbedder,
        ThumbnailEmbedder,
        check_image_size,
        layer21_features,
        load_image_base,
        raw_layer21_embedder,
        read_rgb,
    )
    from geoseg.localize import absolute_position, fuse_gps_distance, rerank_by_distance

    # ---- arguments
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
    else:
        args.distance_rel_sigma = 0.3
    if args.gps_sigma is not None:
        if args.gps is None:
            raise GeosegError("--gps-sigma: needs --gps (the query positions)")
        check_positive("--gps-sigma", args.gps_sigma)
    appearance_weight = args.appearance_weight
    if appearance_weight is None:
        appearance_weight = 0.5 if args.reloc_head is not None else 0.0
    else:
        check_positive("--appearance-weight", appearance_weight, strict=False)
    if args.model is None and (args.reloc_head is not None or args.relpose_head is not None):
        raise GeosegError("--reloc-head/--relpose-head: need --model (the layer-21 trunk)")
    if args.position_k is not None and (isinstance(args.position_k, bool) or args.position_k < 1):
        raise GeosegError(f"--position-k: expected an int >= 1, got {args.position_k}")
    if args.pool is not None and (args.model is None or min(args.pool) < 1):
        raise GeosegError("--pool: needs --model and two sizes >= 1")
    if args.sequence is None and (args.step_m is not None or args.appearance_scale is not None):
        raise GeosegError("--step-m/--appearance-scale: only with --sequence")
    if args.sequence is not None and args.appearance_weight is not None:
        raise GeosegError(
            "--appearance-weight: weighs the distance re-ranking, which --sequence replaces"
        )
    if args.step_m is not None:
        check_positive("--step-m", args.step_m, strict=False)
    route_cfg = None
    if args.sequence is not None:
        from geoseg.route_filter import RouteFilterConfig

        route_cfg = RouteFilterConfig(
            **({} if args.appearance_scale is None else {"appearance_scale": args.appearance_scale})
        )

    if args.out is not None:
        from geoseg.output_dir import prepare_output_file

        prepare_output_file(args.out, overwrite=args.overwrite, owned=_is_localize_output)
    base = load_image_base(args.base)
    queries: list[Path] = list(args.queries)
    gps = _read_query_gps(args.gps, queries) if args.gps is not None else None
    query_images = [read_rgb(q) for q in queries]
    K, k_source = None, None
    if args.relpose_head is None:  # the essential matrix: one K for base and query images
        K, k_source, camera_size, size_source = _intrinsics(base, args, base.load_image(0).shape)
        for q, img in zip(queries, query_images):
            check_image_size(f"query {q}", img, camera_size, size_source)

    # ---- models (all loaded before any work, so that a bad file fails fast)
    segmenter = None
    relpose_head = None
    if args.relpose_head is not None:
        relpose_head = _load_head(args.relpose_head, "relpose", args.device)
    if (
        args.gps_sigma is not None
        and args.sequence is None
        and not getattr(relpose_head, "predict_distance", False)
    ):
        raise GeosegError("--gps-sigma: needs a --relpose-head that predicts distances")
    if args.model is not None:
        from geoseg.export import available_providers
        from geoseg.infer import Segmenter

        if str(args.model).lower().endswith(".onnx"):
            segmenter = Segmenter.from_onnx(args.model, providers=available_providers(args.device))
        else:
            segmenter = Segmenter.from_checkpoint(args.model, device=args.device)
        if args.reloc_head is not None:
            head = _load_head(args.reloc_head, "reloc", args.device)
            st = args.reloc_head.stat()
            name = f"reloc-{args.model.stem}-{args.reloc_head.stem}-{st.st_size}-{st.st_mtime_ns}"
            embedder: Any = HeadEmbedder(segmenter, head, name=name)
            embedding_name = f"learned ({args.reloc_head.name})"
        else:
            embedder = raw_layer21_embedder(
                segmenter, output_size=None if args.pool is None else tuple(args.pool)
            )
            embedding_name = "raw layer-21 features"
    else:
        embedder = ThumbnailEmbedder()
        embedding_name = f"{embedder.name} (placeholder, not the learned embedding)"
    index = base.build_index(embedder, cache=not args.no_cache)
    q_emb = []
    for q, img in zip(queries, query_images):
        try:
            e = np.asarray(embedder([img]), dtype=np.float64)
        except GeosegError as err:
            raise GeosegError(f"query {q}: {err}") from None
        if e.shape != (1, index.dim):
            raise GeosegError(
                f"query {q}: embedding of size {e.shape[-1]} but the base's is {index.dim} "
                "(feature maps of mismatched sizes: query and base images of different sizes?)"
            )
        q_emb.append(e[0])
    sequence_prob = None
    if route_cfg is not None:
        from geoseg.route_filter import RouteFilter

        stamps = base.timestamps if np.isfinite(base.timestamps).all() else None
        if stamps is None:
            logger.info("the base has no timestamps: its route is the order of poses.csv")
        route = RouteFilter(base.t_wc, timestamps=stamps, config=route_cfg)
        all_dist = index.distances(np.stack(q_emb))
        steps = None if args.step_m is None else np.full(len(queries) - 1, args.step_m)
        run_filter = route.filter if args.sequence == "filter" else route.smooth
        post = run_filter(
            all_dist,
            steps,
            gps=None if gps is None else np.asarray(gps),
            radius_m=args.radius,
            gps_sigma_m=args.gps_sigma,
        )
        ranked, sequence_prob = post.top(min(args.k, len(base)))
        dists = np.take_along_axis(all_dist, ranked, axis=1)
        if args.radius is not None:  # the window's outside has probability 0: not a match
            ranked = np.where(sequence_prob > 0, ranked, -1)
    else:
        ranked, dists = index.query(
            np.stack(q_emb),
            k=min(args.k, len(base)),  # no more matches than base images
            gps=None if gps is None else np.asarray(gps),
            radius_m=args.radius,
        )

    # ---- relative poses
    if relpose_head is not None:
        features = layer21_features(segmenter)
        method = f"relative-pose head ({args.relpose_head.name})"
    else:
        method = f"essential matrix ({args.features.upper()} + MAGSAC)"

    def relative_pose(i_base: int, q_img: np.ndarray, q_name: Path) -> dict[str, Any]:
        base_img = base.load_image(i_base)
        if relpose_head is not None:
            import torch

            from geoseg.models.relpose import so3_exp

            fa = torch.from_numpy(features(base_img))[None].to(args.device)
            fb = torch.from_numpy(features(q_img))[None].to(args.device)
            if fa.shape != fb.shape:
                raise GeosegError(
                    f"query {q_name}, base image {base.images[i_base]}: feature maps of "
                    f"mismatched sizes {tuple(fb.shape[1:])} vs {tuple(fa.shape[1:])} "
                    "(the relative-pose head needs images of the same size)"
                )
            with torch.no_grad():
                out = relpose_head(fa, fb)
            R_ab = so3_exp(out["rotation"].double())[0].cpu().numpy()
            t_dir = out["direction"][0].double().cpu().numpy()
            dist = out.get("log_distance")
            return {
                "ok": True,
                "reason": "",
                "R_ab": R_ab,
                "t_dir_ab": t_dir,
                "distance_m": None if dist is None else float(dist[0].double().exp()),
                "n_inliers": None,
            }
        est = estimate_relative_pose(base_img, q_img, K, method=args.features)
        return {
            "ok": est.ok,
            "reason": est.reason,
            "R_ab": est.R_ab,
            "t_dir_ab": est.t_dir_ab,
            "distance_m": None,  # an essential matrix has no scale
            "n_inliers": est.n_inliers,
        }

    results = []
    for j, (q, img) in enumerate(zip(queries, query_images)):
        matches = []
        for r in range(ranked.shape[1]):
            i = int(ranked[j, r])
            if i < 0:
                continue
            rp = relative_pose(i, img, q)
            rp["rotation_deg"] = (
                float(rotation_error_deg(rp["R_ab"], np.eye(3))) if rp["ok"] else None
            )
            rp["query_R_wc"] = base.R_wc[i] @ rp["R_ab"] if rp["ok"] else None
            matches.append(
                {
                    "rank": r + 1,
                    "index": i,
                    "image": base.images[i],
                    "distance": float(dists[j, r]),
                    "base_t_wc": base.t_wc[i],
                    "relative_pose": rp,
                    **(
                        {}
                        if sequence_prob is None
                        else {"sequence_probability": float(sequence_prob[j, r])}
                    ),
                }
            )
        ranged = bool(matches) and all(
            m["relative_pose"]["distance_m"] is not None for m in matches
        )
        if ranged and not args.no_rerank and args.sequence is None:
            dist = np.array([[m["relative_pose"]["distance_m"] for m in matches]])
            if args.gps_sigma is not None:
                gps_m = np.array(
                    [[np.linalg.norm(m["base_t_wc"][:2] - np.asarray(gps[j])) for m in matches]]
                )
                dist = fuse_gps_distance(
                    dist,
                    gps_m,
                    relative_sigma=args.distance_rel_sigma,
                    gps_sigma_m=args.gps_sigma,
                )
                for m, d in zip(matches, dist[0]):
                    m["gps_fused_distance_m"] = float(d)
            order = rerank_by_distance(
                np.arange(len(matches))[None],
                dist,
                appearance=np.array([[m["distance"] for m in matches]]),
                appearance_weight=appearance_weight,
            )[2][0]
            matches = [matches[i] for i in order]
        for r, m in enumerate(matches, start=1):
            m["appearance_rank"], m["rank"] = m["rank"], r
        ok = [m for m in matches if m["relative_pose"]["ok"]][: args.position_k]
        position: dict[str, Any] = {
            "method": "ranged rays" if ranged else "rays",
            "xyz": None,
            "degenerate": True,
            "n_rays": len(ok),
            "n_inliers": 0,
            "inlier_ranks": [],
            "reason": "",
        }
        if not matches:
            position["reason"] = (
                f"no base image within {args.radius} m of the query's GPS"
                if args.radius is not None
                else "no match"
            )
        elif len(ok) < (need := 1 if ranged else 2):
            position["reason"] = f"{len(ok)} relative pose(s), at least {need} needed"
        else:
            idx = [m["index"] for m in ok]
            dirs = np.stack([m["relative_pose"]["t_dir_ab"] for m in ok])
            ranges = [m["relative_pose"]["distance_m"] for m in ok] if ranged else None
            ray = absolute_position(base.R_wc[idx], base.t_wc[idx], dirs, ranges)
            position.update(
                xyz=None if ray.degenerate else ray.point,
                degenerate=ray.degenerate,
                n_inliers=int(ray.inliers.sum()),
                inlier_ranks=[m["rank"] for m, inl in zip(ok, ray.inliers) if inl],
                residuals_m=ray.residuals,
                reason="near-parallel or inconsistent rays" if ray.degenerate else "",
            )
        results.append(
            {
                "image": str(q),
                "gps": None if gps is None else list(gps[j]),
                "matches": matches,
                "position": position,
            }
        )

    result = _clean(
        {
            "base": str(args.base),
            "base_size": len(base),
            "k": args.k,
            "gps_window_m": args.radius,
            "sequence": args.sequence,
            "embedding": embedding_name,
            "relative_pose_method": method,
            "intrinsics": k_source,
            "queries": results,
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
