"""BAL files: round trip, conversion to the OpenCV convention, undistortion, a real file."""

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.ba.solvers.lm import BAObjective, LMConfig, levenberg_marquardt
from slam_bridge.ba.state import BAState
from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.geometry.camera import project
from slam_bridge.testing.bal import (
    BALProblem,
    bal_project,
    bal_to_calibrated,
    poses_to_bal,
    read_bal,
    undistort_bal,
    write_bal,
)


def _bal_from_scene(scene, k1=-0.05, k2=0.01, noise=0.0, seed=0):
    r, t = poses_to_bal(scene.R_wc, scene.t_wc)
    C = r.shape[0]
    f = scene.K[0, 0]
    cams = np.column_stack([r, t, np.full(C, f), np.full(C, k1), np.full(C, k2)])
    xy = bal_project(cams[scene.obs_cameras], scene.X_w[scene.obs_points])
    xy += np.random.default_rng(seed).normal(scale=noise, size=xy.shape)
    return BALProblem(cams, scene.X_w.copy(), scene.obs_cameras, scene.obs_points, xy)


def _redistort(cal, uv):
    """Our pixels -> BAL observation axes, with BAL's distortion of each observation's camera."""
    oc = cal.obs_cameras
    f = cal.K[oc, 0, 0]
    p = np.column_stack([uv[:, 0], -uv[:, 1]]) / f[:, None]
    n2 = np.sum(p * p, axis=1)
    return (f * (1 + cal.k1[oc] * n2 + cal.k2[oc] * n2 * n2))[:, None] * p


def test_round_trip(tmp_path, street):
    bal = _bal_from_scene(street, noise=0.5)
    path = write_bal(tmp_path / "scene.txt", bal)
    back = read_bal(path)
    for name in ("cameras", "points", "obs_cameras", "obs_points", "obs_xy"):
        np.testing.assert_array_equal(getattr(back, name), getattr(bal, name))
    assert back.cost() == pytest.approx(bal.cost())


def test_conversion_matches_bal_formula(street):
    bal = _bal_from_scene(street, noise=0.7)
    cal = bal_to_calibrated(bal)
    # the converted cameras are the scene's (OpenCV convention) cameras
    np.testing.assert_allclose(cal.R_wc, street.R_wc, atol=1e-12)
    np.testing.assert_allclose(cal.t_wc, street.t_wc, atol=1e-12)
    uv_hat, _, ok = project(
        cal.K[cal.obs_cameras],
        cal.R_wc[cal.obs_cameras],
        cal.t_wc[cal.obs_cameras],
        cal.X_w[cal.obs_points],
    )
    assert ok.all()
    pred_bal = bal_project(bal.cameras[bal.obs_cameras], bal.points[bal.obs_points])
    np.testing.assert_allclose(_redistort(cal, uv_hat), pred_bal, rtol=1e-10, atol=1e-9)
    # undistorted observations re-distort to the file's observations
    np.testing.assert_allclose(_redistort(cal, cal.uv), bal.obs_xy, rtol=1e-10, atol=1e-9)
    # without distortion the residuals are BAL's, y negated
    bal0 = _bal_from_scene(street, k1=0.0, k2=0.0, noise=0.7)
    cal0 = bal_to_calibrated(bal0)
    state = BAState(cal0.R_wc, cal0.t_wc, cal0.X_w)
    f = ReprojectionFactor(cal0.K, cal0.obs_cameras, cal0.obs_points, cal0.uv)
    assert f.cost(state) == pytest.approx(bal0.cost(), rel=1e-10)
    r, _ = f.residuals(state)
    r_bal = bal_project(bal0.cameras[bal0.obs_cameras], bal0.points[bal0.obs_points]) - bal0.obs_xy
    np.testing.assert_allclose(r, np.column_stack([r_bal[:, 0], -r_bal[:, 1]]), atol=1e-9)


def test_undistort_inverts_polynomial():
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.5, 0.5, size=(50, 2))
    f = rng.uniform(400, 900, 50)
    k1, k2 = rng.uniform(-0.2, 0.2, 50), rng.uniform(-0.05, 0.05, 50)
    n2 = np.sum(p * p, axis=1)
    xy = (f * (1 + k1 * n2 + k2 * n2 * n2))[:, None] * p
    np.testing.assert_allclose(undistort_bal(xy, f, k1, k2), f[:, None] * p, atol=1e-9)


def test_bad_files(tmp_path):
    (tmp_path / "short.txt").write_text("2 1 3\n0 0 1.0 2.0\n")
    with pytest.raises(GeosegError, match="expected"):
        read_bal(tmp_path / "short.txt")
    (tmp_path / "nan.txt").write_text(
        "1 1 1\n0 0 nan 2.0\n" + "0\n" * 6 + "1\n0\n0\n" + "0\n0\n1\n"
    )
    with pytest.raises(GeosegError, match="NaN"):
        read_bal(tmp_path / "nan.txt")
    with pytest.raises(GeosegError):
        read_bal(tmp_path / "missing.txt")


def test_dubrovnik_from_gtsam():
    gtsam = pytest.importorskip("gtsam")
    path = gtsam.findExampleDataFile("dubrovnik-3-7-pre")
    bal = read_bal(path)
    assert (bal.cameras.shape[0], bal.points.shape[0], bal.obs_cameras.size) == (3, 7, 19)
    cal = bal_to_calibrated(bal)
    sfm = gtsam.SfmData.FromBalFile(path)
    for i in range(3):
        pose = sfm.camera(i).pose()
        np.testing.assert_allclose(pose.rotation().matrix(), cal.R_wc[i], atol=1e-9)
        np.testing.assert_allclose(pose.translation(), cal.t_wc[i], atol=1e-9)
    # our calibrated BA decreases the (undistorted) reprojection cost with 2 cameras fixed
    fixed = np.array([True, True, False])
    state = BAState(cal.R_wc, cal.t_wc, cal.X_w, camera_fixed=fixed)
    f = ReprojectionFactor(cal.K, cal.obs_cameras, cal.obs_points, cal.uv)
    res = levenberg_marquardt(BAObjective([f]), state, LMConfig(max_iterations=30))
    assert res.cost <= res.initial_cost
    assert np.all(np.isfinite(res.state.X_w))


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("neg.txt", b"-1 1 1\n0 0 1 2\n", "negative count"),
        ("negm.txt", b"1 1 -2\n", "negative count"),
        ("float.txt", b"1.5 1 1\n", "3 integer counts"),
        ("trailing.txt", b"1 1 1\n0 0 1 2\n" + b"0\n" * 6 + b"1\n0\n0\n0\n0\n1\n7 8\n", "trailing"),
        ("binary.txt", bytes(range(256)) * 4, "binary"),
        ("corrupt.bz2", b"BZh91AY&SY" + b"\x00" * 40, "corrupt or truncated"),
        ("corrupt.gz", b"\x1f\x8b\x08\x00" + b"\xff" * 40, "corrupt or truncated"),
        (
            "index.txt",
            b"1 1 1\n3 0 1 2\n" + b"0\n" * 6 + b"1\n0\n0\n0\n0\n1\n",
            "index out of range",
        ),
        ("inf.txt", b"1 1 1\n0 0 1 2\n" + b"0\n" * 6 + b"1\n0\n0\n0\n0\ninf\n", "NaN or infinite"),
    ],
)
def test_bad_bal_files_name_the_file_and_the_problem(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(GeosegError, match=message) as info:
        read_bal(path)
    assert name in str(info.value)


def test_truncated_bz2_is_a_clear_error(tmp_path, street):
    import bz2

    good = write_bal(tmp_path / "p.txt", _bal_from_scene(street))
    data = bz2.compress(good.read_bytes())
    (tmp_path / "p.txt.bz2").write_bytes(data[: len(data) // 2])
    with pytest.raises(GeosegError, match="p.txt.bz2.*corrupt or truncated"):
        read_bal(tmp_path / "p.txt.bz2")
