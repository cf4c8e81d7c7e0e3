"""A KITTI odometry sequence folder read as frames: calibration, times, grayscale, errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slam_bridge.errors import SlamError
from slam_bridge.frontend.kitti import (
    KittiSequence,
    is_kitti_sequence,
    read_kitti_calib,
    read_kitti_poses,
)

P0 = "P0: 500 0 32 0 0 510 24 0 0 0 1 0"


def make_sequence(root, n=4, size=(64, 48), camera="image_0", colour=False):
    (root / camera).mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        shape = (size[1], size[0], 3) if colour else (size[1], size[0])
        cv2.imwrite(str(root / camera / f"{i:06d}.png"), rng.integers(0, 255, shape, np.uint8))
    (root / "calib.txt").write_text(
        P0 + "\nP1: 500 0 32 -200 0 510 24 0 0 0 1 0\nP2: 400 0 30 0 0 400 20 0 0 0 1 0\n"
    )
    (root / "times.txt").write_text("\n".join(f"{0.1 * i:.6e}" for i in range(n)) + "\n")
    poses = [np.hstack([np.eye(3), [[0.0], [0.0], [1.2 * i]]]).reshape(-1) for i in range(n)]
    (root / "poses.txt").write_text("\n".join(" ".join(f"{v:g}" for v in p) for p in poses))
    return root


def test_grayscale_sequence_reads_calibration_times_and_frames(tmp_path):
    seq_dir = make_sequence(tmp_path / "seq")
    assert is_kitti_sequence(seq_dir) and not is_kitti_sequence(tmp_path)
    seq = KittiSequence(seq_dir)
    np.testing.assert_allclose(seq.K, [[500, 0, 32], [0, 510, 24], [0, 0, 1]])
    assert seq.K.flags["C_CONTIGUOUS"]  # OpenCV misreads a strided block of P
    assert seq.image_size == (64, 48) and seq.grayscale and len(seq) == 4
    np.testing.assert_allclose(seq.timestamps, [0.0, 0.1, 0.2, 0.3])
    t, image = seq[2]
    assert t == pytest.approx(0.2) and image.shape == (48, 64) and image.dtype == np.uint8
    R, T = read_kitti_poses(seq_dir / "poses.txt")
    assert R.shape == (4, 3, 3) and T[3, 2] == pytest.approx(3.6)
    seq.check_sizes()


def test_colour_camera_uses_its_own_projection(tmp_path):
    seq = KittiSequence(make_sequence(tmp_path / "seq", camera="image_2", colour=True))
    assert seq.camera_index == 2 and not seq.grayscale
    assert seq.K[0, 0] == 400 and seq[0][1].shape == (48, 64, 3)


def test_bad_kitti_files_are_clear_errors(tmp_path):
    seq_dir = make_sequence(tmp_path / "seq")
    (seq_dir / "times.txt").write_text("0\n0.1\n")
    with pytest.raises(SlamError, match="2 times for 4 images"):
        KittiSequence(seq_dir)
    (seq_dir / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(SlamError, match="expected 12 numbers"):
        read_kitti_calib(seq_dir / "calib.txt")
    (seq_dir / "calib.txt").write_text("P1: 500 0 32 0 0 510 24 0 0 0 1 0\n")
    with pytest.raises(SlamError, match="no P0"):
        KittiSequence(seq_dir)
    (seq_dir / "poses.txt").write_text("1 0 0\n")
    with pytest.raises(SlamError, match="12"):
        read_kitti_poses(seq_dir / "poses.txt")
    cv2.imwrite(str(seq_dir / "image_0" / "000003.png"), np.zeros((10, 10), np.uint8))
    (seq_dir / "calib.txt").write_text(P0 + "\n")
    (seq_dir / "times.txt").write_text("0\n0.1\n0.2\n0.3\n")
    with pytest.raises(SlamError, match="000003.png: image is 10x10, expected 64x48"):
        KittiSequence(seq_dir).check_sizes()


def test_a_kitti_folder_loads_with_simulated_logs_and_refuses_a_truth_in_another_frame(tmp_path):
    from slam_bridge.experiments.simulated_logs import SimulatedLogsConfig, simulate_from_folder
    from slam_bridge.slam.initialization import VehicleRig
    from slam_bridge.system.image_slam import load_inputs

    seq_dir = make_sequence(tmp_path / "seq", n=12)
    utm = (652000.0, 6862000.0, 40.0)
    logs = simulate_from_folder(seq_dir, tmp_path / "logs", SimulatedLogsConfig(offset_m=utm))
    inputs = load_inputs(
        seq_dir, gps=logs / "gps.csv", odometry=logs / "odometry.csv", truth=logs / "truth.csv"
    )
    assert inputs.frames.grayscale and inputs.rig == VehicleRig(camera_height_m=1.65)
    assert inputs.truth[2][0, 0] == pytest.approx(utm[0])
    assert inputs.odometry.yaw_change(0.0, 1.0) is not None
    own = seq_dir / "poses.csv"  # KITTI's own poses, in the first camera's frame, renamed
    own.write_text((logs / "truth.csv").read_text().replace("652000", "000000"))
    with pytest.raises(SlamError, match="not a truth in the GPS's world frame"):
        load_inputs(seq_dir, gps=logs / "gps.csv", truth=own)
    assert load_inputs(seq_dir, gps=logs / "gps.csv").truth is None  # found, not asked: ignored


def test_map_points_keep_world_sized_coordinates(tmp_path):
    import types

    from slam_bridge.system.outputs import write_map_points

    X = np.array([[652000.123, 6862000.456, 40.789], [652001.0, 6862001.5, 41.0]])
    fake = types.SimpleNamespace(triangulated_points=lambda: (np.arange(2), X))
    path = write_map_points(tmp_path / "points.ply", fake)
    data = path.read_bytes()
    header, _, body = data.partition(b"end_header\n")
    assert b"element vertex 2" in header and b"property double y" in header
    np.testing.assert_array_equal(np.frombuffer(body, "<f8").reshape(-1, 3), X)
