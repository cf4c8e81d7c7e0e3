"""Tests for the sequence filter over a base route (geoseg.reloc.route_filter)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.special import ndtr

from geoseg.errors import GeosegError
from geoseg.reloc.route_filter import RouteFilter, RouteFilterConfig


def _line(m: int, spacing: float = 10.0) -> np.ndarray:
    """``(m, 3)`` base positions ``spacing`` metres apart along x."""
    return np.stack([np.arange(m) * spacing, np.zeros(m), np.zeros(m)], axis=1)


def _dense_transition(f: RouteFilter, step: float) -> np.ndarray:
    """The full ``(M, M)`` transition matrix, route order, built independently of the
    filter's message passing (a dead row jumps uniformly)."""
    K, leave = f._motion(step)
    eps, m = f.config.off_route, len(f)
    return (1 - eps) * K.toarray() + (eps + (1 - eps) * leave[:, None]) / m


def test_motion_moves_one_spacing_and_rows_sum_to_one() -> None:
    f = RouteFilter(_line(20), config=RouteFilterConfig(step_sigma_m=1.0, step_sigma_rel=0.0))
    assert f.spacing_m == pytest.approx(10.0)
    K, leave = f._motion(10.0)
    K = K.toarray()
    np.testing.assert_allclose(K.sum(axis=1) + leave, 1.0)
    # sigma 1 m against 10 m spacing: essentially all mass on the next image
    assert (K[np.arange(19), np.arange(1, 20)] > 0.99).all()
    # from the last image the vehicle drives off the route
    assert leave[19] > 0.99 and (leave[:19] < 1e-6).all()
    T = _dense_transition(f, 10.0)
    np.testing.assert_allclose(T.sum(axis=1), 1.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_filter_and_smooth_equal_brute_force_enumeration(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m, n = 5, 4
    pos = np.stack([np.cumsum(rng.uniform(5, 15, m)), rng.normal(0, 1, m)], axis=1)
    ts = rng.permutation(m).astype(float)  # route order differs from the index order
    cfg = RouteFilterConfig(appearance_scale=0.5, step_sigma_m=3.0, off_route=0.05)
    f = RouteFilter(pos, timestamps=ts, config=cfg)
    dist = rng.uniform(0, 2, (n, m))
    steps = rng.uniform(4, 16, n - 1)
    lik, _ = f.likelihoods(dist)
    trans = [_dense_transition(f, s) for s in steps]
    joint = np.zeros((n, m))  # sum over all paths, in route order
    prefix = np.zeros((n, m))
    for path in itertools.product(range(m), repeat=n):
        p = 1.0 / m * lik[0, path[0]]
        for t in range(1, n):
            p *= trans[t - 1][path[t - 1], path[t]] * lik[t, path[t]]
        for t in range(n):
            joint[t, path[t]] += p
    for t in range(n):  # the filter at t marginalises the observations after t
        for path in itertools.product(range(m), repeat=t + 1):
            p = 1.0 / m * lik[0, path[0]]
            for u in range(1, t + 1):
                p *= trans[u - 1][path[u - 1], path[u]] * lik[u, path[u]]
            prefix[t, path[t]] += p
    to_index = np.argsort(f.order)  # route position of each original index
    want_smooth = (joint / joint.sum(1, keepdims=True))[:, to_index]
    want_filter = (prefix / prefix.sum(1, keepdims=True))[:, to_index]
    np.testing.assert_allclose(f.smooth(dist, steps).posterior, want_smooth, atol=1e-12)
    np.testing.assert_allclose(f.filter(dist, steps).posterior, want_filter, atol=1e-12)


def _ambiguous_drive(seed: int = 0, m: int = 80, noise: float = 0.9):
    """A drive along a 80-image base whose single images are ambiguous: each query's
    embedding is its base image's plus heavy noise."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(m, 8)) / np.sqrt(8)
    truth = np.arange(m)
    queries = base[truth] + rng.normal(0, noise / np.sqrt(8), size=(m, 8))
    dist = np.linalg.norm(queries[:, None] - base[None], axis=2)
    return _line(m), dist, truth


def test_sequence_resolves_what_single_images_cannot() -> None:
    pos, dist, truth = _ambiguous_drive()
    single = (dist.argmin(axis=1) == truth).mean()
    assert single < 0.8  # the single images are ambiguous
    f = RouteFilter(pos, config=RouteFilterConfig(appearance_scale=0.2))
    steps = np.full(len(truth) - 1, 10.0) * (1 + np.random.default_rng(1).normal(0, 0.05, 79))
    filt = f.filter(dist, steps)
    smooth = f.smooth(dist, steps)
    assert (filt.ranked[10:, 0] == truth[10:]).mean() >= 0.97  # once locked on
    assert (smooth.ranked[:, 0] == truth).mean() >= 0.97
    np.testing.assert_allclose(filt.posterior.sum(axis=1), 1.0)
    idx, prob = filt.top(3)
    assert idx.shape == prob.shape == (80, 3) and (np.diff(prob, axis=1) <= 0).all()


def test_default_appearance_scale_is_scale_free() -> None:
    """By default ``tau`` follows the distances' median: any embedding scale, same posterior."""
    pos, dist, _ = _ambiguous_drive()
    f = RouteFilter(pos)
    a = f.filter(dist).posterior
    np.testing.assert_allclose(f.filter(100.0 * dist).posterior, a, rtol=1e-9, atol=1e-12)
    assert f.appearance_scale(dist) == pytest.approx(0.29 * np.median(dist))
    fixed = RouteFilter(pos, config=RouteFilterConfig(appearance_scale=0.3))
    assert fixed.appearance_scale(100.0 * dist) == 0.3
    assert f.appearance_scale(np.zeros((3, 80))) == 1.0  # all duplicates: no scale to take


def test_gps_window_zeroes_far_base_images() -> None:
    pos, dist, _ = _ambiguous_drive()
    f = RouteFilter(pos)
    gps = pos[:, :2] + 1.0
    res = f.filter(dist, gps=gps, radius_m=25.0)
    far = np.abs(pos[None, :, 0] - gps[:, None, 0]) > 26.5
    assert (res.posterior[far] == 0).all()
    assert res.empty_windows == 0
    # a fix far from every base image: that query falls back to appearance alone
    gps[5] = [1e5, 1e5]
    res = f.filter(dist, gps=gps, radius_m=25.0)
    assert res.empty_windows == 1 and np.isfinite(res.posterior).all()


def test_relocks_after_a_jump_off_the_route() -> None:
    pos, dist, truth = _ambiguous_drive(seed=2, noise=0.5)
    kidnapped = np.r_[np.arange(0, 30), np.arange(50, 80)]  # the drive skips 20 images
    steps = np.full(len(kidnapped) - 1, 10.0)  # odometry does not know about the jump
    res = RouteFilter(pos).filter(dist[kidnapped], steps)
    after = res.ranked[30 + 5 :, 0]  # five queries after the jump
    assert (after == truth[kidnapped][35:]).mean() >= 0.95


def test_segments_never_mix() -> None:
    pos = np.concatenate([_line(10), _line(10) + [0, 500, 0]])
    f = RouteFilter(pos)
    assert f.segment.tolist() == [0] * 10 + [1] * 10
    K, leave = f._motion(10.0)
    K = K.toarray()
    assert K[:10, 10:].sum() == 0 and K[10:, :10].sum() == 0
    # past the last image by more than half a spacing: Phi((10 - 5) / sigma), sigma = 2 + 0.2 * 10
    np.testing.assert_allclose(leave[[9, 19]], ndtr(1.25), rtol=1e-12)
    np.testing.assert_allclose(K.sum(axis=1) + leave, 1.0)


def test_bad_inputs() -> None:
    pos, dist, _ = _ambiguous_drive(m=10)
    f = RouteFilter(pos)
    with pytest.raises(GeosegError, match="empty"):
        RouteFilter(np.zeros((0, 2)))
    with pytest.raises(GeosegError, match="positions"):
        RouteFilter(np.zeros((3, 4)))
    with pytest.raises(GeosegError, match="timestamps"):
        RouteFilter(pos, timestamps=np.zeros(3))
    with pytest.raises(GeosegError, match="distances"):
        f.filter(dist[:, :5])
    bad = dist.copy()
    bad[0, 0] = np.nan
    with pytest.raises(GeosegError, match="distances"):
        f.filter(bad)
    with pytest.raises(GeosegError, match="no queries"):
        f.filter(np.zeros((0, 10)))
    with pytest.raises(GeosegError, match="steps_m"):
        f.filter(dist, np.full(9, -1.0))
    with pytest.raises(GeosegError, match="steps_m"):
        f.smooth(dist, np.full(3, 10.0))
    with pytest.raises(GeosegError, match="gps"):
        f.filter(dist, radius_m=20.0)
    with pytest.raises(GeosegError, match="radius_m"):
        f.filter(dist, gps=pos[:, :2], radius_m=0.0)
    bad_config = (
        ("appearance_scale", 0.0),
        ("appearance_scale_rel", -1.0),
        ("off_route", 1.0),
        ("step_sigma_rel", -1),
    )
    for key, value in bad_config:
        with pytest.raises(GeosegError, match=key):
            RouteFilterConfig(**{key: value})
    with pytest.raises(GeosegError, match="k"):
        f.filter(dist).top(0)
