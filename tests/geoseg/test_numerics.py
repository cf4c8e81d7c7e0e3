"""Extreme but legal numbers give correct, finite answers or a clear error, never NaN.

The class: probabilities that underflow (a GPS sigma of 1e-160), sums that overflow (distances of
1e308), variances that vanish, and networks whose outputs are NaN.
"""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.errors import GeosegError
from geoseg.infer import Segmenter
from geoseg.reloc.retrieval import fuse_gps_distance, intersect_rays, locate_from_ranged_rays
from geoseg.reloc.route_filter import RouteFilter, RouteFilterConfig


def _route(m: int = 12) -> tuple[RouteFilter, np.ndarray]:
    pos = np.c_[np.arange(m) * 5.0, np.zeros(m)]
    return RouteFilter(pos), pos


@pytest.mark.parametrize("sigma", [1e-3, 1e-160, 1e-200, 1e-320])
def test_tiny_gps_sigma_puts_the_posterior_on_the_nearest_base(sigma) -> None:
    route, pos = _route()
    rng = np.random.default_rng(0)
    dist = rng.uniform(0.5, 1.5, (4, len(route)))
    gps = pos[[7, 8, 9, 10]] + [1.0, 0.3]
    for run in (route.filter, route.smooth):
        post = run(dist, gps=gps, gps_sigma_m=sigma)
        assert np.isfinite(post.posterior).all()
        np.testing.assert_allclose(post.posterior.sum(axis=1), 1.0)
        assert post.ranked[:, 0].tolist() == [7, 8, 9, 10]


@pytest.mark.parametrize("scale", [1.0, 1e100, 1e300, 1e308])
def test_huge_distances_do_not_overflow(scale) -> None:
    route, _ = _route()
    dist = np.full((3, len(route)), 1.0)
    for t, b in enumerate([2, 3, 4]):
        dist[t, b] = 0.2
    post = route.filter(dist * scale)
    assert np.isfinite(post.posterior).all()
    assert post.ranked[:, 0].tolist() == [2, 3, 4]


def test_tiny_tau_and_tiny_sigma_together_stay_finite() -> None:
    route, pos = _route()
    dist = np.random.default_rng(1).uniform(0.5, 1.5, (3, len(route)))
    cfg = RouteFilterConfig(appearance_scale=1e-300)
    post = RouteFilter(pos, config=cfg).smooth(dist, gps=pos[[1, 2, 3]], gps_sigma_m=1e-300)
    assert np.isfinite(post.posterior).all()
    np.testing.assert_allclose(post.posterior.sum(axis=1), 1.0)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1.0])
def test_non_finite_inputs_are_refused(bad) -> None:
    route, pos = _route()
    dist = np.ones((2, len(route)))
    dist[1, 3] = bad
    with pytest.raises(GeosegError, match="distances"):
        route.filter(dist)
    with pytest.raises(GeosegError, match="gps_sigma_m"):
        route.filter(np.ones((2, len(route))), gps=pos[:2], gps_sigma_m=abs(bad) * np.nan)


@pytest.mark.parametrize(
    ("d", "sigma"), [(1e-200, 2.0), (5.0, 1e-200), (1e-200, 1e-200), (1e200, 2.0)]
)
def test_fused_distance_is_finite_and_between_the_readings(d, sigma) -> None:
    fused = fuse_gps_distance(np.array([d]), np.array([7.0]), relative_sigma=0.3, gps_sigma_m=sigma)
    assert np.isfinite(fused).all()
    assert min(d, 7.0) - 1e-9 <= fused[0] <= max(d, 7.0) + 1e-9


def test_ray_fits_never_return_a_silent_nan() -> None:
    o = np.array([[0.0, 0.0, 0.0], [1e300, 0.0, 0.0], [0.0, 1e300, 0.0]])
    d = np.array([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [1.0, -1.0, 0.0]])
    res = intersect_rays(o, d)
    assert res.degenerate or np.isfinite(res.point).all()
    with pytest.raises(GeosegError, match="not finite"):
        locate_from_ranged_rays(o[:2], d[:2], np.array([1e-300, 1e-300]), robust=False)


def test_nan_network_outputs_are_an_error_not_class_0() -> None:
    def backend(batch):
        b, _, h, w = batch.shape
        logits = np.zeros((b, 8, h, w), np.float32)
        logits[0, :, 3, 4] = np.nan
        return {"logits": logits}

    seg = Segmenter(backend, source="stub.onnx")
    with pytest.raises(GeosegError, match="stub.onnx.*NaN or infinite logits"):
        seg(np.zeros((16, 16, 3), np.uint8))

    def log_probs(batch):  # a probability of exactly 0 is fine (log = -inf)
        b, _, h, w = batch.shape
        out = np.full((b, 8, h, w), -np.inf, np.float32)
        out[:, 2] = 0.0
        return {"log_probs": out}

    assert (Segmenter(log_probs)(np.zeros((16, 16, 3), np.uint8)).labels == 2).all()
