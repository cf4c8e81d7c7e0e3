"""The frame-sequence readers: folder layouts, timestamp sources, and every bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from slam_bridge.errors import SlamError
from slam_bridge.frontend.frames import FrameList, ImageFolder

W, H = 32, 24
K = [[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]]


def image(seed: int, size=(W, H)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)


def write_folder(
    root: Path,
    n: int = 4,
    *,
    sub: str = "",
    names=None,
    camera: dict | None = None,
    ext: str = ".png",
) -> Path:
    """``n`` RGB images (written as BGR files) and a camera.json in ``root``."""
    d = root / sub if sub else root
    d.mkdir(parents=True, exist_ok=True)
    names = names or [f"{i:06d}{ext}" for i in range(n)]
    for i, name in enumerate(names):
        assert cv2.imwrite(str(d / name), image(i)[..., ::-1])
    cam = {"K": K, "image_size": [W, H]} if camera is None else camera
    (root / "camera.json").write_text(json.dumps(cam))
    return root


def write_csv(path: Path, header: str, rows) -> None:
    path.write_text(header + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))


# ---------------------------------------------------------------------------------- layouts
def test_render_layout_reads_rgb_subfolder_and_poses_csv(tmp_path):
    write_folder(tmp_path, 3, sub="rgb", camera={"K": K, "image_size": [W, H], "fps": 10.0})
    write_csv(
        tmp_path / "poses.csv", "frame,timestamp,tx", [(0, 0.0, 1), (1, 0.1, 1), (2, 0.25, 1)]
    )
    seq = ImageFolder(tmp_path)
    assert len(seq) == 3 and seq.image_size == (W, H)
    assert seq.image_dir == tmp_path / "rgb"
    np.testing.assert_allclose(seq.timestamps, [0.0, 0.1, 0.25])  # poses.csv before fps
    np.testing.assert_allclose(seq.K, K)
    assert seq.names == ["000000.png", "000001.png", "000002.png"]
    t, rgb = seq[1]
    assert t == pytest.approx(0.1)
    assert rgb.dtype == np.uint8 and rgb.shape == (H, W, 3)
    np.testing.assert_array_equal(rgb, image(1))  # RGB, not BGR
    assert [t for t, _ in seq] == pytest.approx([0.0, 0.1, 0.25])
    assert seq[-1][0] == pytest.approx(0.25)


def test_flat_folder_with_image_timestamps_sorted_by_name(tmp_path):
    names = ["b.jpg", "a.png", "c.JPEG"]
    write_folder(tmp_path, names=names)
    write_csv(
        tmp_path / "timestamps.csv",
        "image,timestamp",
        [("c.JPEG", 3.0), ("a", 1.0), ("b.jpg", 2.0)],
    )
    seq = ImageFolder(tmp_path)
    assert seq.names == ["a.png", "b.jpg", "c.JPEG"]
    np.testing.assert_allclose(seq.timestamps, [1.0, 2.0, 3.0])
    assert seq[2][1].shape == (H, W, 3)


def test_frame_column_matches_integer_names_then_positions(tmp_path):
    write_folder(tmp_path, names=["000010.png", "000011.png"])
    write_csv(tmp_path / "timestamps.csv", "frame,timestamp", [(11, 5.5), (10, 5.0)])
    np.testing.assert_allclose(ImageFolder(tmp_path).timestamps, [5.0, 5.5])
    other = write_folder(tmp_path / "x", names=["left.png", "right.png"])
    write_csv(other / "timestamps.csv", "frame,timestamp", [(0, 1.0), (1, 2.0)])
    np.testing.assert_allclose(ImageFolder(other).timestamps, [1.0, 2.0])


def test_fps_fallback_and_explicit_paths(tmp_path):
    write_folder(tmp_path / "imgs", 3, camera={"K": K, "image_size": [W, H], "fps": 4.0})
    seq = ImageFolder(tmp_path / "imgs")
    np.testing.assert_allclose(seq.timestamps, [0.0, 0.25, 0.5])
    cam = tmp_path / "elsewhere.json"
    cam.write_text(json.dumps({"K": K, "image_size": [W, H]}))
    ts = tmp_path / "t.csv"
    write_csv(ts, "image,timestamp", [("000000.png", 0), ("000001.png", 1), ("000002.png", 2)])
    seq = ImageFolder(tmp_path / "imgs", camera=cam, timestamps=ts)
    np.testing.assert_allclose(seq.timestamps, [0, 1, 2])


def test_frame_list_in_memory_and_callable():
    imgs = [image(i) for i in range(3)]
    seq = FrameList(np.array(K), (W, H), [0.0, 0.1, 0.2], imgs)
    assert len(seq) == 3 and seq[2][0] == pytest.approx(0.2)
    np.testing.assert_array_equal(seq[1][1], imgs[1])
    lazy = FrameList(np.array(K), (W, H), [0.0, 0.1], lambda i: imgs[i])
    np.testing.assert_array_equal(lazy[1][1], imgs[1])


# ---------------------------------------------------------------------------------- bad input
def raises(match: str):
    return pytest.raises(SlamError, match=match)


def test_empty_folder_and_missing_folder(tmp_path):
    (tmp_path / "camera.json").write_text(json.dumps({"K": K, "image_size": [W, H]}))
    with raises("no images"):
        ImageFolder(tmp_path)
    with raises("not a folder"):
        ImageFolder(tmp_path / "nope")


def test_unreadable_image_names_the_file(tmp_path):
    write_folder(tmp_path, 3, camera={"K": K, "image_size": [W, H], "fps": 10})
    (tmp_path / "000001.png").write_bytes(b"not a png")
    seq = ImageFolder(tmp_path)  # the first image is fine
    with raises("000001.png: cannot read the image"):
        seq[1]
    (tmp_path / "000000.png").write_bytes(b"")
    with raises("000000.png: cannot read the image"):
        ImageFolder(tmp_path)


def test_mixed_sizes_named_as_read_and_first_checked_against_camera(tmp_path):
    write_folder(tmp_path, 3, camera={"K": K, "image_size": [W, H], "fps": 10})
    cv2.imwrite(str(tmp_path / "000002.png"), image(2, (W + 2, H)))
    seq = ImageFolder(tmp_path)
    seq[1]
    with raises(rf"000002.png: image is {W + 2}x{H}, expected {W}x{H}"):
        seq[2]
    bad = write_folder(tmp_path / "b", 2, camera={"K": K, "image_size": [W, H + 1], "fps": 10})
    with raises(rf"000000.png: image is {W}x{H}, expected {W}x{H + 1}"):
        ImageFolder(bad)


@pytest.mark.parametrize(
    "camera, match",
    [
        ({"image_size": [W, H]}, "missing 'K'"),
        ({"K": K}, "missing 'image_size'"),
        ({"K": [[1, 0], [0, 1]], "image_size": [W, H]}, r"expected shape \(3, 3\)"),
        ({"K": [[30, 0, 15], [0, float("nan"), 11], [0, 0, 1]], "image_size": [W, H]}, "NaN"),
        ({"K": [[30, 0, 15], [0, 30, 11], [0, 1, 1]], "image_size": [W, H]}, "upper-triangular"),
        ({"K": [[-30, 0, 15], [0, 30, 11], [0, 0, 1]], "image_size": [W, H]}, "positive focal"),
        ({"K": "eye", "image_size": [W, H]}, "3x3 matrix of numbers"),
        ({"K": K, "image_size": [W]}, r"image_size: expected \[W, H\]"),
        ({"K": K, "image_size": [W, 0]}, r"image_size: expected \[W, H\]"),
        ({"K": K, "image_size": [W, H], "fps": -1}, "fps: expected a number > 0"),
    ],
)
def test_bad_camera_file(tmp_path, camera, match):
    write_folder(tmp_path, 2, camera=camera)
    with raises(match):
        ImageFolder(tmp_path)


def test_camera_file_missing_or_not_json(tmp_path):
    write_folder(tmp_path, 2)
    (tmp_path / "camera.json").unlink()
    with raises("camera file not found"):
        ImageFolder(tmp_path)
    (tmp_path / "camera.json").write_text("{not json")
    with raises("cannot read the camera file"):
        ImageFolder(tmp_path)


def test_missing_timestamps(tmp_path):
    write_folder(tmp_path, 2)
    with raises("no timestamps"):
        ImageFolder(tmp_path)
    with raises("timestamps file not found"):
        ImageFolder(tmp_path, timestamps=tmp_path / "none.csv")


@pytest.mark.parametrize(
    "header, rows, match",
    [
        ("image,timestamp", [("000000.png", 1.0), ("000001.png", 1.0)], "increase strictly"),
        (
            "image,timestamp",
            [("000000.png", 2.0), ("000001.png", 1.0)],
            "frame 1 has 1.0 after 2.0",
        ),
        ("image,timestamp", [("000000.png", "nan"), ("000001.png", 1.0)], "not a finite number"),
        ("image,timestamp", [("000000.png", 0.0)], "1 rows for 2 images"),
        ("image,timestamp", [("000000.png", 0.0), ("zzz.png", 1.0)], "zzz.png' matches no image"),
        ("image,timestamp", [("000000.png", 0.0), ("000000", 1.0)], "has a second row"),
        ("image,timestamp", [("000000.png", 0.0), ("000001.png", "x")], "'x' is not a number"),
        ("frame,timestamp", [(0, 0.0), ("a", 1.0)], "'a' is not an integer"),
        ("frame,timestamp", [(0, 0.0), (7, 1.0)], "frame 7 matches no image"),
        ("name,time", [("000000.png", 0.0), ("000001.png", 1.0)], "expected columns"),
    ],
)
def test_bad_timestamps_file(tmp_path, header, rows, match):
    write_folder(tmp_path, 2)
    write_csv(tmp_path / "timestamps.csv", header, rows)
    with raises(match):
        ImageFolder(tmp_path)


def test_render_poses_csv_must_match_images(tmp_path):
    write_folder(tmp_path, 3, sub="rgb")
    write_csv(tmp_path / "poses.csv", "frame,timestamp", [(0, 0.0), (1, 0.1)])
    with raises("poses.csv: 2 rows for 3 images"):
        ImageFolder(tmp_path)


def test_frame_list_bad_input():
    img = image(0)
    with raises("expected 2 images"):
        FrameList(np.array(K), (W, H), [0.0, 1.0], [img])
    with raises("increase strictly"):
        FrameList(np.array(K), (W, H), [1.0, 1.0], [img, img])
    seq = FrameList(np.array(K), (W, H), [0.0, 1.0], [img, img[:, :-1]])
    with raises(r"frame 1: expected an \(H, W, 3\)"):
        seq[1]
    with raises("outside the 2 frames"):
        seq[2]
    with raises("expected an integer"):
        seq[0.5]
    with raises("upper-triangular"):
        FrameList(np.ones((3, 3)), (W, H), [0.0], [img])
