"""Repeated traversals of a tram route and their cached layer-21 features (tiny city, 64x48)."""

import numpy as np
import pytest
import torch

from geoseg.data.traversals import (
    RouteSpec,
    TrunkFeatureExtractor,
    render_route,
    route_features,
    route_specs,
    traversal_features,
)
from geoseg.errors import ConfigError, GeosegError
from geoseg.models.registry import get_model

TINY = {"blocks_x": 2, "blocks_y": 2}


def _spec(**kw) -> RouteSpec:
    base = {"seed": 3, "world": TINY, "length_m": 30.0, "spacing_m": 6.0, "size": (48, 64)}
    base.update(kw)
    return RouteSpec(**base)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("traversals")


@pytest.fixture(scope="module")
def extractor():
    torch.manual_seed(0)
    return TrunkFeatureExtractor(get_model("enet"), batch_size=4)


def test_two_traversals_share_poses_and_differ_in_appearance(cache):
    spec = _spec()
    a, b = render_route(spec, cache_dir=cache, progress=False)
    assert len(a) == len(b) == spec.num_keyframes == 6
    assert (a.condition, b.condition) == ("summer_day", "winter")
    np.testing.assert_array_equal(a.R_wc, b.R_wc)
    np.testing.assert_array_equal(a.t_wc, b.t_wc)
    assert a.images.shape == (6, 48, 64, 3) and a.images.dtype == np.uint8
    assert np.abs(a.images.astype(int) - b.images.astype(int)).mean() > 10
    # keyframes every spacing_m metres of track (the drive is sampled at 0.35 m)
    steps = np.linalg.norm(np.diff(a.t_wc, axis=0), axis=1)
    assert np.all(steps < 6.0 + 0.5) and np.all(steps > 3.0)
    assert a.key != b.key


def test_render_cache_hit_on_second_access(cache):
    spec = _spec()
    first = render_route(spec, cache_dir=cache, progress=False)
    again = render_route(spec, cache_dir=cache, progress=False)
    assert all(t.from_cache for t in again)
    for x, y in zip(first, again):
        np.testing.assert_array_equal(x.images, y.images)
        np.testing.assert_array_equal(x.R_wc, y.R_wc)


def test_offset_and_yaw_jitter_move_the_second_traversal(cache):
    spec = _spec(offset_m=3.0, yaw_jitter_deg=5.0)
    a, b = render_route(spec, cache_dir=cache, progress=False)
    shift = np.linalg.norm(b.t_wc - a.t_wc, axis=1)
    assert np.all(np.abs(shift - 3.0) < 0.6)
    yaw = np.degrees(
        np.arccos(np.clip(np.einsum("ni,ni->n", a.R_wc[:, :, 2], b.R_wc[:, :, 2]), -1, 1))
    )
    assert yaw.max() <= 5.0 + 3.0 and yaw.max() > 0.1  # jitter (+ the track's curvature)
    assert render_route(spec, cache_dir=cache, progress=False)[1].key == b.key


def test_feature_cache_hit_and_equality_with_the_network_output(cache, extractor):
    trav = render_route(_spec(), cache_dir=cache, progress=False)[0]
    calls = []
    original = extractor.__class__.__call__

    class Spy(TrunkFeatureExtractor):
        def __call__(self, images):
            calls.append(len(images))
            return original(self, images)

    spy = Spy.__new__(Spy)
    spy.__dict__.update(extractor.__dict__)
    f1 = traversal_features(trav, spy, cache_dir=cache, progress=False)
    n_calls = len(calls)
    f2 = traversal_features(trav, spy, cache_dir=cache, progress=False)
    assert n_calls > 0 and len(calls) == n_calls  # second access: no trunk pass
    np.testing.assert_array_equal(f1, f2)
    assert f1.shape == (6, 128, 6, 8) and f1.dtype == np.float16
    # the trunk path equals the full network's "features" output
    model = get_model("enet")
    model.trunk.load_state_dict(extractor.trunk.state_dict())
    x = torch.from_numpy(trav.images[:2]).permute(0, 3, 1, 2).float() / 255.0
    x = (x - extractor.mean) / extractor.std
    with torch.no_grad():
        ref = model.eval()(x)["features"].numpy()
    np.testing.assert_allclose(f1[:2].astype(np.float32), ref, atol=2e-2, rtol=1e-2)


def test_route_features_can_drop_images(cache, extractor):
    rf = route_features(_spec(), extractor, cache_dir=cache, progress=False, keep_images=False)
    assert [f.shape[0] for f in rf.features] == [6, 6]
    assert rf.traversals[0].images.shape[0] == 0 and len(rf.traversals[0]) == 6


def test_route_specs_are_deterministic_with_distinct_conditions():
    conds = ["summer_day", "overcast", "dusk", "night", "winter"]
    a = route_specs([1, 2], conditions=conds, conditions_per_route=3, world=TINY)
    b = route_specs([1, 2], conditions=conds, conditions_per_route=3, world=TINY)
    assert [s.conditions for s in a] == [s.conditions for s in b]
    assert all(len(set(s.conditions)) == 3 for s in a)
    assert [s.preset for s in a] == ["light", "dense_occlusion"]


def test_bad_inputs_are_clear_errors(extractor):
    with pytest.raises(ConfigError, match="unknown"):
        _spec(conditions=["summer_day", "monsoon"])
    with pytest.raises(ConfigError, match="spacing_m"):
        _spec(spacing_m=100.0)
    with pytest.raises(ConfigError, match="route.world.seed"):
        _spec(world={"seed": 4})
    with pytest.raises(GeosegError, match="trunk"):
        TrunkFeatureExtractor(get_model("reloc"))
    with pytest.raises(GeosegError, match="uint8"):
        extractor(np.zeros((1, 48, 64, 3), dtype=np.float32))
