"""Images meet a camera matrix only at the size it holds for (class: resized images, old K).

An upscaled or resized query with the base's ``camera.json`` gives confidently wrong poses;
every place where an image meets intrinsics must refuse a size that does not fit them.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from geoseg.errors import GeosegError
from geoseg.reloc.image_base import check_image_size, load_image_base, read_camera, write_poses_csv
from geoseg_cli.cli import main

R_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

PLACEHOLDER = ["--embedding", "thumbnail", "--relative-pose", "essential"]


def _base(root: Path, size=(48, 64), camera: dict | None = None) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    root.mkdir(parents=True, exist_ok=True)
    images = []
    for i in range(3):
        img = cv2.GaussianBlur(rng.integers(0, 256, (*size, 3), dtype=np.uint8), (5, 5), 0)
        cv2.imwrite(str(root / f"img_{i}.png"), img)
        images.append(img)
    t = np.c_[np.arange(3) * 10.0, np.zeros(3), np.full(3, 1.5)]
    write_poses_csv(root / "poses.csv", [f"img_{i}.png" for i in range(3)], [R_NORTH] * 3, t)
    if camera is not None:
        (root / "camera.json").write_text(json.dumps(camera))
    return images


CAMERA = {"K": [[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]], "image_size": [64, 48]}


@pytest.mark.parametrize("scale", [2.0, 0.5, (1.25, 1.0)])
def test_localize_refuses_a_resized_query(tmp_path, capsys, scale) -> None:
    images = _base(tmp_path / "base", camera=CAMERA)
    fx, fy = scale if isinstance(scale, tuple) else (scale, scale)
    query = tmp_path / "q.png"
    cv2.imwrite(str(query), cv2.resize(images[1], None, fx=fx, fy=fy))
    assert main(["localize", *PLACEHOLDER, str(query), "--base", str(tmp_path / "base")]) == 2
    err = capsys.readouterr().err
    assert "q.png" in err and "hold for 64x48" in err and "camera.json" in err
    # the same query at the camera's size is fine
    cv2.imwrite(str(query), images[1])
    assert main(["localize", *PLACEHOLDER, str(query), "--base", str(tmp_path / "base")]) == 0


def test_without_camera_json_queries_must_match_the_base_images(tmp_path, capsys) -> None:
    images = _base(tmp_path / "base")
    query = tmp_path / "q.png"
    cv2.imwrite(str(query), cv2.resize(images[1], None, fx=2.0, fy=2.0))
    assert main(["localize", *PLACEHOLDER, str(query), "--base", str(tmp_path / "base")]) == 2
    assert "base images' size" in capsys.readouterr().err


def test_base_images_must_have_the_camera_size(tmp_path) -> None:
    _base(tmp_path / "base", size=(96, 128), camera=CAMERA)
    base = load_image_base(tmp_path / "base")
    with pytest.raises(GeosegError, match="base image img_0.png: 128x96 pixels"):
        base.load_image(0)


def test_focal_and_camera_json_together_are_refused(tmp_path, capsys) -> None:
    images = _base(tmp_path / "base", camera=CAMERA)
    query = tmp_path / "q.png"
    cv2.imwrite(str(query), images[0])
    argv = [
        "localize",
        *PLACEHOLDER,
        str(query),
        "--base",
        str(tmp_path / "base"),
        "--focal",
        "500",
    ]
    assert main(argv) == 2
    assert "--focal" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("camera", "message"),
    [
        ({**CAMERA, "image_size": [64]}, "image_size"),
        ({**CAMERA, "image_size": [64.5, 48]}, "image_size"),
        ({**CAMERA, "image_size": [0, 48]}, "image_size"),
        ({**CAMERA, "image_size": [16, 12]}, "principal point"),
        ({"K": [[float("nan"), 0, 1], [0, 1, 1], [0, 0, 1]]}, "invalid intrinsics"),
        ({"fx": 1.0}, "expected"),
        ([1, 2, 3], "JSON object"),
    ],
)
def test_camera_file_is_validated(tmp_path, camera, message) -> None:
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(camera))
    with pytest.raises(GeosegError, match=message):
        read_camera(path)


def test_check_image_size() -> None:
    check_image_size("x", np.zeros((48, 64, 3)), (64, 48), "camera.json")
    check_image_size("x", np.zeros((10, 10, 3)), None, "camera.json")
    with pytest.raises(GeosegError, match="x: 64x48 pixels.*32x24"):
        check_image_size("x", np.zeros((48, 64, 3)), (32, 24), "camera.json")
