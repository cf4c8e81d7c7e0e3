"""The COLMAP peer (``bench/colmap_peer.py``): a known-answer run on a tiny rendered drive,
COLMAP's pose convention, the GPS alignment alone, and the errors. Skipped without pycolmap
(the ``bench`` extra)."""

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from geoseg.errors import GeosegError  # noqa: E402
from geoseg.synth import build_world, drive, render  # noqa: E402
from slam_bridge.errors import SlamError  # noqa: E402
from slam_bridge.geometry.lie import so3_exp, so3_log  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

# the SLAM tests' tiny world (tests/slam_bridge/slam/conftest.py)


def _load_peer():
    spec = importlib.util.spec_from_file_location("colmap_peer", ROOT / "bench" / "colmap_peer.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


peer = _load_peer()


def _angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """``(N,)`` angles of ``R_a^T R_b``, degrees."""
    return np.array([np.degrees(np.linalg.norm(so3_log(a.T @ b))) for a, b in zip(R_a, R_b)])


@pytest.fixture(scope="module")
def sequence(make_tiny_world):
    """17 frames of a 320x240 drive, one every ~1.5 m (a straight street on a slope)."""
    world = build_world(make_tiny_world())
    traj = drive(world, length_m=24.0, fps=11.0 / 1.5, seed=1, image_size=(320, 240))
    frames = [
        render(world, traj.K, traj.R_wc[i], traj.t_wc[i], traj.image_size).rgb
        for i in range(len(traj))
    ]
    return traj, frames


@pytest.fixture(scope="module")
def run(sequence, tmp_path_factory):
    """The peer aligned to the TRUE optical centres, a third of them missing (no fix)."""
    traj, frames = sequence
    targets = traj.t_wc.copy()
    targets[1::3] = np.nan
    work = tmp_path_factory.mktemp("colmap")
    return peer.colmap_peer(frames, traj.K, work, targets), targets, work


def test_known_answer_on_a_rendered_drive(sequence, run):
    traj, _ = sequence
    res, targets, _ = run
    n = len(traj)
    assert res.R_wc.shape == (n, 3, 3) and res.t_wc.shape == (n, 3) and res.registered.shape == (n,)
    assert res.registered.mean() >= 0.9
    assert res.num_models >= 1 and res.num_points > 100
    ok = res.registered
    assert np.isnan(res.t_wc[~ok]).all() and np.isfinite(res.t_wc[ok]).all()
    # positions: centimetres to a decimetre after the similarity
    err_t = np.linalg.norm(res.t_wc[ok] - traj.t_wc[ok], axis=1)
    assert err_t.max() < 0.25 and np.median(err_t) < 0.1, err_t
    # rotations: the up pin maps the cameras' mean -y onto +z, but the true cameras are tilted
    # by the street's slope (~0.9 deg here): within 1.5 deg of the truth ...
    assert _angle_deg(res.R_wc[ok], traj.R_wc[ok]).max() < 1.5
    # ... and within 0.5 deg of the truth aligned the same way (the pin's bias cancels)
    truth = peer.align_to_gps(traj.R_wc, traj.t_wc, targets)
    assert _angle_deg(res.R_wc[ok], truth.R_wc[ok]).max() < 0.5
    assert np.linalg.norm(res.t_wc[ok] - truth.t_wc[ok], axis=1).max() < 0.25
    # the fit skipped the rows without a target
    assert not res.alignment.used[1::3].any() and res.alignment.used[0::3][ok[0::3]].all()
    assert res.alignment.rms_m < 0.1
    # timings: the three COLMAP stages make the wall time; the alignment is apart
    assert set(res.seconds) == {"write", "extract", "match", "map", "align"}
    stages = res.seconds["extract"] + res.seconds["match"] + res.seconds["map"]
    assert res.wall_seconds == pytest.approx(stages)
    assert res.raw.options["camera"].startswith("PINHOLE")


def test_colmap_convention_is_converted_to_camera_to_world(sequence, run):
    """The poses against COLMAP's own model (projection centres, projections), and against the
    truth without any alignment: relative rotations and motion directions are gauge-free."""
    traj, _ = sequence
    res, _, _ = run
    raw = res.raw
    model = pycolmap.Reconstruction(raw.model_dir)
    names = {f"{i:06d}.png": i for i in range(len(traj))}
    K = traj.K
    assert model.num_reg_images() == raw.registered.sum()
    for image_id in model.reg_image_ids():
        image = model.image(image_id)
        i = names[image.name]
        np.testing.assert_allclose(raw.t_wc[i], np.ravel(image.projection_center()), atol=1e-9)
        ids = [p.point3D_id for p in image.points2D if p.has_point3D()][:20]
        X = np.array([model.point3D(j).xyz for j in ids])
        X_c = (X - raw.t_wc[i]) @ raw.R_wc[i]  # R_wc^T (X - t_wc), row-wise
        uv = X_c @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        assert (X_c[:, 2] > 0).all()
        theirs = np.array([image.project_point(x) for x in X])  # COLMAP: pixel centre + 0.5
        np.testing.assert_allclose(uv + 0.5, theirs, atol=1e-6)
    # the camera of the model is ours, unrefined
    (camera,) = model.cameras.values()
    assert camera.model_name == "PINHOLE"
    np.testing.assert_allclose(camera.params, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
    # no alignment: the rotation from the first camera to each is the truth's
    ok = np.flatnonzero(raw.registered)
    a = ok[0]
    rel = np.einsum("ji,njk->nik", raw.R_wc[a], raw.R_wc[ok])  # R_a^T R_i
    rel_gt = np.einsum("ji,njk->nik", traj.R_wc[a], traj.R_wc[ok])
    assert _angle_deg(rel, rel_gt).max() < 0.5
    # the direction of motion seen from the first camera is the truth's (scale-free)
    far = ok[np.linalg.norm(traj.t_wc[ok] - traj.t_wc[a], axis=1) > 3.0]
    d = (raw.t_wc[far] - raw.t_wc[a]) @ raw.R_wc[a]
    d_gt = (traj.t_wc[far] - traj.t_wc[a]) @ traj.R_wc[a]
    cos = np.sum(d * d_gt, axis=1) / np.linalg.norm(d, axis=1) / np.linalg.norm(d_gt, axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0


def test_same_seed_same_poses(sequence, run, tmp_path):
    """One thread and a seed: a second run (in a used work folder) repeats the poses."""
    traj, frames = sequence
    res, _, work = run
    again = peer.reconstruct(frames, traj.K, work)
    np.testing.assert_array_equal(again.registered, res.raw.registered)
    np.testing.assert_array_equal(again.t_wc, res.raw.t_wc)
    np.testing.assert_array_equal(again.R_wc, res.raw.R_wc)


def _level_drive(n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """``(R_wc (n, 3, 3), t_wc (n, 3))`` of level forward cameras along a curve that climbs."""
    R_level = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # looking +y
    yaw = np.linspace(0.0, 0.8, n)
    R_wc = np.stack([so3_exp(np.array([0.0, 0.0, y])) @ R_level for y in yaw])
    t_wc = np.column_stack([10 * np.sin(yaw), 15 * yaw, 0.2 * yaw + 1.5])
    return R_wc, t_wc


def _similarity():
    s = 0.37
    R = so3_exp(np.array([0.3, -1.1, 2.0]))
    T = np.array([5.0, -2.0, 7.0])
    return s, R, T


def _to_colmap_frame(R_wc, t_wc, s, R, T):
    """The poses in a frame where ``world = s R colmap + T``."""
    return np.einsum("ji,njk->nik", R, R_wc), (t_wc - T) @ R / s


def test_align_to_gps_recovers_a_known_similarity():
    R_w, t_w = _level_drive()
    s, R, T = _similarity()
    R_c, t_c = _to_colmap_frame(R_w, t_w, s, R, T)
    R_c[4], t_c[4] = np.nan, np.nan  # not registered
    targets = t_w.copy()
    targets[[2, 7]] = np.nan  # no fix
    for up_axis in (True, False):
        out = peer.align_to_gps(R_c, t_c, targets, up_axis=up_axis)
        assert out.s == pytest.approx(s, rel=1e-9)
        np.testing.assert_allclose(out.R, R, atol=1e-9)
        np.testing.assert_allclose(out.T, T, atol=1e-8)
        keep = np.ones(len(t_w), dtype=bool)
        keep[4] = False
        np.testing.assert_allclose(out.t_wc[keep], t_w[keep], atol=1e-8)
        np.testing.assert_allclose(out.R_wc[keep], R_w[keep], atol=1e-9)
        assert np.isnan(out.t_wc[4]).all() and np.isnan(out.R_wc[4]).all()
        assert out.used.tolist() == [i not in (2, 4, 7) for i in range(len(t_w))]
        assert out.rms_m < 1e-8


def test_align_to_gps_antenna_offset_and_robust_fit():
    R_w, t_w = _level_drive()
    s, R, T = _similarity()
    R_c, t_c = _to_colmap_frame(R_w, t_w, s, R, T)
    # GPS of an antenna 1 m behind the camera, on the road: xy the antenna's, z the camera's
    antenna_c = np.array([0.0, 1.5, -1.0])
    targets = t_w.copy()
    targets[:, :2] += np.einsum("nij,j->ni", R_w, antenna_c)[:, :2]
    out = peer.align_to_gps(R_c, t_c, targets, antenna_c=antenna_c)
    np.testing.assert_allclose(out.t_wc, t_w, atol=1e-8)
    assert out.rms_m < 1e-8
    # without the offset the fit is off by about the metre
    assert np.abs(peer.align_to_gps(R_c, t_c, targets).t_wc - t_w).max() > 0.3
    # a wild pose (an image registered 40 m off): least squares fails, the robust fit does not
    t_bad = t_c.copy()
    t_bad[6] += np.array([40.0, 0.0, 0.0]) / s
    plain = peer.align_to_gps(R_c, t_bad, t_w)
    assert np.linalg.norm(plain.t_wc - t_w, axis=1).max() > 1.0
    robust = peer.align_to_gps(R_c, t_bad, t_w, max_error_m=0.5)
    assert robust.used.tolist() == [i != 6 for i in range(len(t_w))]
    good = robust.used
    np.testing.assert_allclose(robust.t_wc[good], t_w[good], atol=1e-8)
    assert np.linalg.norm(robust.t_wc[6] - t_w[6]) == pytest.approx(40.0, rel=1e-6)


def test_align_to_gps_errors():
    R_w, t_w = _level_drive(5)
    targets = t_w.copy()
    targets[2:] = np.nan
    with pytest.raises(SlamError, match="2 registered pose.*at least 3"):
        peer.align_to_gps(R_w, t_w, targets)
    R_nan, t_nan = R_w.copy(), t_w.copy()
    R_nan[:3], t_nan[:3] = np.nan, np.nan
    with pytest.raises(SlamError, match="2 registered"):
        peer.align_to_gps(R_nan, t_nan, t_w)
    with pytest.raises(GeosegError, match="targets_w"):
        peer.align_to_gps(R_w, t_w, t_w[:4])
    with pytest.raises(GeosegError, match="max_error_m"):
        peer.align_to_gps(R_w, t_w, t_w, max_error_m=0.0)
    scattered = t_w + np.random.default_rng(0).normal(scale=20.0, size=t_w.shape)
    with pytest.raises(SlamError, match="within max_error_m"):
        peer.align_to_gps(R_w, t_w, scattered, max_error_m=0.01)


def test_reconstruct_errors(tmp_path):
    K = np.array([[200.0, 0.0, 79.5], [0.0, 200.0, 59.5], [0.0, 0.0, 1.0]])
    gray = np.full((120, 160, 3), 128, dtype=np.uint8)
    with pytest.raises(SlamError, match="at least 2 images"):
        peer.reconstruct([gray], K, tmp_path)
    with pytest.raises(SlamError, match="K: expected a pinhole"):
        peer.reconstruct([gray, gray], K * np.array([1, 1, 0])[:, None], tmp_path)
    with pytest.raises(SlamError, match="uint8"):
        peer.reconstruct([gray, gray.astype(np.float32)], K, tmp_path)
    with pytest.raises(SlamError, match="no such file"):
        peer.reconstruct([tmp_path / "a.png", tmp_path / "b.png"], K, tmp_path)
    with pytest.raises(SlamError, match="overlap"):
        peer.reconstruct([gray, gray], K, tmp_path, overlap=0)
    # featureless images (given as files): COLMAP builds no model
    files = []
    for i in range(3):
        files.append(tmp_path / f"frame_{i}.png")
        cv2.imwrite(str(files[-1]), gray)
    with pytest.raises(SlamError, match="COLMAP registered no model from 3 images"):
        peer.reconstruct(files, K, tmp_path / "work")
    assert sorted(p.name for p in (tmp_path / "work" / "images").iterdir()) == [
        "000000.png",
        "000001.png",
        "000002.png",
    ]
