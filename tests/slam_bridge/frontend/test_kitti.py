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
