"""``geoseg slam run`` on a tiny rendered drive: outputs, no ground truth in the loop, bad input."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest

from geoseg.synth.export import render_sequence
from geoseg_cli.cli import main
from slam_bridge.csv_columns import read_columns
from slam_bridge.errors import SlamError
from slam_bridge.system.image_slam import load_inputs


def write_gps(folder, sigma: float = 0.75, seed: int = 3):
    """A frame-rate GPS log of the render's vehicle positions plus N(0, sigma^2) per axis."""
    poses = read_columns(folder / "poses.csv", ["timestamp", "vehicle_x", "vehicle_y"])
    rng = np.random.default_rng(seed)
    xy = np.column_stack([poses["vehicle_x"], poses["vehicle_y"]])
    xy = xy + rng.normal(scale=sigma, size=xy.shape)
    path = folder / "gps_test.csv"
    np.savetxt(
        path, np.column_stack([poses["timestamp"], xy]), delimiter=",", header="timestamp,x,y",
        comments="", fmt="%.6f",
    )  # fmt: skip
    return path


@pytest.fixture(scope="module")
def drive(tmp_path_factory, make_tiny_world):
    folder = tmp_path_factory.mktemp("drive") / "render"
    render_sequence(
        make_tiny_world(), folder, frames=70, image_size=(320, 240), seed=1, progress=False
    )
    return folder, write_gps(folder)


def slam_args(folder, gps, out, *extra):
    return [
        "slam", "run", str(folder), "--out", str(out), "--gps", str(gps), "--no-progress",
        "--odometry", str(folder / "gis" / "odometry.csv"), "--dem", str(folder / "gis" / "dem.csv"),
        *extra,
    ]  # fmt: skip


def read_trajectory(path):
    rows = list(csv.DictReader(open(path)))
    cols = ["tx", "ty", "tz"] + [f"r{i}{j}" for i in range(3) for j in range(3)]
    return rows, np.array([[float(r[c]) if r[c] else np.nan for c in cols] for r in rows])


def test_slam_run_writes_a_georeferenced_trajectory(drive, tmp_path, capsys):
    folder, gps = drive
    out = tmp_path / "run"
    assert main(slam_args(folder, gps, out)) == 0
    printed = capsys.readouterr().out
    assert "keyframes" in printed and "against poses.csv" in printed
    for name in ("trajectory.csv", "map_points.ply", "keyframes.csv", "trajectory.png"):
        assert (out / name).is_file(), name
    s = json.loads((out / "summary.json").read_text())
    assert s["georeferenced"] and s["tracking_failures"] == 0 and s["keyframes"] >= 15
    # a ~50 m drive with a 0.75 m GPS (measured: 0.18 m against the fixes' 0.97 m, 0.22 deg):
    # the SLAM beats its GPS by a wide margin, and says the run is sound
    assert s["translation_error_m"] < 0.5 * s["gps_error_m"] and s["rotation_error_deg"] < 1.0
    assert s["status"] == "ok" and s["status_reasons"] == []
    assert printed.strip().splitlines()[-1] == "status: ok"
    assert s["frames_processed"] == s["frames"] == sum(s["frames_with_pose"].values())
    for name in ("frame_poses.csv", "trajectory_tum.txt", "trajectory_kitti.txt"):
        assert (out / name).is_file(), name
    tum = np.loadtxt(out / "trajectory_tum.txt")
    kitti = np.loadtxt(out / "trajectory_kitti.txt")
    assert tum.shape == (s["frames"] - s["frames_with_pose"]["none"], 8) == (len(kitti), 8)
    np.testing.assert_allclose(kitti[:, [3, 7, 11]], tum[:, 1:4], atol=1e-5)
    rows, poses = read_trajectory(out / "trajectory.csv")
    assert len(rows) == s["keyframes"]
    world = np.array([r["in_world"] == "1" for r in rows])
    assert world.sum() == s["keyframes_in_world"] >= 0.6 * len(rows)
    assert all(r["lat_deg"] and r["lon_deg"] for r, w in zip(rows, world) if w)  # WGS84 too
    # keyframes a failed start could not place have empty poses, the others rotations
    placed = np.isfinite(poses).all(axis=1)
    assert placed[world].all()
    R = poses[placed, 3:].reshape(-1, 3, 3)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-6
    )
    log = list(csv.DictReader(open(out / "keyframes.csv")))
    assert [r["tracking"] for r in log[:2]] == ["start", "start"]
    assert any("gps" in r["constraints"] for r in log)
    assert any("vertical" in r["constraints"] for r in log)  # the line segments' tilt
    # a second run into the same folder is allowed (its own outputs); a foreign folder is not
    assert main(slam_args(folder, gps, out)) == 0
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main(slam_args(folder, gps, foreign)) == 2
    assert "did not write" in capsys.readouterr().err
    assert (foreign / "notes.txt").read_text() == "mine" and not (foreign / "summary.json").exists()


@pytest.mark.parametrize("method", ["dpc", "mpc"])
def test_hybrid_windows_run_on_images(drive, tmp_path, method):
    """``--method dpc|mpc``: the hybrid BA / pose-graph windows of chapter 3 on image tracks,
    their pose-graph cameras in the keyframe log, the keyframes as close to the truth."""
    folder, gps = drive
    out = tmp_path / method
    assert main(slam_args(folder, gps, out, "--method", method)) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["method"] == method and s["tracking_failures"] == 0 and s["georeferenced"]
    # measured: dpc 0.20 m, mpc 0.17 m against the fixes' 0.97 m, 0.5 deg: they beat the GPS
    assert s["translation_error_m"] < 0.5 * s["gps_error_m"] and s["rotation_error_deg"] < 1.0
    log = list(csv.DictReader(open(out / "keyframes.csv")))
    assert sum(int(r["pose_graph_cameras"]) > 0 for r in log) >= 0.3 * len(log)
    assert any("gps" in r["constraints"] for r in log)


def test_a_folder_that_is_not_an_image_base_is_refused(drive, tmp_path):
    """``--base`` names an image base (a run from one: tests/test_readme.py's walkthrough)."""
    folder, _ = drive
    with pytest.raises(SlamError, match="not an image base"):
        load_inputs(folder, base=folder / "gis")


def test_scrambled_ground_truth_changes_only_the_evaluation(drive, tmp_path):
    """No ground truth reaches the loop: scrambling poses.csv changes the reported errors and
    nothing else."""
    folder, gps = drive
    scrambled = tmp_path / "scrambled"
    shutil.copytree(folder, scrambled)
    lines = (scrambled / "poses.csv").read_text().splitlines()
    header = lines[0].split(",")
    rng = np.random.default_rng(0)
    out_lines = [lines[0]]
    for line in lines[1:]:
        v = line.split(",")
        for c in ("tx", "ty", "tz", "vehicle_x", "vehicle_y"):
            i = header.index(c)
            v[i] = f"{float(v[i]) + rng.normal(scale=5.0):.6f}"
        out_lines.append(",".join(v))
    (scrambled / "poses.csv").write_text("\n".join(out_lines) + "\n")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(slam_args(folder, gps, a)) == 0
    assert main(slam_args(scrambled, gps, b)) == 0
    _, pa = read_trajectory(a / "trajectory.csv")
    _, pb = read_trajectory(b / "trajectory.csv")
    np.testing.assert_array_equal(pa, pb)
    sa = json.loads((a / "summary.json").read_text())
    sb = json.loads((b / "summary.json").read_text())
    assert sb["translation_error_m"] > 2 * sa["translation_error_m"]


def test_bad_inputs_are_clear_errors(drive, tmp_path, capsys):
    folder, gps = drive

    def fails(args, match):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert match in err, err

    bad = tmp_path / "gps_no_xy.csv"
    bad.write_text("timestamp,lat\n0.0,1.0\n")
    fails(slam_args(folder, bad, tmp_path / "o1"), "x, y")
    bad.write_text("timestamp,x,y\n0.0,1.0,nan\n0.1,1.0,2.0\n")
    fails(slam_args(folder, bad, tmp_path / "o2"), "row 2, column 'y'")
    bad.write_text("timestamp,x,y\n0.5,1.0,1.0\n0.1,1.0,2.0\n")
    fails(slam_args(folder, bad, tmp_path / "o3"), "increasing")
    bad.write_text("timestamp,x,y\n1000.0,1.0,1.0\n1001.0,1.0,2.0\n")
    fails(slam_args(folder, bad, tmp_path / "o4"), "do not overlap")
    odo = tmp_path / "odo.csv"
    odo.write_text("timestamp,speed\n0.0,1.0\n")
    fails(slam_args(folder, gps, tmp_path / "o5", "--odometry", str(odo)), "speed_mps")
    empty = tmp_path / "empty"
    empty.mkdir()
    fails(slam_args(empty, gps, tmp_path / "o6"), str(empty))
    for o in ("o1", "o2", "o3", "o4", "o5", "o6"):  # nothing that looks like a finished run
        assert not (tmp_path / o / "summary.json").exists()
    with pytest.raises(SlamError, match="not a georeference"):
        geo = tmp_path / "geo.json"
        geo.write_text("{}")
        load_inputs(folder, georeference=geo)


def test_a_bad_image_mid_sequence_stops_the_run_without_finished_outputs(drive, tmp_path, capsys):
    """Images are read as the run goes: an unreadable one is named, and the output folder is
    left without ``summary.json`` (what marks a finished run)."""
    folder, gps = drive
    broken = tmp_path / "broken"
    shutil.copytree(folder, broken)
    (broken / "rgb" / "000040.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    assert main(slam_args(broken, gps, out)) == 2
    assert "000040.png" in capsys.readouterr().err
    assert not (out / "summary.json").exists() and not (out / "trajectory.csv").exists()
    # a camera.json whose image size does not match the images is refused before any work
    cam = json.loads((broken / "camera.json").read_text())
    cam["image_size"] = [640, 480]
    (broken / "camera.json").write_text(json.dumps(cam))
    assert main(slam_args(broken, gps, tmp_path / "out2")) == 2
    assert "expected 640x480" in capsys.readouterr().err


def test_refine_a_run_and_measure_the_run_against_it(drive, tmp_path, capsys):
    """``slam run`` saves its map; ``slam refine`` adjusts it whole against the facade table
    (nearest facades: the run had no building model), the DEM, GPS and odometry; ``slam-eval
    run`` measures the run against the refined run as it would against the truth."""
    folder, gps = drive
    run = tmp_path / "run"
    assert main(slam_args(folder, gps, run)) == 0
    assert (run / "map.npz").is_file()
    gis = folder / "gis"
    refine = [
        "slam", "refine", str(run), "--gps", str(gps), "--dem", str(gis / "dem.csv"),
        "--odometry", str(gis / "odometry.csv"), "--buildings", str(gis / "facades.csv"),
        "--truth", str(folder / "poses.csv"),
    ]  # fmt: skip
    assert main(refine) == 0
    refined = tmp_path / "run_refined"  # the default: beside the run
    s = json.loads((refined / "summary.json").read_text())
    assert s["association"] == "nearest" and s["building_rows"] > 0
    assert s["gps_rows"] == s["keyframes"] == s["run_matched"]
    # a refined trajectory no worse than the run's (measured on this 50 m drive: 0.328 m
    # against 0.329 m)
    assert s["translation_error_m"] < s["run_translation_error_m"] + 0.02
    for name in ("trajectory.csv", "frame_poses.csv", "trajectory_tum.txt", "map_points.ply"):
        assert (refined / name).is_file(), name
    capsys.readouterr()
    assert main(["slam-eval", "run", "--run", str(run), "--reference", str(refined),
                 "--out", str(tmp_path / "eval")]) == 0  # fmt: skip
    versus = json.loads((tmp_path / "eval" / "reference_eval.json").read_text())
    assert versus["matched"] == s["keyframes"] and versus["unmatched"] == 0
    assert 0 < versus["translation_error_m"] < 0.5
    assert main(["slam-eval", "run", "--run", str(run), "--reference",
                 str(folder / "poses.csv")]) == 0  # fmt: skip
    assert f"{s['run_translation_error_m']:.3f} m horizontal" in capsys.readouterr().out
    # a folder without a map (not a run), and slam-eval run without its reference
    assert main([*refine[:2], str(gis), *refine[3:]]) == 2
    assert "no map.npz in this folder" in capsys.readouterr().err
    assert main(["slam-eval", "run", "--run", str(run)]) == 2
    assert "needs --run RUN_DIR and --reference" in capsys.readouterr().err
