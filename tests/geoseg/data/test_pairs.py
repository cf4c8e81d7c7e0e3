"""Tests for pose-based mining of positives, triplets and relative-pose pairs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geoseg.data.pairs import (
    NoEligiblePairError,
    RelPosePairDataset,
    Traversal,
    TripletDataset,
    positive_mask,
    sample_relpose_pairs,
    sample_triplets,
    truth_sets,
)
from geoseg.errors import GeosegError
from geoseg.models.relpose import relative_pose_labels
from geoseg.reloc.retrieval import recall_at_k

# camera looking north (+y) in a z-up world (OpenCV camera: x right, y down, z forward)
R_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _yaw(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _route(n: int, spacing: float, yaw_deg=0.0, offset=(0.0, 0.0)) -> Traversal:
    """``n`` cameras along the x axis, all looking north turned by ``yaw_deg``."""
    R = np.stack([_yaw(yaw_deg) @ R_NORTH] * n)
    t = np.c_[np.arange(n) * spacing + offset[0], np.full(n, offset[1]), np.full(n, 1.5)]
    return Traversal(R, t)


def test_positive_mask_distance_and_angle_both_matter() -> None:
    db = (
        np.stack([R_NORTH, R_NORTH, _yaw(50.0) @ R_NORTH, _yaw(20.0) @ R_NORTH]),
        np.array([[0.0, 0, 0], [10.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]),
    )
    query = (R_NORTH[None], np.array([[0.5, 0.5, 0.0]]))
    mask = positive_mask(db, query, max_distance_m=5.0, max_angle_deg=30.0)
    # 0: near, same direction -> positive; 1: 10 m away -> no; 2: near but 50 deg -> no;
    # 3: near, 20 deg -> positive
    assert mask.tolist() == [[True, False, False, True]]
    # tighter angle drops 3; larger distance adds 1
    assert positive_mask(db, query, max_distance_m=5.0, max_angle_deg=10.0).tolist() == [
        [True, False, False, False]
    ]
    assert positive_mask(db, query, max_distance_m=11.0, max_angle_deg=30.0)[0, 1]
    assert positive_mask(db, query, max_distance_m=5.0, max_angle_deg=60.0)[0, 2]


def test_truth_sets_feed_recall_at_k() -> None:
    db = _route(20, 4.0)
    query = _route(20, 4.0, offset=(1.0, 0.5))
    sets = truth_sets(db, query, max_distance_m=3.5)
    assert len(sets) == 20 and all(s.dtype == np.int64 for s in sets)
    assert sets[0].tolist() == [0, 1]  # 1.1 m and 3.04 m away, sorted by distance
    ranked = np.arange(20)[:, None]
    assert recall_at_k(ranked, sets, k=1) == 1.0
    # a query far from the base has no truth
    far = truth_sets(db, _route(1, 1.0, offset=(500.0, 0.0)))
    assert far[0].size == 0


def test_triplets_are_valid_and_deterministic() -> None:
    db = _route(60, 2.0)
    query = _route(60, 2.0, offset=(0.7, 0.3))
    trip = sample_triplets(db, query, 200, rng=7, min_negative_distance_m=20.0)
    ref, match, other = trip
    assert ref.shape == match.shape == other.shape == (200,)
    pos = positive_mask(db, query)
    assert pos[ref, match].all()
    dist = np.linalg.norm(query.t_wc[ref] - db.t_wc[other], axis=1)
    assert (dist > 20.0).all() and not pos[ref, other].any()
    again = sample_triplets(db, query, 200, rng=7, min_negative_distance_m=20.0)
    for a, b in zip(trip, again):
        np.testing.assert_array_equal(a, b)
    other_seed = sample_triplets(db, query, 200, rng=8, min_negative_distance_m=20.0)
    assert not np.array_equal(other_seed[0], ref)
    # within one traversal, the match is never the ref itself
    r, m, _ = sample_triplets(db, db, 100, rng=0, exclude_same_index=True)
    assert (r != m).all()


def test_hard_negatives_come_from_the_closest_embeddings() -> None:
    db = _route(60, 2.0)
    query = _route(60, 2.0, offset=(0.5, 0.0))
    # embedding distances: base image 59 is "closest" to every query, then 58, ...
    hard = np.tile(np.arange(60, 0, -1, dtype=float), (60, 1))
    ref, _, other = sample_triplets(db, query, 100, rng=0, hard_negatives=hard, hard_k=2)
    far_ok = np.linalg.norm(query.t_wc[ref] - db.t_wc[other], axis=1) > 25.0
    assert far_ok.all()
    # for refs far from 58/59, the negative is one of those two
    sel = query.t_wc[ref, 0] < 80.0
    assert sel.any() and set(other[sel].tolist()) <= {58, 59}
    with pytest.raises(GeosegError, match="hard_negatives"):
        sample_triplets(db, query, 5, hard_negatives=np.zeros((3, 3)))


def test_triplet_errors() -> None:
    db = _route(5, 1.0)
    with pytest.raises(GeosegError, match="no query image"):
        sample_triplets(db, db, 5)  # everything within 25 m: no negative
    with pytest.raises(GeosegError, match="min_negative_distance_m"):
        sample_triplets(db, db, 5, min_negative_distance_m=1.0)
    with pytest.raises(GeosegError, match="query.t_wc"):
        sample_triplets(db, (db.R_wc, db.t_wc[:3]), 5)
    with pytest.raises(GeosegError, match="empty"):
        positive_mask(db, (np.zeros((0, 3, 3)), np.zeros((0, 3))))


def test_relpose_pairs_labels_equal_relative_pose_labels() -> None:
    a = _route(30, 1.5)
    b = _route(30, 1.5, yaw_deg=10.0, offset=(0.3, 1.0))
    pairs = sample_relpose_pairs(a, b, 50, rng=3, min_baseline_m=1.0, max_baseline_m=6.0)
    assert len(pairs) == 50
    R_ab, t_dir = relative_pose_labels(
        a.R_wc[pairs.idx_a], a.t_wc[pairs.idx_a], b.R_wc[pairs.idx_b], b.t_wc[pairs.idx_b]
    )
    np.testing.assert_allclose(pairs.R_ab, R_ab)
    np.testing.assert_allclose(pairs.t_dir_ab, t_dir)
    base = np.linalg.norm(a.t_wc[pairs.idx_a] - b.t_wc[pairs.idx_b], axis=1)
    np.testing.assert_allclose(pairs.baseline_m, base)
    assert ((base >= 1.0) & (base <= 6.0)).all()
    again = sample_relpose_pairs(a, b, 50, rng=3, min_baseline_m=1.0, max_baseline_m=6.0)
    np.testing.assert_array_equal(again.idx_a, pairs.idx_a)
    # the viewing-angle bound excludes non-overlapping views
    c = _route(30, 1.5, yaw_deg=90.0)
    with pytest.raises(GeosegError, match="no pair"):
        sample_relpose_pairs(a, c, 5, max_angle_deg=30.0)
    # a minimum angle asks for turned views: only c (90 deg) has them, never b (10 deg)
    turned = sample_relpose_pairs(a, c, 20, rng=0, min_angle_deg=45.0, max_angle_deg=180.0)
    angles = np.degrees(
        np.arccos(np.clip((np.trace(turned.R_ab, axis1=1, axis2=2) - 1) / 2, -1, 1))
    )
    np.testing.assert_allclose(angles, 90.0, atol=1e-6)
    with pytest.raises(NoEligiblePairError, match="45.0-180.0 deg"):
        sample_relpose_pairs(a, b, 5, min_angle_deg=45.0, max_angle_deg=180.0)
    with pytest.raises(GeosegError, match="min_angle_deg"):
        sample_relpose_pairs(a, c, 5, min_angle_deg=40.0, max_angle_deg=30.0)


def test_relpose_pairs_at_one_place_have_no_direction() -> None:
    a = _route(20, 4.0)
    b = _route(20, 4.0, yaw_deg=3.0)  # the same positions, turned by 3 degrees
    c = _route(20, 4.0, offset=(0.3, 0.0))
    pairs = sample_relpose_pairs(a, b, 30, rng=0, min_baseline_m=0.0, max_baseline_m=0.5)
    np.testing.assert_array_equal(pairs.idx_a, pairs.idx_b)  # only the pose itself is that near
    np.testing.assert_array_equal(pairs.baseline_m, 0.0)
    np.testing.assert_array_equal(pairs.t_dir_ab, 0.0)
    np.testing.assert_allclose(pairs.R_ab, np.stack([R_NORTH.T @ _yaw(3.0) @ R_NORTH] * 30))
    near = sample_relpose_pairs(a, c, 30, rng=0, min_baseline_m=0.0, max_baseline_m=0.5)
    np.testing.assert_allclose(near.baseline_m, 0.3)
    np.testing.assert_allclose(np.linalg.norm(near.t_dir_ab, axis=1), 1.0)
    with pytest.raises(GeosegError, match="min_baseline_m"):
        sample_relpose_pairs(a, b, 5, min_baseline_m=-0.1)


def test_datasets_over_features_and_over_items() -> None:
    db = _route(40, 2.0)
    query = _route(40, 2.0, offset=(0.5, 0.0))
    trip = sample_triplets(db, query, 10, rng=0)
    fq = torch.randn(40, 8, 3, 4)
    fd = torch.randn(40, 8, 3, 4)
    ds = TripletDataset(fq, fd, trip)
    item = ds[3]
    assert len(ds) == 10
    r, m, o = item["index"].tolist()
    torch.testing.assert_close(item["ref"], fq[r])
    torch.testing.assert_close(item["match"], fd[m])
    torch.testing.assert_close(item["other"], fd[o])
    with pytest.raises(GeosegError, match="mismatched sizes"):
        TripletDataset(fq, torch.randn(40, 8, 3, 5), trip)
    # items + feature extractor (here: ids -> constant maps)
    ds2 = TripletDataset(list(range(40)), list(range(100, 140)), trip, feature_fn=_fake)
    assert float(ds2[0]["match"][0, 0, 0]) == 100 + trip[1][0]
    bad = TripletDataset(list(range(40)), list(range(40)), trip, feature_fn=_sized)
    with pytest.raises(GeosegError, match="mismatched sizes"):
        for i in range(len(bad)):
            bad[i]

    pairs = sample_relpose_pairs(db, query, 12, rng=1)
    pds = RelPosePairDataset(fd, fq, pairs)
    s = pds[5]
    ia, ib = s["index"].tolist()
    torch.testing.assert_close(s["feat_a"], fd[ia])
    torch.testing.assert_close(s["feat_b"], fq[ib])
    torch.testing.assert_close(s["R_ab"], torch.as_tensor(pairs.R_ab[5], dtype=torch.float32))
    assert s["t_dir_ab"].shape == (3,)
    batch = next(iter(torch.utils.data.DataLoader(pds, batch_size=4)))
    assert batch["feat_a"].shape == (4, 8, 3, 4) and batch["R_ab"].shape == (4, 3, 3)


def _fake(i: int) -> torch.Tensor:
    return torch.full((2, 3, 3), float(i))


def _sized(i: int) -> torch.Tensor:
    return torch.zeros(2, 3, 3 + (i % 2))
