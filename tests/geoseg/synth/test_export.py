"""The render stage: files, formats, skip-if-done, and the unwritable-directory guard."""

from __future__ import annotations

import json
import types

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geoseg.errors import ConfigError, GeosegError
from geoseg.synth.export import (
    POSES_HEADER,
    GisConfig,
    drive_frames,
    parse_size,
    render_sequence,
)
from geoseg.synth.world import WorldConfig, build_world

TINY = WorldConfig(blocks_x=1, blocks_y=1, seed=2)


@pytest.fixture(scope="module")
def tiny_world():
    return build_world(TINY)


def _fake_render(calls: list):
    """A stand-in renderer: deterministic arrays of the right shapes and dtypes."""

    def fn(K, R_wc, t_wc, time_s):
        calls.append(time_s)
        w, h = int(round(2 * K[0, 2] + 1)), int(round(2 * K[1, 2] + 1))
        rng = np.random.default_rng(len(calls))
        n = rng.normal(size=(3, h, w)).astype(np.float32)
        n /= np.linalg.norm(n, axis=0)
        labels = rng.integers(0, 8, (h, w)).astype(np.uint8)
        return types.SimpleNamespace(
            rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
            labels=labels,
            normals=n,
            normal_valid=labels != 6,
            depth=rng.uniform(1, 60, (h, w)).astype(np.float32),
            instance=rng.integers(-1, 50, (h, w)).astype(np.int32),
        )

    return fn


def test_render_sequence_writes_the_documented_layout(tmp_path, tiny_world) -> None:
    calls: list = []
    out = render_sequence(
        TINY, tmp_path / "seq", frames=3, image_size=(40, 30), world=tiny_world,
        render_fn=_fake_render(calls), progress=False,
    )  # fmt: skip
    assert out == tmp_path / "seq" and len(calls) == 3
    for sub, n in (("rgb", 3), ("labels", 3), ("labels_color", 3), ("geometry", 3)):
        assert len(list((out / sub).iterdir())) == n
    for name in ("poses.csv", "camera.json", "preview.png", "map.png", "README.txt", "meta.json"):
        assert (out / name).is_file(), name
    gis = out / "gis"
    for name in (
        "buildings_model.ply", "buildings_true.ply", "facades.csv", "buildings_model.json",
        "dem.csv", "dem.geojson", "gps.csv", "odometry.csv", "georeference.json",
    ):  # fmt: skip
        assert (gis / name).is_file(), name
    meta = json.loads((out / "meta.json").read_text())
    assert meta["request"]["frames"] == 3 and meta["request"]["world"]["blocks_x"] == 1
    assert all((out / f).exists() for f in meta["files"])
    assert "z-depth" in (out / "README.txt").read_text()

    # PNGs and npz hold exactly what the renderer returned (frame 1 = the second call)
    frame = _fake_render([None])(np.array([[40.0, 0, 19.5], [0, 40.0, 14.5], [0, 0, 1]]), 0, 0, 0)
    labels = cv2.imread(str(out / "labels" / "000001.png"), cv2.IMREAD_UNCHANGED)
    assert labels.dtype == np.uint8 and np.array_equal(labels, frame.labels)
    rgb = cv2.imread(str(out / "rgb" / "000001.png"))[..., ::-1]
    assert np.array_equal(rgb, frame.rgb)
    geo = np.load(out / "geometry" / "000001.npz")
    assert geo["depth"].dtype == np.float32 and np.array_equal(geo["depth"], frame.depth)
    assert geo["normals"].dtype == np.float16 and geo["normals"].shape == (3, 30, 40)
    np.testing.assert_allclose(geo["normals"], frame.normals, atol=1e-3)
    assert np.array_equal(geo["instance"], frame.instance)
    assert np.array_equal(geo["normal_valid"], frame.normal_valid)


def test_poses_csv_matches_the_trajectory(tmp_path, tiny_world) -> None:
    out = render_sequence(
        TINY, tmp_path, frames=4, image_size=(40, 30), world=tiny_world, rig="tram",
        render_fn=_fake_render([]), progress=False,
    )  # fmt: skip
    traj = drive_frames(tiny_world, 4, rig="tram", seed=TINY.seed, image_size=(40, 30))
    table = np.loadtxt(out / "poses.csv", delimiter=",", skiprows=1)
    header = (out / "poses.csv").read_text().splitlines()[0]
    assert header == POSES_HEADER and table.shape == (4, 23)
    np.testing.assert_allclose(table[:, 1], traj.timestamps, atol=1e-6)
    np.testing.assert_allclose(table[:, 2:5], traj.t_wc, atol=1e-5)
    R_rows = table[:, 9:18].reshape(4, 3, 3)
    np.testing.assert_allclose(R_rows, traj.R_wc, atol=1e-8)
    qw, qx, qy, qz = table[:, 5:9].T
    R_quat = Rotation.from_quat(np.column_stack([qx, qy, qz, qw])).as_matrix()
    np.testing.assert_allclose(R_quat, traj.R_wc, atol=1e-7)
    camera = json.loads((out / "camera.json").read_text())
    np.testing.assert_allclose(camera["K"], traj.K)
    assert camera["rig"] == "tram" and camera["image_size"] == [40, 30]


def test_render_sequence_skips_an_identical_request_only(tmp_path, tiny_world) -> None:
    kwargs = dict(frames=2, image_size=(40, 30), world=tiny_world, progress=False)
    calls: list = []
    render_sequence(TINY, tmp_path, render_fn=_fake_render(calls), **kwargs)
    assert len(calls) == 2
    render_sequence(TINY, tmp_path, render_fn=_fake_render(calls), **kwargs)
    assert len(calls) == 2  # up to date: nothing rendered
    render_sequence(TINY, tmp_path, render_fn=_fake_render(calls), overwrite=True, **kwargs)
    assert len(calls) == 4
    render_sequence(TINY, tmp_path, condition="winter", render_fn=_fake_render(calls), **kwargs)
    assert len(calls) == 6
    kwargs["frames"] = 1  # a shorter render leaves no frame of the longer one behind
    render_sequence(TINY, tmp_path, render_fn=_fake_render(calls), **kwargs)
    assert sorted(p.name for p in (tmp_path / "rgb").iterdir()) == ["000000.png"]
    assert len(list((tmp_path / "geometry").iterdir())) == 1


def test_unwritable_output_directory_fails_before_rendering(tmp_path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    calls: list = []
    with pytest.raises(GeosegError, match="a_file.*not writable"):
        render_sequence(TINY, blocker / "out", frames=2, render_fn=_fake_render(calls))
    assert calls == []


def test_bad_requests_are_named(tmp_path) -> None:
    with pytest.raises(GeosegError, match="condition"):
        render_sequence(TINY, tmp_path, frames=2, condition="monsoon")
    with pytest.raises(GeosegError, match="rig"):
        render_sequence(TINY, tmp_path, frames=2, rig="bike")
    with pytest.raises(GeosegError, match="frames"):
        render_sequence(TINY, tmp_path, frames=0)
    for workers in (0, 65, 1.5, True):
        with pytest.raises(GeosegError, match="workers"):
            render_sequence(TINY, tmp_path, frames=2, workers=workers)
    with pytest.raises(GeosegError, match="workers: a render_fn"):
        render_sequence(TINY, tmp_path, frames=2, workers=2, render_fn=_fake_render([]))
    assert parse_size("64x48") == (64, 48)
    with pytest.raises(ConfigError, match="size"):
        parse_size("64by48")


def test_gis_products_are_seeded_and_shared_between_conditions(tmp_path, tiny_world) -> None:
    kwargs = dict(frames=2, image_size=(40, 30), world=tiny_world, progress=False)
    a = render_sequence(TINY, tmp_path / "a", render_fn=_fake_render([]), **kwargs)
    b = render_sequence(
        TINY, tmp_path / "b", condition="winter", render_fn=_fake_render([]), **kwargs
    )
    c = render_sequence(TINY, tmp_path / "c", seed=9, render_fn=_fake_render([]), **kwargs)
    for name in ("facades.csv", "dem.csv", "gps.csv", "odometry.csv"):
        assert (a / "gis" / name).read_text() == (b / "gis" / name).read_text(), name
    assert (a / "gis" / "facades.csv").read_text() != (c / "gis" / "facades.csv").read_text()


def test_gis_config_overrides(tmp_path, tiny_world) -> None:
    from geoseg.config import load_config

    gis = load_config(GisConfig, None, overrides=["gps.bias_max_m=0.0", "gps.noise_std_m=0.0"])
    out = render_sequence(
        TINY, tmp_path, frames=12, gis=gis, world=tiny_world, image_size=(40, 30),
        render_fn=_fake_render([]), progress=False,
    )  # fmt: skip
    table = np.genfromtxt(out / "gis" / "gps.csv", delimiter=",", names=True)
    valid = table["valid"] == 1
    np.testing.assert_allclose(table["x"][valid], table["true_x"][valid], atol=1e-4)
    with pytest.raises(ConfigError, match="gps.bias_max"):
        load_config(GisConfig, None, overrides=["gps.bias_max=1"])


def test_real_renderer_frames_on_a_tiny_world(tmp_path, tiny_world) -> None:
    out = render_sequence(
        TINY, tmp_path, frames=2, image_size=(48, 36), world=tiny_world, progress=False
    )
    labels = cv2.imread(str(out / "labels" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert labels.shape == (36, 48) and labels.max() < 8
    geo = np.load(out / "geometry" / "000000.npz")
    valid = geo["normal_valid"]
    norms = np.linalg.norm(geo["normals"].astype(np.float32), axis=0)
    np.testing.assert_allclose(norms[valid], 1.0, atol=2e-3)
    assert np.all(geo["depth"][valid] > 0)


def test_render_processes_write_the_same_files_as_one(tmp_path, tiny_world) -> None:
    kwargs = dict(frames=5, image_size=(48, 36), world=tiny_world, progress=False)
    one = render_sequence(TINY, tmp_path / "one", **kwargs)
    two = render_sequence(TINY, tmp_path / "two", workers=2, **kwargs)
    names = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(two) for p in two.rglob("*") if p.is_file())
    frame_dirs = ("rgb", "labels", "labels_color", "geometry")
    compared = [n for n in names if n.parts[0] in frame_dirs or n.name == "poses.csv"]
    assert len(compared) == 5 * 4 + 1
    for name in compared:
        assert (one / name).read_bytes() == (two / name).read_bytes(), name
