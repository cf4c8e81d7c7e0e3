"""Relocalisation of real photographs: the KITTI clips of ``shared/data/kitti_clips``.

A user relocalising their own camera's photos against a base of their own: for each clip, the
even frames with their true positions and headings become an image base (``geoseg base build
--positions``), the odd frames are the queries (``geoseg localize --out``), through the same
commands a user runs. The shipped networks were trained on a synthetic tram camera at 320x240;
these are real 1226x370 grey frames, a camera the heads have never seen.

Figures per clip (``<clip>/...``) and their means over the clips:

* ``reloc_position_error_m`` mean / median / p90: the localiser's horizontal position against
  the truth;
* ``reloc_best_match_error_m``: the position of the best-ranked base image itself (what a user
  gets without the relative-pose heads);
* ``reloc_over_best_match``: the ratio of the two means (<= 1: the heads do not make it worse);
* ``reloc_gated_share``: the queries whose matches' relative poses did not agree, so that the
  localiser took its best match's position (:class:`geoseg.reloc.localizer.LocalizerConfig`'s
  ``min_agreeing_rays``).

Split: ``straight`` showed the failure the gate answers (the rule was checked on it, the
tuning clip); ``right_turn`` reports. The base spacing is about 2 m (every other frame of a
10 Hz camera at ~10 m/s), so a query is ~1 m from its nearest base image.

Usage: ``python bench/reloc_real.py [--clips DIR] [--out DIR]``; writes
``bench/results/reloc_real.json``.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import ROOT, provenance  # noqa: E402
from splits import KITTI_REPORT_CLIPS, KITTI_TUNING_CLIPS  # noqa: E402

from slam_bridge.experiments.simulated_logs import KITTI_TO_WORLD, headings  # noqa: E402
from slam_bridge.frontend.kitti import KITTI_CAMERA_HEIGHT_M, read_kitti_poses  # noqa: E402

CLIPS = KITTI_TUNING_CLIPS + KITTI_REPORT_CLIPS
SPLIT = (
    f"tuning: {', '.join(KITTI_TUNING_CLIPS)} (the gate's rule was checked on it); report: "
    f"{', '.join(KITTI_REPORT_CLIPS)}"
)


def split_clip(clip: Path, out: Path) -> tuple[Path, Path, Path, dict[str, np.ndarray]]:
    """The clip's even frames as a base folder + positions CSV, its odd frames as queries.

    Returns:
        ``(base images, positions CSV, query images, true (x, y) per query file name)``.
    """
    R_wc, t_wc = read_kitti_poses(clip / "poses.txt")
    times = np.loadtxt(clip / "times.txt").reshape(-1)
    centres = t_wc @ KITTI_TO_WORLD.T  # the frame `geoseg slam simulate-logs` writes
    heading = np.degrees(headings(KITTI_TO_WORLD @ R_wc))
    base, queries = out / "base_images", out / "queries"
    for folder in (base, queries):
        folder.mkdir(parents=True, exist_ok=True)
    rows, truth = [], {}
    for i, image in enumerate(sorted((clip / "image_0").iterdir())):
        x, y, z = centres[i]
        if i % 2 == 0:
            shutil.copy(image, base / image.name)
            rows.append([image.name, x, y, z - KITTI_CAMERA_HEIGHT_M, heading[i], times[i]])
        else:
            shutil.copy(image, queries / image.name)
            truth[image.name] = np.array([x, y])
    positions = out / "positions.csv"
    with positions.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["image", "x", "y", "z", "heading_deg", "timestamp"])
        writer.writerows(rows)
    return base, positions, queries, truth


def geoseg(*args: str) -> None:
    """Run the ``geoseg`` command as a user does; a failure stops the bench with its output."""
    command = [shutil.which("geoseg") or "geoseg", *args]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")


def evaluate(results: dict, truth: dict[str, np.ndarray]) -> dict:
    """The clip's figures (module docstring) from ``geoseg localize --out``'s JSON."""
    err, best, gated = [], [], []
    for q in results["queries"]:
        t = truth[Path(q["image"]).name]
        err.append(float(np.linalg.norm(np.asarray(q["position"]["xyz"][:2]) - t)))
        best.append(float(np.linalg.norm(np.asarray(q["matches"][0]["base_t_wc"][:2]) - t)))
        gated.append(q["position"]["method"] == "best match")
    err, best = np.array(err), np.array(best)
    return {
        "queries": len(err),
        "reloc_position_error_m_mean": float(err.mean()),
        "reloc_position_error_m_median": float(np.median(err)),
        "reloc_position_error_m_p90": float(np.percentile(err, 90)),
        "reloc_best_match_error_m_mean": float(best.mean()),
        "reloc_over_best_match": float(err.mean() / best.mean()),
        "reloc_gated_share": float(np.mean(gated)),
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", type=Path, default=ROOT.parent / "shared" / "data" / "kitti_clips")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "reloc_real")
    p.add_argument("--results", type=Path, default=ROOT / "bench" / "results" / "reloc_real.json")
    args = p.parse_args(argv)
    meta = provenance(SPLIT)
    figures: dict = {}
    for name in CLIPS:
        clip, out = args.clips / name, args.out / name
        if not clip.is_dir():
            raise SystemExit(f"{clip}: not found (--clips: the kitti_clips folder)")
        base_images, positions, queries, truth = split_clip(clip, out)
        base = out / "base"
        geoseg("base", "build", str(base_images), "--out", str(base), "--overwrite",
               "--positions", str(positions), "--camera-height", str(KITTI_CAMERA_HEIGHT_M))  # fmt: skip
        located = out / "localized.json"
        geoseg("localize", *map(str, sorted(queries.iterdir())), "--base", str(base),
               "--out", str(located), "--overwrite")  # fmt: skip
        figures[name] = evaluate(json.loads(located.read_text()), truth)
        print(name, json.dumps(figures[name]))
    for key in figures[CLIPS[0]]:
        if key.startswith("reloc_"):
            figures[f"real_{key}"] = float(np.mean([figures[c][key] for c in CLIPS]))
    figures.update(meta)
    args.results.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.results.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(figures, indent=1, sort_keys=True) + "\n")
    tmp.replace(args.results)
    return figures


if __name__ == "__main__":
    main()
