"""Visual front end benchmark: track accuracy against rendered ground truth, and speed.

For each case (rig, appearance condition, world preset) a drive is rendered once into
``runs/cache/frontend_tracks/<case>`` (``geoseg render`` layout; reused when present), then
:class:`slam_bridge.frontend.image_tracks.ImageTracks` runs over it with keyframes spaced by the
distance from the render's wheel odometry (``gis/odometry.csv``; ``--parallax``: the image rule),
fed back by a :class:`slam_bridge.evaluation.tracks.TruthMap` (true poses, points triangulated from
the tracks as a loop with perfect poses would, so the map check and the re-observation work as in
the loop). Figures per case:

* ``bad_share``: observations whose true reprojection error exceeds 2 px
  (:func:`slam_bridge.evaluation.tracks.evaluate_tracks`: depth-referenced), and error percentiles;
* ``bad_share_consistency``: observations farther than 2 px from the static point that fits the
  track best at the true poses (what would bias the poses);
* ``tracks_per_keyframe``, ``continued_per_keyframe`` (median number of tracks shared with the
  previous keyframe), ``track_length_*`` (keyframes per point), ``reobservations`` (a point seen
  again after missing a keyframe) and their bad share;
* ``two_view_rot_deg`` / ``two_view_dir_deg``: :func:`slam_bridge.geometry.two_view_init` on
  the tracks shared by two keyframes up to 3 apart, against the true relative pose (medians);
* ``ms_per_frame`` / ``ms_per_keyframe``: CPU time of the front end alone (frames decoded in
  memory beforehand, OpenCV and BLAS on one thread), and ``read_ms_per_frame`` (PNG decoding);
  ``stage_*``: where the time goes.

Usage: ``python bench/frontend_tracks.py [--frames N] [--full] [--parallax]``. Prints a Markdown
table and writes ``bench/results/frontend_tracks.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from geoseg.config import load_config
from geoseg.synth.export import render_sequence
from geoseg.synth.world import WorldConfig
from slam_bridge.evaluation.tracks import RenderTruth, TruthMap, evaluate_tracks
from slam_bridge.frontend.frames import FrameList, ImageFolder
from slam_bridge.frontend.image_tracks import ImageTracks, ImageTracksConfig
from slam_bridge.geometry.multiview import two_view_init

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402

SPLIT = (
    "tuning: drives rendered from world_default / world_dense_occlusion (route seed 3), the "
    "drives the front end's settings were chosen on"
)

# name: (rig, condition, world config, image size)
CASES = {
    "car_day": ("car", "summer_day", "world_default", (640, 480)),
    "tram_day": ("tram", "summer_day", "world_default", (640, 480)),
    "car_dense": ("car", "summer_day", "world_dense_occlusion", (640, 480)),
    "tram_dense": ("tram", "overcast", "world_dense_occlusion", (640, 480)),
    "car_night": ("car", "night", "world_default", (640, 480)),
    "tram_winter": ("tram", "winter", "world_dense_occlusion", (640, 480)),
    "car_day_320": ("car", "summer_day", "world_default", (320, 240)),
}
FULL_CASES = {
    "car_dusk": ("car", "dusk", "world_default", (640, 480)),
    "car_overcast": ("car", "overcast", "world_default", (640, 480)),
    "car_sun_low": ("car", "sun_low", "world_default", (640, 480)),
    "tram_night": ("tram", "night", "world_default", (640, 480)),
    "car_winter_dense": ("car", "winter", "world_dense_occlusion", (640, 480)),
}


def odometry_distance(folder: Path):
    """``distance(t0, t1) -> metres`` integrated from ``gis/odometry.csv`` (measured speed)."""
    data = np.genfromtxt(folder / "gis" / "odometry.csv", delimiter=",", names=True)
    t, v = data["timestamp"], data["speed_mps"]
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    return lambda t0, t1: float(np.interp(t1, t, s) - np.interp(t0, t, s))


def rotation_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def two_view_errors(kfs, truth: RenderTruth, K: np.ndarray) -> tuple[float, float]:
    """Median rotation and translation-direction errors (degrees) of
    :func:`~slam_bridge.geometry.two_view_init` between keyframes up to 3 apart (the widest gap
    that still shares 30 tracks), from 6 starting keyframes along the drive."""
    rot, dirn = [], []
    for a in range(1, len(kfs) - 1, max(1, (len(kfs) - 2) // 6)):
        for gap in (3, 2, 1):
            if a + gap >= len(kfs):
                continue
            k0, k1 = kfs[a], kfs[a + gap]
            common, i0, i1 = np.intersect1d(k0.point_ids, k1.point_ids, return_indices=True)
            if common.size >= 30:
                break
        else:
            continue
        res = two_view_init(K, k0.uv[i0], k1.uv[i1])
        f0, f1 = k0.frame_index, k1.frame_index
        R_true = truth.R_wc[f0].T @ truth.R_wc[f1]
        d_true = truth.R_wc[f0].T @ (truth.t_wc[f1] - truth.t_wc[f0])
        rot.append(rotation_deg(res.R_wc.T @ R_true))
        cosang = d_true @ res.t_wc / np.linalg.norm(d_true)
        dirn.append(float(np.degrees(np.arccos(np.clip(cosang, -1, 1)))))
    return (float(np.median(rot)), float(np.median(dirn))) if rot else (np.nan, np.nan)


def run_case(folder: Path, parallax: bool) -> dict[str, float]:
    frames = ImageFolder(folder)
    truth = RenderTruth(folder)
    t0 = time.perf_counter()
    images = [frames[i][1] for i in range(len(frames))]
    read_ms = 1e3 * (time.perf_counter() - t0) / len(frames)
    memory = FrameList(frames.K, frames.image_size, frames.timestamps, images)
    distance = None if parallax else odometry_distance(folder)
    src = ImageTracks(memory, ImageTracksConfig(), distance=distance)
    tm = TruthMap(frames.K, frames.image_size, truth.R_wc, truth.t_wc, truth.depth,
                  points="triangulate")  # fmt: skip
    kfs, cpu = [], 0.0
    while True:
        c0 = time.process_time()
        kf = src.next_keyframe(tm.map)
        cpu += time.process_time() - c0
        if kf is None:
            break
        kfs.append(kf)
        tm.add(kf)
    ev = evaluate_tracks(kfs, frames.K, truth.R_wc, truth.t_wc, truth.depth)
    s = ev.summary
    rot, dirn = two_view_errors(kfs, truth, frames.K)
    timing = src.timing_report()
    out = {
        "bad_share": s["bad_share"],
        "bad_share_consistency": s["bad_share_consistency"],
        "bad_share_surface": s["bad_share_surface"],
        "error_median_px": s["error_median_px"],
        "error_p90_px": s["error_p90_px"],
        "keyframes": s["keyframes"],
        "frames": float(len(frames)),
        "tracks_per_keyframe": s["tracks_per_keyframe_mean"],
        "tracks_per_keyframe_min": s["tracks_per_keyframe_min"],
        "track_length_mean": s["track_length_mean"],
        "track_length_p90": s["track_length_p90"],
        "reobservations": s["reobservations"],
        "bad_share_reobserved": s["bad_share_reobserved"],
        "continued_per_keyframe": float(
            np.median(
                [np.isin(kfs[k].point_ids, kfs[k - 1].point_ids).sum() for k in range(1, len(kfs))]
            )
        ),
        "two_view_rot_deg": rot,
        "two_view_dir_deg": dirn,
        "ms_per_frame": 1e3 * cpu / len(frames),
        "ms_per_keyframe": 1e3 * cpu / max(len(kfs), 1),
        "read_ms_per_frame": read_ms,
    }
    for key in ("track_ms_per_frame", "epipolar_ms_per_frame", "gray_ms_per_frame"):
        out["stage_" + key] = timing[key]
    for key in ("checks", "map_check", "detect", "reobserve", "describe", "topup"):
        out[f"stage_{key}_ms_per_keyframe"] = timing[f"{key}_ms_per_keyframe"]
    return out


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=None, help="frames per drive (40; --full 120)")
    p.add_argument("--full", action="store_true", help="more conditions, longer drives")
    p.add_argument("--parallax", action="store_true", help="keyframes by parallax, not distance")
    p.add_argument("--cases", default=None, help="comma-separated case names")
    p.add_argument("--cache-dir", type=Path, default=ROOT / "runs" / "cache" / "frontend_tracks")
    args = p.parse_args(argv)
    cv2.setNumThreads(1)
    threadpool_limits(1)  # idle BLAS threads would count in the process CPU time
    frames = args.frames or (120 if args.full else 40)
    cases = dict(CASES, **(FULL_CASES if args.full else {}))
    if args.cases:
        cases = {k: cases[k] for k in args.cases.split(",")}
    meta = provenance(
        SPLIT,
        command=" ".join(["python", "bench/frontend_tracks.py", *(argv or sys.argv[1:])]),
    )
    results: dict[str, float | str] = {}
    rows = []
    for name, (rig, condition, world, size) in cases.items():
        cfg = load_config(WorldConfig, ROOT / "configs" / f"{world}.yaml")
        folder = args.cache_dir / f"{name}_{frames}"
        render_sequence(cfg, folder, frames, condition, rig, image_size=size, seed=3,
                        progress=False)  # fmt: skip
        fig = run_case(folder, args.parallax)
        results.update({f"{name}_{k}": v for k, v in fig.items()})
        rows.append((name, rig, condition, world.removeprefix("world_"), size, fig))
        print(
            f"{name}: bad {fig['bad_share']:.3f}, {fig['ms_per_frame']:.1f} ms/frame",
            file=sys.stderr,
        )
    results.update(meta)
    results["machine"] += (
        f", OpenCV {cv2.__version__} on 1 thread, load {os.getloadavg()[0]:.1f} at the end "
        "(shared machine: CPU times)"
    )
    print(
        "| case | rig | condition | world | size | bad share | consistency | err p50/p90 px | "
        "tracks/kf | continued/kf | track len mean/p90 | re-obs (bad) | two-view rot/dir deg | "
        "ms/frame | ms/kf |"
    )
    print("|" + "---|" * 15)
    for name, rig, cond, world, size, f in rows:
        print(
            f"| {name} | {rig} | {cond} | {world} | {size[0]}x{size[1]} | {f['bad_share']:.3f} | "
            f"{f['bad_share_consistency']:.3f} | "
            f"{f['error_median_px']:.2f}/{f['error_p90_px']:.2f} | "
            f"{f['tracks_per_keyframe']:.0f} | {f['continued_per_keyframe']:.0f} | "
            f"{f['track_length_mean']:.2f}/{f['track_length_p90']:.0f} | "
            f"{f['reobservations']:.0f} ({f['bad_share_reobserved']:.2f}) | "
            f"{f['two_view_rot_deg']:.2f}/{f['two_view_dir_deg']:.1f} | {f['ms_per_frame']:.1f} | "
            f"{f['ms_per_keyframe']:.1f} |"
        )
    out = ROOT / "bench" / "results" / "frontend_tracks.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(results, indent=1, default=float) + "\n")
    os.replace(tmp, out)
    return results


if __name__ == "__main__":
    main()
