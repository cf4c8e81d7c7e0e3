"""The hybrid window (eq. 3.4): bookkeeping, n = 0 reduction, fig. 3.3 structure, Theorem 3.1."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from slam_bridge.ba.normal_equations import assemble
from slam_bridge.ba.solvers.barrier import solve_barrier
from slam_bridge.ba.solvers.lm import LMConfig
from slam_bridge.ba.solvers.schur import latest_camera_covariance
from slam_bridge.ba.state import BAState
from slam_bridge.errors import SlamError
from slam_bridge.factors.gps import GPSFactor
from slam_bridge.factors.pose_graph_dpc import DPCFactor
from slam_bridge.factors.pose_graph_mpc import MPCFactor
from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.geometry.camera import local_window, project
from slam_bridge.geometry.lie import so3_exp
from slam_bridge.slam.hybrid_problem import (
    HybridWindowConfig,
    WindowError,
    build_hybrid_problem,
    hybrid_window,
    minimize_zeta,
)
from slam_bridge.testing.scenes import street_scene


@pytest.fixture(scope="module")
def scene():
    return street_scene(12, points_per_camera=15, noise_px=1.0, seed=2)


def _build(scene, **kw):
    cfg = HybridWindowConfig(**kw)
    return build_hybrid_problem(
        scene.R_wc,
        scene.t_wc,
        scene.X_w,
        scene.K,
        np.arange(scene.R_wc.shape[0]),
        scene.obs_cameras,
        scene.obs_points,
        scene.uv,
        cfg,
    )


# ------------------------------------------------------------------------------- bookkeeping
def test_window_split_and_pose_graph_pairs(scene) -> None:
    w = hybrid_window(np.arange(12), scene.obs_cameras, scene.obs_points, l=8, n=3)
    assert w.keyframes.tolist() == list(range(4, 12))
    assert w.pose_graph_cameras.tolist() == [4, 5, 6]
    assert w.ba_cameras.tolist() == list(range(7, 12))
    assert w.z0 == 3
    # z0 -> z1, z1 -> z2, z2 -> z3, z3 (= z_n) -> z_{n+1}: n + 1 terms when z0 exists (§3.6)
    assert w.pose_graph_pairs.tolist() == [[3, 4], [4, 5], [5, 6], [6, 7]]
    assert 3 in w.fixed_cameras.tolist()
    kept = w.observations
    assert not np.isin(scene.obs_cameras[kept], w.pose_graph_cameras).any()
    assert np.isin(scene.obs_points[kept], w.points).all()
    # every kept point keeps >= 2 observations (its other views may be in the pose-graph window)
    hyb = _build(scene, l=8, n=3)
    counts = np.bincount(hyb.vision[0].points, minlength=hyb.state.num_points)
    assert counts.min() >= 2
    # no z0 when the window starts at the first keyframe: n terms
    w2 = hybrid_window(np.arange(12), scene.obs_cameras, scene.obs_points, l=12, n=3)
    assert w2.z0 is None and w2.pose_graph_pairs.tolist() == [[0, 1], [1, 2], [2, 3]]


def test_pose_graph_rows_keep_the_junction_and_their_own_sigma(scene) -> None:
    """``pose_graph_rows``: the pose-graph cameras keep their rows of the BA window's points
    (and only those); with ``pose_graph_row_sigma`` they form a second reprojection family
    whose whitened residuals are divided by that sigma, and the Hessian memory counts them."""
    from slam_bridge.slam.windows import hessian_bytes

    plain = hybrid_window(np.arange(12), scene.obs_cameras, scene.obs_points, l=8, n=3)
    rows = hybrid_window(
        np.arange(12), scene.obs_cameras, scene.obs_points, l=8, n=3, pose_graph_rows=True
    )
    assert rows.points.tolist() == plain.points.tolist()
    extra = np.setdiff1d(rows.observations, plain.observations)
    assert extra.size > 0 and np.isin(plain.observations, rows.observations).all()
    assert np.isin(scene.obs_cameras[extra], rows.pose_graph_cameras).all()
    assert np.isin(scene.obs_points[extra], rows.points).all()
    expected = np.isin(scene.obs_cameras, rows.pose_graph_cameras) & np.isin(
        scene.obs_points, rows.points
    )
    assert np.flatnonzero(expected).tolist() == extra.tolist()

    one = _build(scene, l=8, n=3, pose_graph_rows=True)
    two = _build(scene, l=8, n=3, pose_graph_rows=True, pose_graph_row_sigma=0.5)
    assert [f.name for f in two.vision[:2]] == ["reprojection", "reprojection_pose_graph"]
    junction = two.vision[1]
    built = np.setdiff1d(one.window.observations, _build(scene, l=8, n=3).window.observations)
    assert junction.sigma == 0.5 and junction.cameras.size == built.size > 0
    assert np.isin(two.camera_ids[junction.cameras], rows.pose_graph_cameras).all()
    r1, _ = one.vision[0].residuals(one.state)
    r0, _ = two.vision[0].residuals(two.state)
    rj, _ = junction.residuals(two.state)
    assert np.sum(r0**2) + 0.25 * np.sum(rj**2) == pytest.approx(np.sum(r1**2))
    # each junction row adds a (pose-graph camera, point) W block: 18 float64 each
    base = _build(scene, l=8, n=3)
    pairs = np.unique(scene.obs_cameras[built] * 10_000 + scene.obs_points[built]).size
    assert hessian_bytes(one) - hessian_bytes(base) == 8 * 18 * pairs
    assert hessian_bytes(two) == hessian_bytes(one)
    with pytest.raises(WindowError, match="pose_graph_row_sigma"):
        HybridWindowConfig(l=8, n=3, pose_graph_row_sigma=0.0)


def test_reprojection_kernel_threshold_is_in_pixels_in_every_family(scene) -> None:
    """The kernel threshold is a pixel error: the thinned pose-graph rows (sigma 0.5) start
    being down-weighted at the same pixel error as the BA window's rows (sigma 1)."""
    prob = _build(
        scene,
        l=8,
        n=3,
        pose_graph_rows=True,
        pose_graph_row_sigma=0.5,
        reprojection_kernel="huber",
        reprojection_kernel_scale=2.45,
    )
    ba_rows, pg_rows = prob.vision[:2]
    for fam in (ba_rows, pg_rows):
        s_in = (np.array([2.4]) / fam.sigma) ** 2  # whitened squared norm of a 2.4 px error
        s_out = (np.array([2.5]) / fam.sigma) ** 2
        assert fam.kernel.weight(s_in)[0] == 1.0
        assert fam.kernel.weight(s_out)[0] < 1.0
    least_squares = _build(scene, l=8, n=3, pose_graph_rows=True, pose_graph_row_sigma=0.5)
    assert least_squares.vision[1].kernel.weight(np.array([1e6]))[0] == 1.0


def test_window_bad_inputs(scene) -> None:
    obs_c, obs_p = scene.obs_cameras, scene.obs_points
    with pytest.raises(WindowError, match="empty"):
        hybrid_window(np.zeros(0, dtype=int), obs_c, obs_p, l=5, n=0)
    with pytest.raises(WindowError, match="at least 3"):
        hybrid_window(np.arange(12), obs_c, obs_p, l=8, n=6)
    with pytest.raises(WindowError):
        HybridWindowConfig(l=10, n=8)
    with pytest.raises(WindowError):
        HybridWindowConfig(pose_graph="sim3")
    with pytest.raises(WindowError, match="observes no point"):
        hybrid_window(np.arange(20, 25), obs_c, obs_p, l=5, n=0)
    assert issubclass(WindowError, SlamError)


def test_window_nan_observation_and_coincident_cameras(scene) -> None:
    uv = scene.uv.copy()
    uv[3, 0] = np.nan
    with pytest.raises(GeosegError, match="uv"):
        build_hybrid_problem(
            scene.R_wc,
            scene.t_wc,
            scene.X_w,
            scene.K,
            np.arange(12),
            scene.obs_cameras,
            scene.obs_points,
            uv,
            HybridWindowConfig(l=8, n=2),
        )
    t = np.repeat(scene.t_wc[:1], 12, axis=0)  # all cameras at one position
    for kind in ("dpc", "mpc"):
        with pytest.raises(SlamError, match="optical centre"):
            build_hybrid_problem(
                scene.R_wc,
                t,
                scene.X_w,
                scene.K,
                np.arange(12),
                scene.obs_cameras,
                scene.obs_points,
                scene.uv,
                HybridWindowConfig(l=8, n=2, pose_graph=kind),
            )


# ------------------------------------------------------------------------------ n = 0 == k-BA
def test_n0_equals_plain_barrier_ba(scene) -> None:
    hyb = _build(scene, l=8, n=0)
    assert len(hyb.vision) == 1  # reprojection only: no pose-graph term at n = 0
    # the plain k-BA window, built independently with the core's local_window
    lw = local_window(np.arange(12), scene.obs_cameras, scene.obs_points, 8)
    ids = np.concatenate([lw.fixed_cameras, lw.free_cameras])
    fixed = np.arange(ids.size) < lw.fixed_cameras.size
    state = BAState(scene.R_wc[ids], scene.t_wc[ids], scene.X_w[lw.points], camera_fixed=fixed)
    cam_of = {int(c): i for i, c in enumerate(ids)}
    o = lw.observations
    rep = ReprojectionFactor(
        scene.K,
        np.array([cam_of[int(c)] for c in scene.obs_cameras[o]]),
        np.searchsorted(lw.points, scene.obs_points[o]),
        scene.uv[o],
    )
    np.testing.assert_array_equal(hyb.camera_ids, ids)
    target = scene.t_wc[11, :2] + [0.2, 0.6]
    res_h = solve_barrier(hyb.vision, [GPSFactor([hyb.latest_camera], target[None])], hyb.state)
    res_p = solve_barrier([rep], [GPSFactor([ids.size - 1], target[None])], state)
    np.testing.assert_allclose(res_h.state.t_wc, res_p.state.t_wc, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res_h.state.R_wc, res_p.state.R_wc, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res_h.state.X_w, res_p.state.X_w, rtol=0, atol=1e-12)
    assert res_h.zeta == pytest.approx(res_p.zeta, rel=1e-14)


# ------------------------------------------------------------------------------- fig. 3.3
@pytest.mark.parametrize("kind", ["dpc", "mpc"])
def test_hessian_structure_fig_3_3(scene, kind: str) -> None:
    """2 pose-graph + 3 BA cameras (fig. 3.3): pose-graph cameras have no point block and the
    only camera-camera blocks join successive cameras."""
    hyb = _build(scene, l=5, n=2, pose_graph=kind)
    assert isinstance(hyb.vision[1], DPCFactor if kind == "dpc" else MPCFactor)
    moved = hyb.state.retract(
        np.random.default_rng(0).normal(scale=1e-3, size=(hyb.state.free_cameras.size, 6)),
        np.zeros((hyb.state.free_points.size, 3)),
    )
    ne = assemble(hyb.vision, moved)
    cmap = hyb.state.camera_index_map
    z = [cmap[hyb.camera_index(int(k))] for k in hyb.window.keyframes]  # z_1..z_5 free indices
    assert {tuple(p) for p in ne.pairs.tolist()} == {(z[0], z[1]), (z[1], z[2])}
    assert not np.isin(ne.W_cameras, z[:2]).any()  # pose-graph cameras see no point
    assert np.isin(z[2:], ne.W_cameras).all()  # BA cameras do
    H, _ = ne.dense()
    C = len(z)
    for a in range(C):
        for b in range(C):
            blk = H[6 * a : 6 * a + 6, 6 * b : 6 * b + 6]
            if a != b and not ({a, b} <= {0, 1, 2} and abs(a - b) == 1):
                assert np.all(blk == 0), (a, b)
            elif a != b:
                assert np.any(blk != 0), (a, b)


# ------------------------------------------------------------------------------- Theorem 3.1
def _side_scene(C: int = 12, seed: int = 0):
    """Side-looking tram camera (good parallax): cameras along x, looking at a facade y = 8."""
    rng = np.random.default_rng(seed)
    R_side = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z_c = +y_w
    R = so3_exp(rng.normal(scale=0.01, size=(C, 3))) @ R_side
    t = np.stack([np.arange(C, dtype=float), np.zeros(C), np.full(C, 2.0)], axis=1)
    X = np.stack(
        [rng.uniform(-2, C + 1, 40 * C), rng.uniform(7.0, 9.0, 40 * C), rng.uniform(0, 6, 40 * C)],
        axis=1,
    )
    K = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
    cams, pts, uvs = [], [], []
    for c in range(C):
        uv, _, front = project(K, R[c], t[c], X)
        ok = front & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
        idx = np.flatnonzero(ok)
        cams.append(np.full(idx.size, c))
        pts.append(idx)
        uvs.append(uv[idx])
    return R, t, X, K, np.concatenate(cams), np.concatenate(pts), np.concatenate(uvs)


def _latest_cov(R, t, X, K, oc, op, uv, l: int, n: int) -> np.ndarray:
    hyb = build_hybrid_problem(
        R, t, X, K, np.arange(R.shape[0]), oc, op, uv, HybridWindowConfig(l=l, n=n)
    )
    return latest_camera_covariance(assemble(hyb.vision, hyb.state))


def _assert_grows(C_small: np.ndarray, C_big: np.ndarray) -> None:
    """``x^T C_big^-1 x <= x^T C_small^-1 x`` for all x (eq. 3.6) <=> C_big - C_small PSD."""
    ev = np.linalg.eigvalsh(np.linalg.inv(C_small) - np.linalg.inv(C_big))
    assert ev.min() >= -1e-9 * np.abs(ev).max()
    assert ev.max() > 0


def test_theorem_3_1_pose_graph_camera() -> None:
    """Adding a camera to the pose-graph window (no point added) never shrinks the latest
    camera's covariance."""
    data = _side_scene()
    prev = _latest_cov(*data, l=6, n=2)
    for l, n in ((7, 3), (8, 4), (9, 5)):
        cur = _latest_cov(*data, l=l, n=n)
        _assert_grows(prev, cur)
        prev = cur


def test_theorem_3_1_ba_camera() -> None:
    """Freeing a fixed camera that only sees points already in the problem (adding it to the BA
    window without adding points) never shrinks the latest camera's covariance."""
    R, t, X, K, oc, op, uv = _side_scene()
    hyb = build_hybrid_problem(R, t, X, K, np.arange(12), oc, op, uv, HybridWindowConfig(l=5, n=0))
    st = hyb.state
    fixed_idx = np.flatnonzero(st.camera_fixed)
    assert fixed_idx.size >= 3
    base = latest_camera_covariance(assemble(hyb.vision, st))
    freed = st.camera_fixed.copy()
    freed[fixed_idx[-1]] = False  # the newest fixed observer joins the BA window
    st2 = BAState(st.R_wc, st.t_wc, st.X_w, camera_fixed=freed)
    _assert_grows(base, latest_camera_covariance(assemble(hyb.vision, st2)))


# ------------------------------------------------------------------------- hybrid fusion run
@pytest.mark.parametrize("kind", ["dpc", "mpc"])
def test_hybrid_gps_fusion(kind: str) -> None:
    R, t, X, K, oc, op, uv0 = _side_scene(seed=1)
    uv = uv0 + np.random.default_rng(3).normal(scale=0.5, size=uv0.shape)
    hyb = build_hybrid_problem(
        R, t, X, K, np.arange(12), oc, op, uv, HybridWindowConfig(l=10, n=5, pose_graph=kind)
    )
    hyb, _ = minimize_zeta(hyb, LMConfig(max_iterations=15))
    target = hyb.state.t_wc[-1, :2] + [0.3, 0.5]
    res = solve_barrier(hyb.vision, [GPSFactor([hyb.latest_camera], target[None])], hyb.state)
    assert res.zeta < res.t
    before = np.linalg.norm(hyb.state.t_wc[-1, :2] - target)
    assert np.linalg.norm(res.state.t_wc[-1, :2] - target) < before
    assert np.all(np.isfinite(res.state.t_wc))
    R_all, t_all, X_all = R.copy(), t.copy(), X.copy()
    hyb.write_back(res.state, R_all, t_all, X_all)
    np.testing.assert_array_equal(t_all[11], res.state.t_wc[-1])
    np.testing.assert_array_equal(t_all[: hyb.window.keyframes[0]], t[: hyb.window.keyframes[0]])
    np.testing.assert_array_equal(X_all[hyb.point_ids], res.state.X_w)


def test_points_behind_every_camera_are_dropped(scene, caplog) -> None:
    X = scene.X_w.copy()
    hyb0 = _build(scene, l=6, n=2)
    bad = int(hyb0.point_ids[0])
    X[bad] = scene.t_wc[11] - [20.0, 0.0, 0.0]  # behind every forward-looking camera
    with caplog.at_level("WARNING", logger="slam_bridge.slam.hybrid_problem"):
        hyb = build_hybrid_problem(
            scene.R_wc,
            scene.t_wc,
            X,
            scene.K,
            np.arange(12),
            scene.obs_cameras,
            scene.obs_points,
            scene.uv,
            HybridWindowConfig(l=6, n=2),
        )
    assert hyb.dropped_points.tolist() == [bad]
    assert bad not in hyb.point_ids.tolist()
    assert "behind every camera" in caplog.text
    assert hyb.vision[0].evaluate(hyb.state).n_invalid == 0
    X_all = np.tile(scene.t_wc[11] - [20.0, 0.0, 0.0], (X.shape[0], 1))
    with pytest.raises(WindowError, match="every point"):
        build_hybrid_problem(
            scene.R_wc,
            scene.t_wc,
            X_all,
            scene.K,
            np.arange(12),
            scene.obs_cameras,
            scene.obs_points,
            scene.uv,
            HybridWindowConfig(l=6, n=2),
        )


def test_mpc_pair_with_too_few_matches_falls_back_to_dpc(scene) -> None:
    """A pose-graph pair sharing < mpc_min_correspondences points gets a DPC link (no error)."""
    oc, op = scene.obs_cameras.copy(), scene.obs_points.copy()
    # keyframes 5 and 6 (a pose-graph pair of l = 8, n = 3) keep only 3 shared points
    shared = np.intersect1d(op[oc == 5], op[oc == 6])
    assert shared.size > 3
    drop = (oc == 6) & np.isin(op, shared[3:])
    keep = ~drop
    cfg = HybridWindowConfig(l=8, n=3, pose_graph="mpc", mpc_min_correspondences=5)
    hyb = build_hybrid_problem(
        scene.R_wc,
        scene.t_wc,
        scene.X_w,
        scene.K,
        np.arange(12),
        oc[keep],
        op[keep],
        scene.uv[keep],
        cfg,
    )
    kinds = [type(f) for f in hyb.vision]
    assert kinds == [ReprojectionFactor, MPCFactor, DPCFactor]
    dpc = hyb.vision[2]
    ids = hyb.camera_ids[dpc.pairs]
    assert ids.tolist() == [[5, 6]]
    mpc = hyb.vision[1]
    ci, cj = hyb.camera_ids[mpc.cameras_i], hyb.camera_ids[mpc.cameras_j]
    assert not np.any((ci == 5) & (cj == 6))  # no MPC rows for the fallback pair
    assert np.any((ci == 4) & (cj == 5)) and np.any((ci == 6) & (cj == 7))
    # the fallback link is at rest at the built state: zeta(X) is the reprojection + MPC part
    assert dpc.cost(hyb.state) < 1e-12
    hyb, lm = minimize_zeta(hyb, LMConfig(max_iterations=5))
    assert np.all(np.isfinite(hyb.state.t_wc))
