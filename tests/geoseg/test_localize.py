"""Tests for retrieval (GPS window, metrics) and ray intersection (absolute position)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geoseg.errors import GeosegError
from geoseg.reloc.retrieval import (
    RetrievalIndex,
    absolute_position,
    evaluate_retrieval,
    fuse_gps_distance,
    intersect_rays,
    locate_from_ranged_rays,
    recall_at_k,
    rerank_by_distance,
    triplet_accuracy,
)

# ----------------------------------------------------------------------------- retrieval


def _base(m: int = 50, d: int = 16, seed: int = 0):
    rng = np.random.default_rng(seed)
    emb = rng.normal(size=(m, d))
    pos = np.stack([np.arange(m) * 10.0, np.zeros(m)], axis=1)  # 10 m apart along x
    return emb, pos


@pytest.mark.parametrize("m", [50, 5000])  # dense path and sklearn path
def test_planted_duplicate_is_rank_one(m: int) -> None:
    emb, pos = _base(m)
    index = RetrievalIndex(emb, positions=pos)
    targets = np.array([3, 17, m - 1])
    queries = emb[targets] + 1e-9
    idx, dist = index.query(queries, k=5)
    assert idx.shape == (3, 5) and dist.shape == (3, 5)
    np.testing.assert_array_equal(idx[:, 0], targets)
    assert (dist[:, 0] < 1e-6).all()
    assert (np.diff(dist, axis=1) >= 0).all()
    # distances are the true L2 distances
    np.testing.assert_allclose(
        dist[0], np.linalg.norm(emb[idx[0]] - queries[0], axis=1), rtol=1e-6, atol=1e-6
    )


def test_distances_are_every_pair_and_agree_with_query() -> None:
    emb, pos = _base()
    index = RetrievalIndex(emb, positions=pos)
    q = np.random.default_rng(1).normal(size=(4, emb.shape[1]))
    d = index.distances(q)
    np.testing.assert_allclose(d, np.linalg.norm(q[:, None] - emb[None], axis=2), atol=1e-9)
    idx, dist = index.query(q, k=3)
    np.testing.assert_array_equal(idx, np.argsort(d, axis=1)[:, :3])
    assert index.distances(np.zeros((0, emb.shape[1]))).shape == (0, len(emb))
    with pytest.raises(GeosegError, match="embeddings"):
        index.distances(q[:, :3])


def test_gps_window_excludes_far_candidates() -> None:
    emb, pos = _base()
    index = RetrievalIndex(emb, positions=pos)
    # query is a duplicate of base image 40 but its GPS says it is near image 5
    q = emb[[40]]
    idx, _ = index.query(q, k=1)
    assert idx[0, 0] == 40
    idx, dist = index.query(q, k=5, gps=pos[[5]], radius_m=25.0)
    cand = set(idx[0][idx[0] >= 0].tolist())
    assert cand == {3, 4, 5, 6, 7}  # within 25 m of x = 50: 30..70
    assert 40 not in cand
    # fewer candidates than k: padded with -1 / inf
    idx, dist = index.query(q, k=8, gps=pos[[5]], radius_m=15.0)
    assert sorted(idx[0, :3].tolist()) == [4, 5, 6]
    assert (idx[0, 3:] == -1).all() and np.isinf(dist[0, 3:]).all()
    # no candidates at all
    idx, dist = index.query(q, k=2, gps=np.array([[1e6, 1e6]]), radius_m=5.0)
    assert (idx == -1).all() and np.isinf(dist).all()
    # k larger than the base without window: padded too
    small = RetrievalIndex(emb[:3])
    idx, dist = small.query(emb[:1], k=5)
    assert idx[0, 0] == 0 and (idx[0, 3:] == -1).all()


def test_positions_from_poses() -> None:
    emb, pos = _base(10)
    t = np.concatenate([pos, np.full((10, 1), 1.5)], axis=1)
    R = np.repeat(np.eye(3)[None], 10, axis=0)
    index = RetrievalIndex(emb, R_wc=R, t_wc=t)
    np.testing.assert_array_equal(index.positions, pos)
    idx, _ = index.query(emb[[9]], k=1, gps=t[[2]], radius_m=1.0)
    assert idx[0, 0] == 2


def test_retrieval_bad_inputs() -> None:
    emb, pos = _base(10)
    with pytest.raises(GeosegError, match="empty"):
        RetrievalIndex(np.zeros((0, 8)))
    with pytest.raises(GeosegError, match="embeddings"):
        RetrievalIndex(np.zeros(8))
    with pytest.raises(GeosegError, match="positions"):
        RetrievalIndex(emb, positions=pos[:5])
    with pytest.raises(GeosegError, match="both"):
        RetrievalIndex(emb, R_wc=np.repeat(np.eye(3)[None], 10, axis=0))
    index = RetrievalIndex(emb, positions=pos)
    with pytest.raises(GeosegError, match=r"\(\*, 16\)"):
        index.query(np.zeros((2, 15)))
    with pytest.raises(GeosegError, match="gps"):
        index.query(emb[:2], k=1, radius_m=10.0)
    with pytest.raises(GeosegError, match="gps"):
        index.query(emb[:2], k=1, gps=pos[:3], radius_m=10.0)
    with pytest.raises(GeosegError, match="k"):
        index.query(emb[:2], k=0)
    with pytest.raises(GeosegError, match="NaN"):
        index.query(np.full((1, 16), np.nan))
    with pytest.raises(GeosegError, match="positions"):
        RetrievalIndex(emb).query(emb[:1], k=1, gps=pos[:1], radius_m=10.0)


def test_recall_at_k_hand_made() -> None:
    ranked = np.array([[1, 2, 3], [4, 5, 6], [7, -1, -1], [9, 8, 0]])
    truth = [{2}, 4, [0, 7], np.array([0])]
    assert recall_at_k(ranked, truth, k=1) == pytest.approx(2 / 4)
    assert recall_at_k(ranked, truth, k=2) == pytest.approx(3 / 4)
    assert recall_at_k(ranked, truth) == pytest.approx(1.0)
    # padding never counts, even if -1 were in the truth set
    assert recall_at_k(np.array([[-1]]), [{-1}]) == 0.0
    with pytest.raises(GeosegError, match="truth_sets"):
        recall_at_k(ranked, truth[:3])
    with pytest.raises(GeosegError, match="empty"):
        recall_at_k(ranked, [set(), 4, 7, 0])
    with pytest.raises(GeosegError, match="k"):
        recall_at_k(ranked, truth, k=4)


def test_triplet_accuracy_hand_made() -> None:
    ref = np.zeros((4, 2))
    match = np.array([[1.0, 0], [0, 1], [3, 0], [0, 0.5]])
    other = np.array([[2.0, 0], [0, 0.5], [0, 4], [1, 0]])
    assert triplet_accuracy(ref, match, other) == pytest.approx(3 / 4)
    assert triplet_accuracy(torch.tensor(ref), torch.tensor(match), torch.tensor(other)) == 0.75
    with pytest.raises(GeosegError, match="match"):
        triplet_accuracy(ref, match[:3], other)


# ----------------------------------------------------------------------------- rays


def _rays_to(point: np.ndarray, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-50, 50, size=(n, 3))
    origins[:, 2] = rng.uniform(1, 3, size=n)
    d = point[None] - origins
    return origins, d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.5, 2, (n, 1))


@pytest.mark.parametrize("robust", [False, True])
@pytest.mark.parametrize("n", [2, 3, 8])
def test_exact_without_noise(robust: bool, n: int) -> None:
    point = np.array([12.0, -7.0, 1.6])
    o, d = _rays_to(point, n)
    res = intersect_rays(o, d, robust=robust)
    assert not res.degenerate
    np.testing.assert_allclose(res.point, point, atol=1e-9)
    assert res.residuals.shape == (n,) and res.residuals.max() < 1e-9
    assert res.inliers.all()
    assert np.isfinite(res.condition)


def test_robust_to_one_outlier_ray() -> None:
    point = np.array([5.0, 20.0, 1.5])
    o, d = _rays_to(point, 6, seed=1)
    rng = np.random.default_rng(2)
    d_noisy = d / np.linalg.norm(d, axis=1, keepdims=True) + rng.normal(scale=1e-3, size=d.shape)
    d_noisy[2] = np.array([1.0, 0.3, 0.0])  # outlier ray
    plain = intersect_rays(o, d_noisy, robust=False)
    robust = intersect_rays(o, d_noisy, robust=True)
    assert not robust.degenerate
    assert robust.inliers.tolist() == [True, True, False, True, True, True]
    err_robust = np.linalg.norm(robust.point - point)
    err_plain = np.linalg.norm(plain.point - point)
    assert err_robust < 0.3 and err_plain > 3 * err_robust
    # exact when the inliers are noiseless
    d_out = d.copy()
    d_out[4] = -d_out[4]  # points away from the query: behind the ray
    exact = intersect_rays(o, d_out)
    np.testing.assert_allclose(exact.point, point, atol=1e-9)
    assert not exact.inliers[4]


def test_degenerate_on_parallel_rays() -> None:
    o = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    d = np.array([[0.0, 1, 0], [0, 1, 0], [0, 1, 1e-4]])
    for robust in (False, True):
        res = intersect_rays(o, d, robust=robust)
        assert res.degenerate
        assert np.isnan(res.point).all()
        assert res.min_eigenvalue < 1e-4
    # two rays 0.5 degree apart are flagged, 5 degrees apart are not
    for angle, flagged in ((0.5, True), (5.0, False)):
        a = np.deg2rad(angle)
        res = intersect_rays([[0, 0, 0], [1, 0, 0]], [[0, 1, 0], [-np.sin(a), np.cos(a), 0]])
        assert res.degenerate is flagged


def test_rays_meeting_behind_are_degenerate_in_robust_mode() -> None:
    o = np.array([[0.0, 0, 0], [10, 0, 0]])
    d = np.array([[-1.0, 1, 0], [1, 1, 0]])  # the lines meet at (5, -5, 0), behind both rays
    plain = intersect_rays(o, d, robust=False)
    np.testing.assert_allclose(plain.point, [5.0, -5.0, 0.0], atol=1e-12)
    res = intersect_rays(o, d)
    assert res.degenerate and not res.inliers.any() and np.isnan(res.point).all()
    res3 = intersect_rays(np.vstack([o, [[20.0, 0, 0]]]), np.vstack([d, [[1.0, 1, 0]]]))
    assert res3.degenerate and res3.inliers.sum() < 2


def test_absolute_position_rotates_directions() -> None:
    query = np.array([3.0, 4.0, 1.5])
    rng = np.random.default_rng(3)
    n = 4
    t_wc = rng.uniform(-20, 20, size=(n, 3))
    # random camera-to-world rotations (QR of a Gaussian, det +1)
    R_wc = np.empty((n, 3, 3))
    for i in range(n):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        R_wc[i] = q * np.linalg.det(q)
    d_world = query - t_wc
    d_cam = np.einsum("nji,nj->ni", R_wc, d_world)  # R_wc^T d_world
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    res = absolute_position(R_wc, t_wc, d_cam)
    np.testing.assert_allclose(res.point, query, atol=1e-9)
    with pytest.raises(GeosegError, match="directions_in_base_camera"):
        absolute_position(R_wc, t_wc, d_cam[:3])


def test_ray_bad_inputs() -> None:
    with pytest.raises(GeosegError, match="2 rays"):
        intersect_rays(np.zeros((1, 3)), np.ones((1, 3)))
    with pytest.raises(GeosegError, match="zero-length"):
        intersect_rays(np.zeros((2, 3)), np.array([[0.0, 0, 0], [1, 0, 0]]))
    with pytest.raises(GeosegError, match="directions"):
        intersect_rays(np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(GeosegError, match="NaN"):
        intersect_rays(np.full((2, 3), np.nan), np.ones((2, 3)))


# ----------------------------------------------------------------------------- ranged rays


@pytest.mark.parametrize("robust", [False, True])
@pytest.mark.parametrize("n", [1, 2, 5])
def test_ranged_rays_exact_without_noise(robust: bool, n: int) -> None:
    point = np.array([12.0, -7.0, 1.6])
    o, d = _rays_to(point, n)
    r = np.linalg.norm(point - o, axis=1)
    res = locate_from_ranged_rays(o, d, r, robust=robust)
    assert not res.degenerate and res.inliers.all()
    np.testing.assert_allclose(res.point, point, atol=1e-9)
    assert res.residuals.max() < 1e-9


def test_ranged_rays_fix_collinear_bases() -> None:
    """Bases on a straight street in line with the query: rays alone are degenerate, ranges
    place the query; with a range error the point moves along the street only."""
    o = np.array([[0.0, 0, 1.5], [-11.7, 0, 1.5]])
    query = np.array([3.0, 0.0, 1.5])
    d = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    assert intersect_rays(o, d).degenerate
    res = locate_from_ranged_rays(o, d, [3.0, 14.7])
    np.testing.assert_allclose(res.point, query, atol=1e-9)
    # ranges 10 % long: the weighted mean of 3.3 and 16.17 - 11.7 = 4.47 with weights
    # 1 / (r sigma)^2, i.e. the near base dominates as 1 / r^2
    res = locate_from_ranged_rays(o, d, [3.3, 16.17], robust=False)
    w = np.array([1 / 3.3**2, 1 / 16.17**2])
    np.testing.assert_allclose(res.point, [(w @ [3.3, 4.47]) / w.sum(), 0, 1.5], atol=1e-9)


def test_ranged_rays_cross_where_directions_meet() -> None:
    """Two crossing rays with ranges 20 % too long: the directions (3 deg sigma) outweigh the
    ranges (25 % sigma), so the point stays near the true intersection."""
    point = np.array([0.0, 5.0, 0.0])
    o = np.array([[-5.0, 0, 0], [5.0, 0, 0]])
    d = point - o
    r = np.linalg.norm(d, axis=1)
    res = locate_from_ranged_rays(o, d, 1.2 * r, robust=False)
    single = o[0] + 1.2 * d[0]  # what the first ranged ray alone says
    assert np.linalg.norm(res.point - point) < 0.1 * np.linalg.norm(single - point)


def test_ranged_rays_reject_an_outlier() -> None:
    point = np.array([5.0, 20.0, 1.5])
    o, d = _rays_to(point, 5, seed=1)
    r = np.linalg.norm(point - o, axis=1)
    r_bad = r.copy()
    r_bad[3] *= 3.0  # a wrong match: three times too far
    plain = locate_from_ranged_rays(o, d, r_bad, robust=False)
    res = locate_from_ranged_rays(o, d, r_bad)
    assert res.inliers.tolist() == [True, True, True, False, True]
    np.testing.assert_allclose(res.point, point, atol=1e-9)
    assert np.linalg.norm(plain.point - point) > 0.1


def test_absolute_position_with_distances() -> None:
    R_wc = np.stack([np.eye(3), np.eye(3)])
    t_wc = np.array([[0.0, 0, 0], [0, 0, -8]])
    d_cam = np.array([[0.0, 0, 1], [0, 0, 1]])  # both look at the query straight ahead
    res = absolute_position(R_wc, t_wc, d_cam, [2.0, 10.0])
    np.testing.assert_allclose(res.point, [0.0, 0, 2], atol=1e-9)
    assert absolute_position(R_wc, t_wc, d_cam).degenerate
    one = absolute_position(R_wc[:1], t_wc[:1], d_cam[:1], [2.0])
    np.testing.assert_allclose(one.point, [0.0, 0, 2], atol=1e-12)


def test_ranged_rays_bad_inputs() -> None:
    o, d = np.zeros((2, 3)), np.array([[1.0, 0, 0], [0, 1, 0]])
    with pytest.raises(GeosegError, match="ranges"):
        locate_from_ranged_rays(o, d, [1.0, 0.0])
    with pytest.raises(GeosegError, match="ranges"):
        locate_from_ranged_rays(o, d, [1.0])
    with pytest.raises(GeosegError, match="NaN"):
        locate_from_ranged_rays(o, d, [1.0, np.nan])
    with pytest.raises(GeosegError, match="at least 1"):
        locate_from_ranged_rays(np.zeros((0, 3)), np.zeros((0, 3)), [])
    with pytest.raises(GeosegError, match="zero-length"):
        locate_from_ranged_rays(o, np.zeros((2, 3)), [1.0, 1.0])
    with pytest.raises(GeosegError, match="range_sigma"):
        locate_from_ranged_rays(o, d, [1.0, 1.0], range_sigma=0.0)


def test_rerank_by_distance() -> None:
    ranked = np.array([[7, 3, 9], [4, 5, -1], [1, 2, 0]])
    dist = np.array([[8.7, 2.9, 20.0], [3.0, 1.0, np.nan], [5.0, 5.0, 5.0]])
    out, d, order = rerank_by_distance(ranked, dist)
    assert out.tolist() == [[3, 7, 9], [5, 4, -1], [1, 2, 0]]  # padding last, ties stable
    np.testing.assert_array_equal(d[1], [1.0, 3.0, np.inf])
    np.testing.assert_array_equal(np.take_along_axis(ranked, order, 1), out)
    with pytest.raises(GeosegError, match="distances"):
        rerank_by_distance(ranked, np.where(ranked >= 0, np.nan, 1.0))
    with pytest.raises(GeosegError, match="distances"):
        rerank_by_distance(ranked, dist[:, :2])
    with pytest.raises(GeosegError, match="integer"):
        rerank_by_distance(ranked.astype(float), dist)


def test_rerank_appearance_breaks_the_heads_near_ties() -> None:
    # candidate 7 is 3 m behind the query, 8 is 9 m ahead: the head nearly ties them (4.1 vs
    # 4.0 m) while the embedding clearly prefers 7; a clear distance gap (2 m vs 20 m) still wins
    ranked = np.array([[8, 7, -1], [5, 6, 4]])
    dist = np.array([[4.0, 4.1, np.nan], [20.0, 2.0, 9.0]])
    app = np.array([[0.9, 0.6, np.nan], [0.5, 0.9, 0.7]])
    assert rerank_by_distance(ranked, dist)[0].tolist() == [[8, 7, -1], [6, 4, 5]]
    out, d, _ = rerank_by_distance(ranked, dist, appearance=app, appearance_weight=0.5)
    assert out.tolist() == [[7, 8, -1], [6, 4, 5]]
    np.testing.assert_array_equal(d[0], [4.1, 4.0, np.inf])  # the distances, not the key
    # the key: log(4.0) + 0.5 * 0.9 = 1.836 > log(4.1) + 0.5 * 0.6 = 1.711; with w = 0.05 the
    # head's 2.5 % lead holds (log 4.1 - log 4.0 = 0.0247 > 0.05 * 0.3 = 0.015)
    weak = rerank_by_distance(ranked, dist, appearance=app, appearance_weight=0.05)[0]
    assert weak[0].tolist() == [8, 7, -1]
    with pytest.raises(GeosegError, match="appearance: required"):
        rerank_by_distance(ranked, dist, appearance_weight=0.5)
    with pytest.raises(GeosegError, match="appearance_weight"):
        rerank_by_distance(ranked, dist, appearance=app, appearance_weight=-1.0)
    with pytest.raises(GeosegError, match="appearance"):
        rerank_by_distance(ranked, dist, appearance=app[:, :2], appearance_weight=0.5)
    with pytest.raises(GeosegError, match="appearance: NaN"):
        rerank_by_distance(
            ranked, dist, appearance=np.where(ranked >= 0, np.nan, 0.0), appearance_weight=0.5
        )
    with pytest.raises(GeosegError, match="distances: expected > 0"):
        rerank_by_distance(ranked, np.abs(dist) * 0.0, appearance=app, appearance_weight=0.5)


def test_fuse_gps_distance_is_the_inverse_variance_mean() -> None:
    # equal variances (0.5 * 4 m = 2 m): the plain mean; a vague GPS leaves the head's reading
    fused = fuse_gps_distance([4.0], [8.0], relative_sigma=0.5, gps_sigma_m=2.0)
    np.testing.assert_allclose(fused, [6.0])
    vague = fuse_gps_distance([4.0, 9.0], [30.0, 1.0], relative_sigma=0.3, gps_sigma_m=1e6)
    np.testing.assert_allclose(vague, [4.0, 9.0], rtol=1e-9)
    # the head's near-tie between the base 3 m behind the query (true) and the one 9 m ahead
    # is broken by the fix; a far reading barely moves a near candidate (its variance grows)
    ranked = np.array([[11, 10, 12, -1]])
    head = np.array([[3.05, 3.08, 12.0, np.inf]])
    gps = np.array([[8.1, 2.6, 14.0, np.inf]])
    fused = fuse_gps_distance(head, gps, relative_sigma=0.3, gps_sigma_m=2.0)
    assert rerank_by_distance(ranked, fused)[0].tolist() == [[10, 11, 12, -1]]
    assert np.isinf(fused[0, 3])
    w_head, w_gps = 1 / (0.3 * 3.08) ** 2, 1 / 4.0
    assert fused[0, 1] == pytest.approx((w_head * 3.08 + w_gps * 2.6) / (w_head + w_gps))
    for kw, match in (
        ({"relative_sigma": 0.0, "gps_sigma_m": 2.0}, "relative_sigma"),
        ({"relative_sigma": 0.3, "gps_sigma_m": float("nan")}, "gps_sigma_m"),
    ):
        with pytest.raises(GeosegError, match=match):
            fuse_gps_distance([3.0], [2.0], **kw)
    with pytest.raises(GeosegError, match="positive"):
        fuse_gps_distance([0.0], [2.0], relative_sigma=0.3, gps_sigma_m=2.0)
    with pytest.raises(GeosegError, match="gps_m"):
        fuse_gps_distance([1.0, 2.0], [2.0], relative_sigma=0.3, gps_sigma_m=2.0)


def test_evaluate_retrieval_with_and_without_window() -> None:
    _, pos = _base(30)
    emb = np.eye(30, 32)  # orthonormal base embeddings
    index = RetrievalIndex(emb, positions=pos)
    rng = np.random.default_rng(4)
    truth = np.arange(30)
    # a confusable twin: query j looks slightly more like base (j + 15) % 30, 150 m away
    queries = 0.5 * emb[truth] + 0.52 * emb[(truth + 15) % 30] + rng.normal(0, 1e-3, (30, 32))
    whole = evaluate_retrieval(index, queries, list(truth), ks=(1, 2))
    window = evaluate_retrieval(index, queries, list(truth), ks=(1, 2), gps=pos, radius_m=25.0)
    assert whole == {"recall@1": 0.0, "recall@2": 1.0}
    assert window["recall@1"] == 1.0
