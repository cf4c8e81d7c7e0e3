"""The SLAM on real drives: the KITTI clips of ``shared/data/kitti_clips``, as a user runs it.

For each clip and GPS seed the sensor logs are simulated from the clip's true poses exactly as
``geoseg slam simulate-logs CLIP --out LOGS --seed S`` does (1 Hz GPS with 0.75 m per axis,
wheel speed with 1 % noise and yaw rate, DEM segments with 0.2 m error), then
``geoseg slam run CLIP --out RUN --gps ... [--odometry ...] [--dem ...]`` runs through the same
library entry (:func:`slam_bridge.system.image_slam.load_inputs`, :func:`run_image_slam`), once per
sensor variant: ``gps_odo``, ``gps_odo_dem``, ``gps_only``, ``odo_only``.

Evaluation reads each run's ``trajectory_tum.txt`` with ``evo`` (a pose for every frame) against
the truth in the logs' world frame:

* ``translation_error_m``: mean horizontal error over the frames, no alignment (the run is
  georeferenced by the GPS); ``rotation_error_deg`` mean, ``..._max`` per run, and the same
  error split in the world frame into ``heading_error_deg`` (about z) and ``tilt_error_deg``
  (about x and y: the fixes are 2-D, and the truth's up is the first camera's ``-y`` axis);
* ``gps_error_m``: the fixes' own mean error, each against the truth at its own time;
* ``oracle_error_m``: the true trajectory's shape fitted rigidly (x, y, heading) to the same
  fixes: the best any method can do from those fixes alone (the clips hold only six fixes);
  ``oracle_heading_error_deg`` its heading error;
* ``odo_only``: no GPS, so the map stays in the first camera's frame: a similarity fit to the
  truth (evo's Umeyama alignment) gives its scale error ``|s - 1|`` and the aligned error;
* the run's ``status`` (``ok`` / ``degraded`` / ``failed``) and tracking failures, and its
  frames per second (wall time of the whole run over the clip's frames).

Keys (``real_*``) are means / maxima over the runs. Split: the two shared clips are where the
SLAM's real-drive settings were developed (a tuning split); a longer drive outside the
repository is the judge. Usage: ``python bench/slam_real.py [--clips DIR] [--out DIR]``; writes
``bench/results/slam_real.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import ROOT, provenance  # noqa: E402

VARIANTS = {
    "gps_odo": ("gps", "odometry"),
    "gps_odo_dem": ("gps", "odometry", "dem"),
    "gps_only": ("gps",),
    "odo_only": ("odometry",),
}
SEEDS = (0, 1, 2)
CLIPS = ("straight", "right_turn")
SPLIT = "tuning: the two shared KITTI clips (straight, right_turn), GPS seeds 0-2"


def rigid_fit_2d(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation + translation ``dst ~ R src + T`` in the plane.

    Args:
        src: ``(N, 2)``.
        dst: ``(N, 2)``.

    Returns:
        ``(R (2, 2), T (2,))``.
    """
    from slam_bridge.geometry.alignment import rotation_and_scale

    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    _, R = rotation_and_scale(a, b, b.T @ a, fix_scale=True, name="rigid_fit_2d")
    return R, md - R @ ms


def _truth_at(truth, t: np.ndarray) -> np.ndarray:
    t_true, _, T_true = truth
    return np.column_stack([np.interp(t, t_true, T_true[:, i]) for i in range(3)])


def evaluate(run_dir: Path, inputs, variant: str) -> dict:
    """The figures of one run (module docstring)."""
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface
    from scipy.spatial.transform import Rotation

    from slam_bridge.system.image_slam import gps_fix_errors

    summary = json.loads((run_dir / "summary.json").read_text())
    t_true, R_true, T_true = inputs.truth
    est = file_interface.read_tum_trajectory_file(str(run_dir / "trajectory_tum.txt"))
    idx = np.clip(np.searchsorted(t_true, est.timestamps), 0, t_true.size - 1)
    if np.any(np.abs(t_true[idx] - est.timestamps) > 1e-4):
        raise RuntimeError(f"{run_dir}: trajectory times do not match the truth's")
    out = {
        "status": summary.get("status", "ok"),
        "tracking_failures": int(summary["tracking_failures"]),
        "frames_per_second": float(summary["frames_per_second"]),
        "frames_with_pose": int(len(est.timestamps)),
    }
    R_est = np.stack([p[:3, :3] for p in est.poses_se3])
    rot = Rotation.from_matrix(np.einsum("kji,kjl->kil", R_true[idx], R_est)).magnitude()
    # the same error in the world frame: its z part is the heading's, its x-y part the tilt's
    # (which 2-D fixes do not measure: the up of a truth made from KITTI poses is cam0's -y)
    world = Rotation.from_matrix(np.einsum("kij,klj->kil", R_est, R_true[idx])).as_rotvec()
    if variant == "odo_only":
        ref = PoseTrajectory3D(
            positions_xyz=T_true[idx],
            orientations_quat_wxyz=np.roll(Rotation.from_matrix(R_true[idx]).as_quat(), 1, axis=1),
            timestamps=est.timestamps,
        )
        aligned = PoseTrajectory3D(
            positions_xyz=est.positions_xyz.copy(),
            orientations_quat_wxyz=est.orientations_quat_wxyz.copy(),
            timestamps=est.timestamps.copy(),
        )
        _, _, s = aligned.align(ref, correct_scale=True)
        e = np.linalg.norm(aligned.positions_xyz[:, :2] - T_true[idx, :2], axis=1)
        out.update(scale_error=float(abs(s - 1.0)), aligned_translation_error_m=float(e.mean()))
        return out
    e = np.linalg.norm(est.positions_xyz[:, :2] - T_true[idx, :2], axis=1)
    gps_err = gps_fix_errors(inputs)
    valid = np.isfinite(inputs.gps_xy).all(axis=1)
    tf = inputs.gps_timestamps[valid]
    inside = (tf >= t_true[0]) & (tf <= t_true[-1])
    R2, T2 = rigid_fit_2d(_truth_at(inputs.truth, tf[inside])[:, :2], inputs.gps_xy[valid][inside])
    oracle = T_true[:, :2] @ R2.T + T2
    out.update(
        translation_error_m=float(e.mean()),
        translation_error_max_m=float(e.max()),
        rotation_error_deg=float(np.degrees(rot.mean())),
        rotation_error_max_deg=float(np.degrees(rot.max())),
        heading_error_deg=float(np.degrees(np.abs(world[:, 2]).mean())),
        tilt_error_deg=float(np.degrees(np.linalg.norm(world[:, :2], axis=1).mean())),
        oracle_heading_error_deg=float(np.degrees(abs(np.arctan2(R2[1, 0], R2[0, 0])))),
        gps_error_m=float(gps_err.mean()),
        oracle_error_m=float(np.linalg.norm(oracle - T_true[:, :2], axis=1).mean()),
    )
    out["translation_error_over_gps"] = out["translation_error_m"] / out["gps_error_m"]
    out["translation_error_over_oracle"] = out["translation_error_m"] / out["oracle_error_m"]
    return out


def run_one(clip: Path, logs: Path, run_dir: Path, variant: str, cfg) -> Path:
    """``geoseg slam run`` with the variant's logs, through the command's library entry."""
    from slam_bridge.system.image_slam import load_inputs, run_image_slam

    use = VARIANTS[variant]
    inputs = load_inputs(
        clip,
        gps=logs / "gps.csv" if "gps" in use else None,
        odometry=logs / "odometry.csv" if "odometry" in use else None,
        dem=logs / "dem.csv" if "dem" in use else None,
        truth=logs / "truth.csv" if "gps" in use else None,
    )
    run_image_slam(inputs, run_dir, cfg, overwrite=True, progress=False)
    return run_dir


def main(argv: list[str] | None = None) -> dict:
    from geoseg.config import load_config
    from slam_bridge.experiments.simulated_logs import SimulatedLogsConfig, simulate_from_folder
    from slam_bridge.system.image_slam import ImageSlamConfig, load_inputs, read_truth_csv

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", type=Path, default=ROOT.parent / "shared" / "data" / "kitti_clips")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "slam_real")
    p.add_argument("--results", type=Path, default=ROOT / "bench" / "results" / "slam_real.json")
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a setting of configs/slam_images.yaml (as geoseg slam run --set)",
    )  # fmt: skip
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    meta = provenance(SPLIT)
    cfg = load_config(
        ImageSlamConfig, ROOT / "configs" / "slam_images.yaml", overrides=args.overrides
    )
    runs = {}
    for clip_name in CLIPS:
        clip = args.clips / clip_name
        if not clip.is_dir():
            raise SystemExit(f"{clip}: not found (--clips: the kitti_clips folder)")
        for seed in SEEDS:
            logs = simulate_from_folder(
                clip, args.out / clip_name / f"logs_{seed}", SimulatedLogsConfig(seed=seed)
            )
            for variant in VARIANTS:
                run_dir = run_one(
                    clip, logs, args.out / clip_name / f"{variant}_{seed}", variant, cfg
                )
                inputs = load_inputs(clip, gps=logs / "gps.csv")
                inputs.truth = read_truth_csv(logs / "truth.csv")
                key = f"{clip_name}/{variant}/seed{seed}"
                runs[key] = evaluate(run_dir, inputs, variant)
                print(key, json.dumps(runs[key]))
    with_gps = [r for k, r in runs.items() if "/odo_only/" not in k]
    odo = [r for k, r in runs.items() if "/odo_only/" in k]
    figures = {
        "real_translation_error_over_oracle_mean": float(
            np.mean([r["translation_error_over_oracle"] for r in with_gps])
        ),
        "real_translation_error_over_gps_mean": float(
            np.mean([r["translation_error_over_gps"] for r in with_gps])
        ),
        "real_translation_error_over_gps_max": float(
            np.max([r["translation_error_over_gps"] for r in with_gps])
        ),
        "real_oracle_over_gps_mean": float(
            np.mean([r["oracle_error_m"] / r["gps_error_m"] for r in with_gps])
        ),
        "real_rotation_error_deg_mean": float(np.mean([r["rotation_error_deg"] for r in with_gps])),
        "real_rotation_error_deg_max": float(
            np.max([r["rotation_error_max_deg"] for r in with_gps])
        ),
        "real_heading_error_deg_mean": float(np.mean([r["heading_error_deg"] for r in with_gps])),
        "real_tilt_error_deg_mean": float(np.mean([r["tilt_error_deg"] for r in with_gps])),
        "real_oracle_heading_error_deg_mean": float(
            np.mean([r["oracle_heading_error_deg"] for r in with_gps])
        ),
        "real_scale_error_max": float(np.max([r["scale_error"] for r in odo])),
        "real_tracking_failures": int(sum(r["tracking_failures"] for r in runs.values())),
        "real_status_failed": int(sum(r["status"] == "failed" for r in runs.values())),
        "real_status_degraded": int(sum(r["status"] == "degraded" for r in runs.values())),
        "real_frames_per_second": float(np.mean([r["frames_per_second"] for r in runs.values()])),
        "runs": runs,
        **meta,
        "note": (
            "frames_per_second: the whole run (reading, front end, SLAM, outputs) over the "
            "clip's frames, on the machine and load named in `machine`"
        ),
    }
    args.results.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.results.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(figures, indent=1, sort_keys=True) + "\n")
    tmp.replace(args.results)
    print("\n| figure | value |\n|---|---|")
    for k, v in figures.items():
        if k.startswith("real_"):
            print(f"| {k} | {v:.3f} |" if isinstance(v, float) else f"| {k} | {v} |")
    return figures


if __name__ == "__main__":
    main()
