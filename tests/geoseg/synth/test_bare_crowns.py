"""Leafless crowns drawn as limbs: the ray-segment test, the skeletons, the twig mass, the
rendered frames."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from geoseg.classes import SKY, VEGETATION
from geoseg.errors import ConfigError
from geoseg.synth.bare_crowns import (
    _MEAN_CHORD,
    CrownLimbs,
    _closest_approach,
    crown_skeleton,
    haze_cover,
    labelled_crown,
    mass_cover,
    twig_colour,
    twig_speckle,
    veil,
)
from geoseg.synth.conditions import get_condition
from geoseg.synth.realism import (
    REALISTIC_FURNISHED,
    RealismConfig,
    Variation,
    cache_fields,
    draw_variation,
)
from geoseg.synth.world_meshes import SurfaceKind
from geoseg.synth.world_records import Tree


def _tree(instance: int = 7) -> Tree:
    return Tree(
        instance, np.array([10.0, 5.0, 0.0]), 0.2, 3.0, np.array([10.0, 5.0, 5.2]),
        np.array([2.5, 2.4, 2.8]),
    )  # fmt: skip


def _brute_force(o, d, a, b, n=20001):
    """Distances of rays to segments by sampling both finely (s up to 50 m)."""
    s = np.linspace(0.0, 50.0, n)
    u = np.linspace(0.0, 1.0, 2001)
    out = np.empty((len(o), len(a)))
    for i in range(len(o)):
        ray = o[i] + s[:, None] * d[i]
        for j in range(len(a)):
            seg = a[j] + u[:, None] * (b[j] - a[j])
            # nearest ray sample for each segment sample, then the best pair
            gap = np.linalg.norm(ray[::20, None, :] - seg[None, ::20, :], axis=2)
            out[i, j] = gap.min()
    return out


def test_closest_approach_matches_hand_cases():
    o = np.array([[0.0, 0.0, 0.0]])
    d = np.array([[1.0, 0.0, 0.0]])
    a = np.array([[5.0, 1.0, -2.0], [5.0, 0.0, -1.0], [-4.0, 3.0, 0.0], [2.0, 0.0, 0.5]])
    b = np.array([[5.0, 1.0, 2.0], [5.0, 0.0, 1.0], [-2.0, 3.0, 0.0], [8.0, 0.0, 0.5]])
    s, dist, closest = _closest_approach(o, d, a, b)
    # crossing 1 m to the side at x = 5; through the ray at x = 5; behind the origin (s
    # clamped to 0, the nearest end 2 m back); parallel 0.5 m above
    np.testing.assert_allclose(dist[0], [1.0, 0.0, np.hypot(2.0, 3.0), 0.5], atol=1e-12)
    np.testing.assert_allclose(s[0, :3], [5.0, 5.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(closest[0, 0], [5.0, 1.0, 0.0], atol=1e-12)


def test_closest_approach_matches_sampling_on_random_rays():
    rng = np.random.default_rng(0)
    o = rng.normal(0, 2, (6, 3))
    d = rng.normal(0, 1, (6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = rng.normal(0, 4, (5, 3)) + 6 * d[0]
    b = a + rng.normal(0, 2, (5, 3))
    _, dist, _ = _closest_approach(o, d, a, b)
    sampled = _brute_force(o, d, a, b)
    assert np.all(dist <= sampled + 1e-9)  # never farther than a sampled pair
    np.testing.assert_allclose(dist, sampled, atol=0.05)


def test_skeleton_is_deterministic_inside_the_crown_and_tapers():
    tree = _tree()
    a, b, r = crown_skeleton(tree)
    a2, b2, r2 = crown_skeleton(_tree())
    np.testing.assert_array_equal(a, a2)
    np.testing.assert_array_equal(r, r2)
    assert not np.array_equal(crown_skeleton(_tree(8))[1], b)  # another tree, another shape
    assert len(r) > 30 and np.all(r > 0)
    assert r[0] == max(r) and min(r) < 0.2 * r[0]  # stem thickest, twigs a fraction of it
    # every limb ends inside the crown's ellipsoid
    inside = np.sum(((b - tree.crown_center) / tree.crown_radii) ** 2, axis=1)
    assert np.all(inside <= 1.0 + 1e-9)
    assert np.isclose(a[0, 2], tree.trunk_height)  # the stem starts at the trunk's top


def test_a_ray_at_a_wide_limb_stops_on_its_surface_and_a_far_one_only_veils():
    tree = _tree()
    limbs = CrownLimbs([tree])
    limbs._skeletons[7] = (
        np.array([[10.0, 5.0, 3.0]]),
        np.array([[10.0, 5.0, 7.0]]),
        np.array([0.1]),
    )
    # horizontal ray towards the vertical limb's axis, from 2 m away
    origin = np.array([[8.0, 5.0, 4.0]])
    direction = np.array([[1.0, 0.0, 0.0]])
    got = limbs.intersect(origin, direction, np.array([7]), np.array([3.0]), 1e-3)
    np.testing.assert_allclose(got.distance[0], 1.9, atol=1e-9)
    np.testing.assert_allclose(got.normal[0], [-1.0, 0.0, 0.0], atol=1e-6)
    assert got.cover[0] == 0
    # a ray passing 0.15 m beside it misses; one above its top misses
    miss = limbs.intersect(
        np.array([[8.0, 5.15, 4.0], [8.0, 5.0, 7.3]]), np.repeat(direction, 2, 0),
        np.array([7, 7]), np.array([3.0, 3.0]), 1e-3,
    )  # fmt: skip
    assert np.all(np.isinf(miss.distance)) and np.all(miss.cover == 0)
    # the same ray seen from 2 km with a wide pixel (half a pixel 2 m wide): it only veils,
    # by the share of the pixel the limb covers
    far = limbs.intersect(origin, direction, np.array([7]), np.array([2000.0]), 2e-3)
    assert np.isinf(far.distance[0])
    np.testing.assert_allclose(far.cover[0], 0.1 / (0.5 * 2e-3 * (2000.0 + 2.0)), rtol=1e-6)


def test_the_path_through_a_crown_matches_the_chords_of_its_sphere():
    radius = 2.0
    tree = Tree(3, np.zeros(3), 0.2, 3.0, np.array([0.0, 0.0, 5.0]), np.full(3, radius))
    limbs = CrownLimbs([tree])
    limbs._skeletons[3] = (
        np.array([[0.0, 9.0, 0.0]]),
        np.array([[0.0, 9.0, 1.0]]),
        np.array([0.01]),
    )
    x = np.array([1.0, 0.0, 0.0])
    # entering on the surface at the impact parameters 0, 1.2 and 1.9 m along +x, missing the
    # one limb (far to the side)
    offsets = np.array([0.0, 1.2, 1.9])
    origins = np.stack(
        [-np.sqrt(radius**2 - offsets**2), np.zeros(3), 5.0 + offsets], axis=1
    )  # fmt: skip
    dirs = np.repeat(x[None], 3, 0)
    got = limbs.intersect(origins, dirs, np.full(3, 3), np.full(3, 10.0), 1e-3)
    assert np.all(np.isinf(got.distance))
    np.testing.assert_allclose(got.path, 2.0 * np.sqrt(1.0 - (offsets / radius) ** 2), rtol=1e-12)
    # stopped 1 m in, at a wide limb across the middle ray: 1 m of a 2 m radius
    limbs._skeletons[3] = (
        np.array([[-0.9, 0.0, 4.0]]),
        np.array([[-0.9, 0.0, 6.0]]),
        np.array([0.1]),
    )
    stopped = limbs.intersect(origins[:1], dirs[:1], np.array([3]), np.array([10.0]), 1e-3)
    np.testing.assert_allclose(stopped.distance, [1.0], rtol=1e-12)
    np.testing.assert_allclose(stopped.path, [0.5], rtol=1e-12)
    # an ellipsoid crown: the same in its scaled frame (half the crown's x radius, then 4 m)
    wide = Tree(4, np.zeros(3), 0.2, 3.0, np.array([0.0, 0.0, 5.0]), np.array([4.0, 2.0, 2.0]))
    wide_limbs = CrownLimbs([wide])
    wide_limbs._skeletons[4] = limbs._skeletons[3][:2] + (np.array([0.0]),)
    got = wide_limbs.intersect(
        np.array([[-4.0, 0.0, 5.0]]), dirs[:1], np.array([4]), np.array([10.0]), 1e-3
    )
    np.testing.assert_allclose(got.path, [2.0], rtol=1e-12)


def test_twig_speckle_is_fixed_in_the_world_with_mean_one():
    rng = np.random.default_rng(0)
    X = rng.uniform(-20.0, 20.0, (200_000, 3))
    a = twig_speckle(X, np.full(len(X), 5))
    np.testing.assert_array_equal(a, twig_speckle(X, np.full(len(X), 5)))
    assert np.all(a >= 0) and abs(a.mean() - 1.0) < 0.02
    assert a.std() > 0.8  # sky shows through some pixels, others are dense
    b = twig_speckle(X, np.full(len(X), 6))  # another tree, other twigs
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.02
    # the clumps are smooth: nearby points (1 mm) share their clump, not always their twig
    near = twig_speckle(X + 1e-3, np.full(len(X), 5))
    assert np.corrcoef(a, near)[0, 1] > 0.9


def test_a_mean_path_through_the_twig_mass_covers_as_much_as_the_flat_haze():
    mass = mass_cover(np.array([0.0, _MEAN_CHORD, 2.0, 0.2], np.float32), 0.3)
    haze = haze_cover(np.array([0, 2, 3, 0]), 0.3)
    assert mass.dtype == haze.dtype == np.float32
    assert mass[0] == 0 and haze[0] == 0  # no twigs in front
    np.testing.assert_allclose(haze[1:3], [1 - 0.7**2, 1 - 0.7**3], rtol=1e-6)
    np.testing.assert_allclose(mass[1], haze[1], rtol=1e-5)  # a mean path: two surfaces
    # across the middle (path 2) denser than the mean, near the rim (0.2) thinner
    assert mass[2] > mass[1] > mass[3] > 0
    # veiled by the share covered, with the twigs' colour
    cond = get_condition("winter")
    rgb = np.tile(np.float32([0.6, 0.7, 0.9]), (4, 1))
    veil(rgb, mass, cond)
    np.testing.assert_array_equal(rgb[0], np.float32([0.6, 0.7, 0.9]))
    expected = (1 - mass[1]) * np.float32([0.6, 0.7, 0.9]) + mass[1] * twig_colour(cond)
    np.testing.assert_allclose(rgb[1], expected, rtol=1e-6)


@pytest.fixture(scope="module")
def crown_scene(first_frame):
    return first_frame(lambda labels: (labels == VEGETATION).sum() > 300)


def test_limbs_change_only_the_bare_crowns(crown_scene):
    renderer, pose, time_s, base = crown_scene
    bare = renderer.render(*pose, time_s=time_s, variation=Variation(bare_trees=True))
    limbs = renderer.render(*pose, time_s=time_s, variation=Variation(bare_trees=True, limbs=True))
    outside = base.labels != VEGETATION
    for key in ("rgb", "labels", "depth"):
        np.testing.assert_array_equal(getattr(limbs, key)[outside], getattr(bare, key)[outside])
    # inside the crowns: some rays stop on limbs (vegetation), others show what lies behind
    inside = ~outside
    assert (limbs.labels[inside] == VEGETATION).sum() > 10
    assert (limbs.labels[inside] != VEGETATION).sum() > 10
    assert not np.array_equal(limbs.labels, bare.labels)  # not the voxel branches
    # leafy crowns: limbs change nothing
    leafy = renderer.render(*pose, time_s=time_s, variation=Variation(limbs=True))
    np.testing.assert_array_equal(leafy.rgb, base.rgb)
    np.testing.assert_array_equal(leafy.labels, base.labels)


def test_the_twig_mass_veils_only_the_crowns_of_limbs_and_keeps_their_labels(crown_scene):
    renderer, pose, time_s, base = crown_scene
    limbs = Variation(bare_trees=True, limbs=True)
    plain = renderer.render(*pose, time_s=time_s, variation=limbs)
    twigs = dataclasses.replace(limbs, twig_density=0.4)
    frame = renderer.render(*pose, time_s=time_s, variation=twigs)
    for key in ("labels", "depth"):
        np.testing.assert_array_equal(getattr(frame, key), getattr(plain, key))
    changed = np.any(frame.rgb != plain.rgb, axis=2)
    assert changed.sum() > 100
    assert not changed[base.labels != VEGETATION].any()  # only where crowns are
    # behind voxel branches the same density is the flat haze: another image
    voxels = dataclasses.replace(twigs, limbs=False)
    assert not np.array_equal(
        renderer.render(*pose, time_s=time_s, variation=voxels).rgb, frame.rgb
    )


def test_limbs_with_the_crown_label_keep_the_leafy_labels(crown_scene):
    renderer, pose, time_s, base = crown_scene
    v = Variation(bare_trees=True, limbs=True, bare_crown_label=True)
    frame = renderer.render(*pose, time_s=time_s, variation=v)
    np.testing.assert_array_equal(frame.labels, base.labels)


def test_limbs_are_drawn_last_and_stay_out_of_the_cache_key_when_off():
    on = dataclasses.replace(REALISTIC_FURNISHED, p_limbs=1.0)
    for seed in range(10):
        a = draw_variation(REALISTIC_FURNISHED, np.random.default_rng(seed))
        b = draw_variation(on, np.random.default_rng(seed))
        assert not a.limbs and b.limbs
        assert dataclasses.replace(b, limbs=False) == a
        assert cache_fields(b)["limbs"] is True
        assert "limbs" not in cache_fields(a)
    assert RealismConfig(p_limbs=0.5).enabled


def test_the_crown_label_keeps_branches_the_sky_behind_and_dense_twigs():
    kinds = [SurfaceKind.CROWN] + [SurfaceKind.FACADE] * 4 + [255]
    hits = SimpleNamespace(
        crown=np.array([True, True, True, True, False, True]),
        kind=np.array(kinds),
        passes=np.array([1, 2, 2, 1, 0, 1]),
        cover=np.float32([0.0, 0.6, 0.1, 0.0, 0.0, 0.0]),  # thin limbs
        twigs=None,  # voxel branches: a flat haze
    )
    sky = np.array([False] * 5 + [True])  # the last ray goes through its crown to the sky
    # the flat haze of density 0.3 covers 0.3 per crown surface: with the limbs 0.804, 0.559
    # and 0.3 of the three rays that went through to a facade; the first stopped at a branch
    np.testing.assert_array_equal(labelled_crown(hits, sky, 0.3, 0.0), hits.crown)
    np.testing.assert_array_equal(labelled_crown(hits, sky, 0.3, 0.55), [1, 1, 1, 0, 0, 1])
    np.testing.assert_array_equal(labelled_crown(hits, sky, 0.3, 0.6), [1, 1, 0, 0, 0, 1])
    np.testing.assert_array_equal(labelled_crown(hits, sky, 0.0, 0.55), [1, 1, 0, 0, 0, 1])
    # behind limbs the twig mass's cover counts instead of the haze
    hits.twigs = np.float32([0.0, 0.0, 2.0, 0.1, 0.0, 0.0])
    np.testing.assert_array_equal(labelled_crown(hits, sky, 0.3, 0.55), [1, 1, 1, 0, 0, 1])


def test_the_crown_label_cover_narrows_the_silhouette_to_what_the_twigs_cover(crown_scene):
    renderer, pose, time_s, base = crown_scene
    plain = Variation(bare_trees=True, limbs=True, twig_density=0.4)
    whole = dataclasses.replace(plain, bare_crown_label=True)
    dense = dataclasses.replace(whole, crown_label_cover=0.5)
    frames = {v: renderer.render(*pose, time_s=time_s, variation=v) for v in (plain, whole, dense)}
    for key in ("rgb", "depth", "normals"):
        np.testing.assert_array_equal(getattr(frames[dense], key), getattr(frames[whole], key))
    veg = {v: f.labels == VEGETATION for v, f in frames.items()}
    # between the limbs alone and the whole silhouette, strictly
    assert np.all(veg[dense] <= veg[whole]) and np.all(veg[plain] <= veg[dense])
    assert veg[plain].sum() < veg[dense].sum() < veg[whole].sum()
    # where the crown's label gives way, what lies behind labels the pixel, never the sky
    given_way = veg[whole] & ~veg[dense]
    np.testing.assert_array_equal(frames[dense].labels[given_way], frames[plain].labels[given_way])
    assert not np.any(frames[dense].labels[given_way] == SKY)  # against the sky: the silhouette
    through_to_sky = veg[whole] & (frames[plain].labels == SKY)
    assert through_to_sky.sum() > 0 and np.all(veg[dense][through_to_sky])


def test_the_crown_label_cover_needs_the_crown_label_and_is_drawn_last():
    with pytest.raises(ConfigError, match="bare_crown_label"):
        RealismConfig(crown_label_cover=0.5)
    with pytest.raises(ConfigError, match="crown_label_cover"):
        RealismConfig(bare_crown_label=True, crown_label_cover=1.5)
    before = dataclasses.replace(REALISTIC_FURNISHED, p_limbs=0.8)
    after = dataclasses.replace(before, crown_label_cover=0.5)
    for seed in range(5):
        a = draw_variation(before, np.random.default_rng(seed))
        b = draw_variation(after, np.random.default_rng(seed))
        assert dataclasses.replace(b, crown_label_cover=0.0) == a
        assert cache_fields(b)["crown_label_cover"] == 0.5
        assert "crown_label_cover" not in cache_fields(a)
