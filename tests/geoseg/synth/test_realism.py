"""Realism options: each appearance option changes the image only; geometry options keep the
labels consistent; draws are deterministic and off by default."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from geoseg.classes import BUILDING, ROAD, SIDEWALK, SKY, VEGETATION, VEHICLE
from geoseg.errors import ConfigError
from geoseg.synth.conditions import get_condition
from geoseg.synth.realism import (
    REALISTIC,
    REALISTIC_STREETS,
    RealismConfig,
    Variation,
    draw_variation,
)
from geoseg.synth.renderer import Renderer
from geoseg.synth.trajectory import drive

GEOMETRY = ("labels", "depth", "normals", "instance", "normal_valid")

# one appearance option at a time, and the class whose pixels it must recolour
APPEARANCE = {
    "shopfront": (Variation(seed=4, shopfront_share=1.0), BUILDING),
    "paint": (Variation(seed=4, paint_share=1.0), BUILDING),
    "vehicle_colour": (Variation(seed=4, vehicle_colour_share=1.0), VEHICLE),
    "road": (Variation(seed=4, road_gain=1.4, marking_gain=0.6), ROAD),
    "paving": (Variation(seed=4, walk_rgb=(0.7, 0.75, 0.8)), SIDEWALK),
    "light": (Variation(seed=4, sun=(300.0, 15.0, 1.2), ambient_gain=0.8), BUILDING),
    "sky": (Variation(seed=4, sky=((0.7, 0.7, 0.72), (0.85, 0.85, 0.85))), SKY),
    "clouds": (Variation(seed=4, cloud_cover=0.7), SKY),
    "shadows": (Variation(seed=4, shadows=True), ROAD),
    "kerb": (Variation(seed=4, kerb_face=0.5, slab_m=0.6), SIDEWALK),
    "road_texture": (Variation(seed=4, road_texture=0.2), ROAD),
    "posters": (Variation(seed=4, poster_share=1.0), BUILDING),
}


@pytest.fixture(scope="module")
def scene(first_frame):
    # a frame that shows every class the options recolour
    classes = (BUILDING, ROAD, SIDEWALK, SKY, VEHICLE)
    return first_frame(lambda labels: all((labels == c).sum() > 20 for c in classes))


@pytest.mark.parametrize("name", sorted(APPEARANCE))
def test_appearance_option_changes_the_image_not_the_geometry(scene, name):
    renderer, pose, time_s, base = scene
    variation, cls = APPEARANCE[name]
    frame = renderer.render(*pose, time_s=time_s, variation=variation)
    for key in GEOMETRY:
        np.testing.assert_array_equal(getattr(frame, key), getattr(base, key), err_msg=key)
    changed = np.abs(frame.rgb.astype(int) - base.rgb.astype(int)).max(axis=2) > 2
    assert changed[base.labels == cls].mean() > 0.05, name


def test_identity_variation_renders_as_before(scene):
    renderer, pose, time_s, base = scene
    frame = renderer.render(*pose, time_s=time_s, variation=Variation(seed=9))
    np.testing.assert_array_equal(frame.rgb, base.rgb)


def test_bare_trees_labels_follow_the_leafless_crowns(scene):
    renderer, pose, time_s, base = scene
    bare = renderer.render(*pose, time_s=time_s, variation=Variation(bare_trees=True))
    leafless = dataclasses.replace(get_condition("summer_day"), leaves_on=False)
    expected = renderer.render(*pose, leafless, time_s=time_s)
    for key in GEOMETRY:
        np.testing.assert_array_equal(getattr(bare, key), getattr(expected, key), err_msg=key)
    assert (bare.labels == VEGETATION).sum() < (base.labels == VEGETATION).sum()
    kept = base.labels != VEGETATION
    np.testing.assert_array_equal(bare.labels[kept], base.labels[kept])


def test_kerb_lines_paint_the_road_along_the_kerbs(scene):
    renderer, pose, time_s, base = scene
    changed_any = 0
    for seed in range(4):  # each street side draws its style: try a few
        frame = renderer.render(
            *pose, time_s=time_s, variation=Variation(seed=seed, kerb_lines=0.9)
        )
        for key in GEOMETRY:
            np.testing.assert_array_equal(getattr(frame, key), getattr(base, key), err_msg=key)
        changed = np.abs(frame.rgb.astype(int) - base.rgb.astype(int)).max(axis=2) > 2
        assert not changed[base.labels != ROAD].any()
        changed_any += int(changed.sum())
    assert changed_any > 10


def test_twigs_veil_what_shows_through_bare_crowns(scene):
    renderer, pose, time_s, base = scene
    bare = renderer.render(*pose, time_s=time_s, variation=Variation(bare_trees=True))
    twigs = Variation(bare_trees=True, twig_density=0.4)
    frame = renderer.render(*pose, time_s=time_s, variation=twigs)
    for key in GEOMETRY:
        np.testing.assert_array_equal(getattr(frame, key), getattr(bare, key), err_msg=key)
    changed = np.abs(frame.rgb.astype(int) - bare.rgb.astype(int)).max(axis=2) > 2
    crown = (base.labels == VEGETATION) & (bare.labels != VEGETATION)  # seen through a crown
    assert crown.sum() > 20 and changed[crown].mean() > 0.5
    assert not changed[base.labels != VEGETATION].any()  # nothing outside the crowns


def test_bare_crown_label_draws_the_whole_crown_vegetation(scene):
    renderer, pose, time_s, base = scene
    bare = renderer.render(*pose, time_s=time_s, variation=Variation(bare_trees=True))
    labelled = renderer.render(
        *pose, time_s=time_s, variation=Variation(bare_trees=True, bare_crown_label=True)
    )
    # the image and the geometry are the bare crowns'; the labels are the leafy crowns'
    for key in ("rgb", "depth", "normals", "instance", "normal_valid"):
        np.testing.assert_array_equal(getattr(labelled, key), getattr(bare, key), err_msg=key)
    np.testing.assert_array_equal(labelled.labels, base.labels)
    assert (labelled.labels == VEGETATION).sum() > (bare.labels == VEGETATION).sum()
    # leafy crowns: nothing to change
    leafy = renderer.render(*pose, time_s=time_s, variation=Variation(bare_crown_label=True))
    np.testing.assert_array_equal(leafy.labels, base.labels)
    np.testing.assert_array_equal(leafy.rgb, base.rgb)


def test_second_round_options_keep_the_first_rounds_draws():
    fields = [f.name for f in dataclasses.fields(Variation)]
    first = fields[: fields.index("twig_density")]
    both = dataclasses.replace(
        REALISTIC, p_twigs=1.0, p_kerb=1.0, p_kerb_lines=1.0, bare_crown_label=True
    )
    for seed in range(10):
        a = draw_variation(REALISTIC, np.random.default_rng(seed))
        b = draw_variation(both, np.random.default_rng(seed))
        assert [getattr(a, f) for f in first] == [getattr(b, f) for f in first]
        assert a.twig_density == a.kerb_face == 0 and not a.bare_crown_label
        assert b.twig_density > 0 and b.kerb_face > 0 and b.slab_m > 0 and b.bare_crown_label
        assert b.kerb_lines > 0 and a.kerb_lines == 0
        # the kerb lines are drawn last: the other second-round draws stay
        c = draw_variation(dataclasses.replace(both, p_kerb_lines=0.0), np.random.default_rng(seed))
        assert dataclasses.replace(b, kerb_lines=0.0) == c
    assert RealismConfig(bare_crown_label=True).enabled
    assert REALISTIC_STREETS.enabled and REALISTIC_STREETS.bare_crown_label


def test_overcast_draws_a_flat_grey_sky_and_a_weak_sun():
    cfg = RealismConfig(p_overcast=1.0)
    for seed in range(10):
        v = draw_variation(cfg, np.random.default_rng(seed))
        zenith, horizon = np.array(v.sky[0]), np.array(v.sky[1])
        assert np.ptp(zenith) < 0.06 and np.ptp(horizon) < 0.06  # grey, not blue
        assert np.abs(zenith - horizon).max() < 0.1 and v.cloud_cover >= 0.6
        assert v.sun[2] <= 0.4 and not v.shadows
    day = v.condition(get_condition("summer_day"))
    assert day.sun_strength < get_condition("summer_day").sun_strength


def test_lens_distortion_moves_pixels_with_their_labels(scene):
    renderer, pose, time_s, base = scene
    frame = renderer.render(*pose, time_s=time_s, variation=Variation(lens_k1=0.25))
    h, w = base.labels.shape
    K = pose[0]
    cy, cx = int(K[1, 2]), int(K[0, 2])
    # the principal point does not move; the edges do
    assert frame.labels[cy, cx] == base.labels[cy, cx]
    assert frame.depth[cy, cx] == pytest.approx(base.depth[cy, cx], rel=1e-5)
    assert (frame.labels != base.labels).mean() > 0.02
    # every channel comes from the same rays: sky has no depth and no normal, surfaces do
    sky = frame.labels == SKY
    np.testing.assert_array_equal(sky, frame.depth == 0)
    np.testing.assert_array_equal(~sky, frame.normal_valid)
    # barrel distortion (k1 > 0) shows more of the scene: the horizon's building band shrinks
    assert (frame.labels == BUILDING).sum() != (base.labels == BUILDING).sum()


def test_draws_are_deterministic_and_off_by_default():
    off = RealismConfig()
    assert not off.enabled and REALISTIC.enabled
    v = draw_variation(off, np.random.default_rng(0))
    assert dataclasses.replace(v, seed=0) == Variation()
    a = draw_variation(REALISTIC, np.random.default_rng(5))
    assert a == draw_variation(REALISTIC, np.random.default_rng(5))
    draws = [draw_variation(REALISTIC, np.random.default_rng(s)) for s in range(40)]
    assert 0 < sum(d.shopfront_share > 0 for d in draws) < 40
    assert any(d.lens_k1 != 0 for d in draws) and any(d.shadows for d in draws)
    always = RealismConfig(p_sky=1.0, cloud_cover=(0.4, 0.4))
    assert draw_variation(always, np.random.default_rng(1)).cloud_cover == 0.4


def test_variation_keeps_dusk_and_night_light():
    v = Variation(sun=(10.0, 40.0, 1.0), sky=((1.0, 1.0, 1.0), (1.0, 1.0, 1.0)))
    for name in ("dusk", "night"):
        assert v.condition(get_condition(name)) == get_condition(name)
    day = v.condition(get_condition("summer_day"))
    assert day.sun_elevation_deg == 40.0 and day.sky_zenith == (1.0, 1.0, 1.0)


@pytest.mark.parametrize(
    "kwargs, key",
    [
        ({"p_shopfront": 1.5}, "p_shopfront"),
        ({"paint_share": (0.8, 0.2)}, "paint_share"),
        ({"lens_k1": (-0.5, 0.1)}, "lens_k1"),
        ({"p_kerb": -0.1}, "p_kerb"),
        ({"p_kerb_lines": 2.0}, "p_kerb_lines"),
        ({"slab_m": (0.0, 0.5)}, "slab_m"),
        ({"bare_crown_label": "yes"}, "bare_crown_label"),
        ({"p_posters": 1.5}, "p_posters"),
        ({"poster_share": (0.5, 0.2)}, "poster_share"),
    ],
)
def test_bad_realism_values_are_named(kwargs, key):
    with pytest.raises(ConfigError, match=key):
        RealismConfig(**kwargs)


def test_lens_distortion_finds_every_moving_vehicle_pixel(tiny_world, monkeypatch):
    traj = drive(tiny_world, rig="car", length_m=120.0, fps=2.0, seed=3, image_size=(160, 120))
    renderer = Renderer(tiny_world)
    lens = Variation(lens_k1=0.2)
    frames = [
        renderer.render(
            traj.K,
            traj.R_wc[i],
            traj.t_wc[i],
            traj.image_size,
            time_s=float(traj.timestamps[i]),
            variation=lens,
        )
        for i in range(len(traj))
    ]
    # the same frames with every ray cast against the moving vehicles
    monkeypatch.setattr(Renderer, "_mover_pixels", lambda self, *args: None)
    for i, frame in enumerate(frames):
        full = renderer.render(
            traj.K,
            traj.R_wc[i],
            traj.t_wc[i],
            traj.image_size,
            time_s=float(traj.timestamps[i]),
            variation=lens,
        )
        np.testing.assert_array_equal(frame.instance, full.instance)
    assert any((f.labels == VEHICLE).any() for f in frames)


def test_posters_are_drawn_last_and_stay_out_of_the_cache_key_when_off():
    from geoseg.synth.realism import REALISTIC_FURNISHED, cache_fields

    for seed in range(10):
        a = draw_variation(REALISTIC_FURNISHED, np.random.default_rng(seed))
        b = draw_variation(
            dataclasses.replace(REALISTIC_FURNISHED, p_posters=1.0), np.random.default_rng(seed)
        )
        assert a.poster_share == 0 and 0.1 <= b.poster_share <= 0.4
        assert dataclasses.replace(b, poster_share=0.0) == a
        assert cache_fields(b)["poster_share"] == b.poster_share
        assert "poster_share" not in cache_fields(a)
    assert RealismConfig(p_posters=0.5).enabled
