"""An image base's triangulated points and PnP on them (``geoseg.reloc.base_structure``).

The scene: a textured facade, the plane ``x = 8`` m, seen sideways by cameras driving along
``y``; every image is the facade's texture warped by the plane's homography, so the points'
truth (on the plane) and the cameras' (their poses) are exact.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from geoseg.errors import GeosegError
from geoseg.reloc.base_structure import (
    StructureConfig,
    StructureLocator,
    build_structure,
    neighbour_pairs,
)
from geoseg.reloc.image_base import load_image_base, write_poses_csv

K = np.array([[250.0, 0.0, 159.5], [0.0, 250.0, 119.5], [0.0, 0.0, 1.0]])
SIZE = (320, 240)
FACADE_X = 8.0
PX_PER_M = 100.0  # texture resolution
Y0, Z0 = -6.0, 5.0  # the texture's top-left corner on the facade
# a camera looking along +x (z up): its x axis is -y, its y axis -z
R_SIDEWAYS = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def texture(seed: int = 0) -> np.ndarray:
    """A facade texture rich in corners: noise at several scales plus random blocks."""
    rng = np.random.default_rng(seed)
    h, w = 800, 1800
    img = np.zeros((h, w), np.float32)
    for cells in (8, 30, 120):
        small = rng.random((cells * h // w + 1, cells)).astype(np.float32)
        img += cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(400):
        x, y = rng.integers(0, w - 40), rng.integers(0, h - 40)
        img[y : y + rng.integers(8, 40), x : x + rng.integers(8, 40)] += rng.uniform(-1, 1)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return np.repeat(img.astype(np.uint8)[:, :, None], 3, axis=2)


def view(tex: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray) -> np.ndarray:
    """The facade seen by the camera ``(R_wc, t_wc)``: the texture through the homography."""
    # texture pixel (u, v, 1) -> facade point (FACADE_X, Y0 + u / s, Z0 - v / s)
    A = np.array([[0.0, 0.0, FACADE_X], [1 / PX_PER_M, 0.0, Y0], [0.0, -1 / PX_PER_M, Z0]])
    H = K @ R_wc.T @ (A - np.outer(t_wc, [0.0, 0.0, 1.0]))
    return cv2.warpPerspective(tex, H, SIZE, flags=cv2.INTER_AREA)


def yawed(deg: float) -> np.ndarray:
    a = np.radians(deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return Rz @ R_SIDEWAYS


@pytest.fixture(scope="module")
def facade_base(tmp_path_factory):
    """Six base images 1 m apart along the facade, with camera.json."""
    root = tmp_path_factory.mktemp("facade_base")
    tex = texture()
    t_wc = np.array([[0.0, y, 1.5] for y in np.arange(6.0)])
    R_wc = np.repeat(R_SIDEWAYS[None], len(t_wc), axis=0)
    names = []
    for i, (R, t) in enumerate(zip(R_wc, t_wc)):
        names.append(f"rgb/{i:03d}.png")
        (root / "rgb").mkdir(exist_ok=True)
        cv2.imwrite(str(root / names[-1]), cv2.cvtColor(view(tex, R, t), cv2.COLOR_RGB2BGR))
    write_poses_csv(root / "poses.csv", names, R_wc, t_wc, timestamps=np.arange(6.0))
    (root / "camera.json").write_text(json.dumps({"K": K.tolist(), "image_size": list(SIZE)}))
    return load_image_base(root), tex


def test_triangulated_points_lie_on_the_facade(facade_base):
    base, _ = facade_base
    structure = build_structure(base, cache=False)
    assert len(structure) > 300
    assert (structure.points_per_image(len(base)) > 50).all()  # every image holds points
    off_plane = np.abs(structure.xyz[:, 0] - FACADE_X)
    assert np.median(off_plane) < 0.02 and np.percentile(off_plane, 95) < 0.1


def test_a_query_between_base_images_is_localised_to_centimetres(facade_base):
    base, tex = facade_base
    locator = StructureLocator(build_structure(base, cache=False), K)
    R_true, t_true = yawed(4.0), np.array([0.3, 2.4, 1.3])
    pose = locator.locate(view(tex, R_true, t_true), [2, 3])
    assert pose.ok, pose.reason
    assert pose.n_inliers >= 60 and pose.rms_px < 1.0
    assert np.linalg.norm(pose.t_wc - t_true) < 0.05
    angle = np.degrees(np.arccos(np.clip((np.trace(pose.R_wc.T @ R_true) - 1) / 2, -1, 1)))
    assert angle < 0.5
    # grey queries work the same
    grey = cv2.cvtColor(view(tex, R_true, t_true), cv2.COLOR_RGB2GRAY)
    assert np.linalg.norm(locator.locate(grey, [2, 3]).t_wc - t_true) < 0.05


def test_a_query_of_another_place_gives_no_pose_and_says_why(facade_base):
    base, _ = facade_base
    locator = StructureLocator(build_structure(base, cache=False), K)
    elsewhere = view(texture(seed=1), R_SIDEWAYS, np.array([0.0, 2.0, 1.5]))
    pose = locator.locate(elsewhere, [1, 2, 3])
    assert not pose.ok and pose.t_wc is None and pose.reason
    blank = locator.locate(np.zeros((240, 320, 3), np.uint8), [2])
    assert not blank.ok and blank.n_matches == 0


def test_the_cache_is_reused_and_refreshed_when_a_setting_changes(facade_base, monkeypatch):
    base, _ = facade_base
    first = build_structure(base)
    assert (base.root / "cache" / "structure_sift.npz").is_file()
    import geoseg.reloc.base_structure as bs

    def no_detection(*args, **kwargs):
        raise AssertionError("the cached points should have been read")

    monkeypatch.setattr(bs, "detect", no_detection)
    again = build_structure(base)
    np.testing.assert_array_equal(again.xyz, first.xyz)
    with pytest.raises(AssertionError, match="cached"):  # another setting: triangulated again
        build_structure(base, StructureConfig(min_parallax_deg=3.0))


def test_neighbours_are_near_and_look_the_same_way():
    t_wc = np.array([[0.0, 0, 0], [0, 4, 0], [0, 30, 0], [0, 2, 0]])
    R_wc = np.stack([R_SIDEWAYS, R_SIDEWAYS, R_SIDEWAYS, yawed(90.0)])
    assert neighbour_pairs(R_wc, t_wc, StructureConfig()) == [(0, 1)]


def test_bad_input_is_refused(facade_base, tmp_path):
    base, _ = facade_base
    with pytest.raises(GeosegError, match="ratio"):
        StructureConfig(ratio=1.5)
    with pytest.raises(GeosegError, match="min_inliers"):
        StructureConfig(min_inliers=0)
    with pytest.raises(GeosegError, match="K"):
        StructureLocator(build_structure(base, cache=False), np.eye(2))
    no_camera = load_image_base(base.root)
    no_camera.K = None
    with pytest.raises(GeosegError, match="camera.json"):
        build_structure(no_camera, cache=False)


def test_the_localizer_takes_the_pose_from_the_points_and_falls_back_without_them(facade_base):
    from geoseg.reloc.localizer import Localizer

    base, tex = facade_base
    localizer = Localizer.from_base(
        base, embedding="thumbnail", relative_pose="essential", structure=True, cache=False
    )
    t_true = np.array([0.2, 3.3, 1.5])
    here, elsewhere = view(tex, yawed(-3.0), t_true), view(texture(seed=2), R_SIDEWAYS, t_true)
    placed, lost = localizer.localize([here, elsewhere], sequence=None)
    assert placed.position["method"] == "structure"
    assert np.linalg.norm(placed.xyz - t_true) < 0.05
    assert placed.position["n_inliers"] >= 60
    # the relative poses are not needed once the points placed the query
    assert all(not m["relative_pose"]["ok"] for m in placed.matches)
    assert lost.position["method"] != "structure" and lost.position["structure_reason"]


def test_geoseg_localize_structure_prints_and_writes_the_pose(facade_base, tmp_path, capsys):
    from geoseg_cli.cli import main

    base, tex = facade_base
    t_true = np.array([0.0, 1.6, 1.4])
    query = tmp_path / "q.png"
    cv2.imwrite(str(query), cv2.cvtColor(view(tex, yawed(2.0), t_true), cv2.COLOR_RGB2BGR))
    out = tmp_path / "res.json"
    args = ["localize", str(query), "--base", str(base.root), "--embedding", "thumbnail"]
    args += ["--relative-pose", "essential", "--structure", "--no-cache", "--out", str(out)]
    assert main(args) == 0
    assert "on the base's points" in capsys.readouterr().out
    (result,) = json.loads(out.read_text())["queries"]
    assert result["position"]["method"] == "structure"
    assert np.linalg.norm(np.array(result["position"]["xyz"]) - t_true) < 0.05
    assert np.asarray(result["position"]["R_wc"]).shape == (3, 3)
