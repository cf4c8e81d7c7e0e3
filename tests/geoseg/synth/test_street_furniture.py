"""Extra street furniture (realism option ``p_furniture``): labels follow the new geometry,
the rest of the frame is unchanged, draws are deterministic, off by default and kept out of
the frame cache keys at their default (and so is the road texture, drawn after it)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from geoseg.classes import OBJECT
from geoseg.data.synthetic import SyntheticConfig, SyntheticDataset
from geoseg.errors import ConfigError
from geoseg.synth.realism import (
    REALISTIC_FURNISHED,
    REALISTIC_STREETS,
    RealismConfig,
    Variation,
    cache_fields,
    draw_variation,
)
from geoseg.synth.renderer import Renderer
from geoseg.synth.street_furniture import (
    FURNITURE_RADIUS,
    furniture_part,
    plate_albedo,
    pole_albedo,
)
from geoseg.synth.trajectory import drive
from geoseg.synth.world import SURFACE_CLASS

GEOMETRY = ("labels", "depth", "normals", "instance", "normal_valid")


@pytest.fixture(scope="module")
def furnished(tiny_world):
    """A frame of the tiny city with and without dense extra furniture that shows some of it."""
    renderer = Renderer(tiny_world)
    traj = drive(tiny_world, rig="car", length_m=120.0, fps=2.0, seed=3, image_size=(160, 120))
    first = len(tiny_world.instance_class)
    for i in range(len(traj)):
        pose = (traj.K, traj.R_wc[i], traj.t_wc[i], traj.image_size)
        time_s = float(traj.timestamps[i])
        var = Variation(seed=5, furniture_spacing=4.0)
        frame = renderer.render(*pose, time_s=time_s, variation=var)
        if (frame.instance >= first).sum() > 30:
            base = renderer.render(*pose, time_s=time_s, variation=Variation(seed=5))
            return frame, base, first
    raise AssertionError("no frame shows the extra furniture")


def test_furniture_labels_follow_its_geometry(furnished):
    frame, base, first = furnished
    new = frame.instance >= first  # the rays that meet the frame's furniture first
    assert (frame.labels[new] == OBJECT).all()
    assert (frame.depth[new] > 0).all()
    nearer = base.depth[new] == 0  # sky before, or something further away
    nearer |= frame.depth[new] < base.depth[new]
    assert nearer.all()
    # everywhere else the frame is the one without furniture
    for key in GEOMETRY:
        a, b = getattr(frame, key), getattr(base, key)
        if key == "normals":
            a, b = a[:, ~new], b[:, ~new]
        else:
            a, b = a[~new], b[~new]
        np.testing.assert_array_equal(a, b, err_msg=key)
    np.testing.assert_array_equal(frame.rgb[~new], base.rgb[~new])


def test_furniture_is_deterministic_and_camera_independent(tiny_world):
    centre = tiny_world.streets[0].centerline.mean(axis=0)
    a = furniture_part(tiny_world, 7, 5.0, centre)
    b = furniture_part(tiny_world, 7, 5.0, centre)
    c = furniture_part(tiny_world, 8, 5.0, centre)
    assert a is not None and c is not None
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)
    assert set(np.unique(SURFACE_CLASS[a.kind])) == {OBJECT}
    assert a.instance.min() == len(tiny_world.instance_class)
    # an item near both cameras is the same item: the draw does not depend on the camera
    moved = furniture_part(tiny_world, 7, 5.0, centre + [5.0, 0.0])
    shared = {tuple(np.round(v, 6)) for v in a.vertices} & {
        tuple(np.round(v, 6)) for v in moved.vertices
    }
    assert len(shared) > 0.5 * min(len(a.vertices), len(moved.vertices))
    assert furniture_part(tiny_world, 7, 5.0, centre + [10 * FURNITURE_RADIUS, 0.0]) is None


def test_pole_albedo_keeps_the_citys_own_poles():
    grey = [0.42, 0.44, 0.46]
    out = pole_albedo(np.array([3, 10, 11, 12]), 10, grey)
    np.testing.assert_allclose(out[0], grey)
    assert out.dtype == np.float32 and out.shape == (4, 3)


def test_furniture_draw_is_last_and_off_by_default():
    for seed in range(10):
        a = draw_variation(REALISTIC_STREETS, np.random.default_rng(seed))
        b = draw_variation(
            dataclasses.replace(REALISTIC_STREETS, p_furniture=1.0), np.random.default_rng(seed)
        )
        assert a.furniture_spacing == 0 and 4.0 <= b.furniture_spacing <= 12.0
        assert dataclasses.replace(b, furniture_spacing=0.0) == a
        # the road texture is drawn after the furniture: its draws stay
        both = dataclasses.replace(REALISTIC_STREETS, p_furniture=1.0, p_road_texture=1.0)
        c = draw_variation(both, np.random.default_rng(seed))
        assert 0.1 <= c.road_texture <= 0.8 and a.road_texture == b.road_texture == 1.0
        assert dataclasses.replace(c, road_texture=1.0) == b
    assert not RealismConfig().enabled and RealismConfig(p_furniture=0.5).enabled
    assert REALISTIC_FURNISHED.p_furniture > 0 and REALISTIC_FURNISHED.p_kerb_lines > 0


def test_furniture_stays_out_of_the_cache_key_at_its_default():
    var = Variation(seed=3, kerb_lines=0.5)
    assert "furniture" not in repr(var) and "texture" not in repr(var)
    assert cache_fields(var) == {}
    assert cache_fields(dataclasses.replace(var, road_texture=0.5)) == {"road_texture": 0.5}
    assert cache_fields(dataclasses.replace(var, furniture_spacing=6.0)) == {
        "furniture_spacing": 6.0
    }
    keys = {}
    for p in (0.0, 1.0):
        realism = dataclasses.replace(REALISTIC_STREETS, p_furniture=p)
        ds = SyntheticDataset(SyntheticConfig(frames=4, realism=realism), size=(24, 32))
        keys[p] = [ds.cache_key(ds.spec(i)) for i in range(4)]
    assert all(a != b for a, b in zip(keys[0.0], keys[1.0]))
    ds = SyntheticDataset(SyntheticConfig(frames=4, realism=REALISTIC_STREETS), size=(24, 32))
    assert [ds.cache_key(ds.spec(i)) for i in range(4)] == keys[0.0]


@pytest.mark.parametrize(
    "kwargs, key",
    [
        ({"p_furniture": 1.5}, "p_furniture"),
        ({"furniture_spacing_m": (0.5, 4.0)}, "furniture_spacing_m"),
        ({"furniture_spacing_m": (9.0, 4.0)}, "furniture_spacing_m"),
        ({"p_road_texture": -0.5}, "p_road_texture"),
        ({"road_texture": (0.5, 1.5)}, "road_texture"),
    ],
)
def test_bad_furniture_values_are_named(kwargs, key):
    with pytest.raises(ConfigError, match=key):
        RealismConfig(**kwargs)


def test_plain_plates_change_the_image_only(tiny_world, furnished):
    frame, _, first = furnished
    renderer = Renderer(tiny_world)
    traj = drive(tiny_world, rig="car", length_m=120.0, fps=2.0, seed=3, image_size=(160, 120))
    for i in range(len(traj)):
        pose = (traj.K, traj.R_wc[i], traj.t_wc[i], traj.image_size)
        time_s = float(traj.timestamps[i])
        var = Variation(seed=5, furniture_spacing=4.0)
        frame = renderer.render(*pose, time_s=time_s, variation=var)
        plates = (frame.instance >= first) & (frame.labels == OBJECT)
        plain = renderer.render(
            *pose,
            time_s=time_s,
            variation=dataclasses.replace(var, furniture_plain_plates=True),
        )
        changed = (plain.rgb != frame.rgb).any(axis=-1)
        if changed.sum() > 5:
            break
    else:
        raise AssertionError("no frame shows a plate of the extra furniture")
    for key in GEOMETRY:
        np.testing.assert_array_equal(getattr(plain, key), getattr(frame, key), err_msg=key)
    assert plates[changed].all()  # only the frame's furniture changes colour


def test_plate_albedo_is_plain_per_item_and_keeps_the_citys_own_panels():
    striped = np.random.default_rng(0).random((5, 3)).astype(np.float32)
    out = plate_albedo(np.array([3, 10, 10, 11, 12]), 10, striped)
    np.testing.assert_array_equal(out[0], striped[0])
    np.testing.assert_array_equal(out[1], out[2])  # one colour per item
    assert out.dtype == np.float32 and out.shape == (5, 3)


def _distances_from_street(world, part):
    """Each vertex's distance from the nearest street centre line (xy), metres."""
    a = np.concatenate([s.centerline[:-1] for s in world.streets])  # segment starts
    b = np.concatenate([s.centerline[1:] for s in world.streets])  # and ends
    p = part.vertices[:, None, :2]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1).min(axis=1)


def test_kerb_share_moves_the_items_not_their_draws(tiny_world):
    cfg = tiny_world.config
    half, sw = cfg.street_width / 2, cfg.sidewalk_width
    centre = tiny_world.streets[0].centerline.mean(axis=0)
    default = furniture_part(tiny_world, 7, 4.0, centre)
    kerb = furniture_part(tiny_world, 7, 4.0, centre, kerb_share=1.0)
    back = furniture_part(tiny_world, 7, 4.0, centre, kerb_share=0.0)
    assert default is not None and kerb is not None and back is not None
    # the same items moved across the sidewalk (the few near the 90 m radius may cross it)
    counts = [len(np.unique(p.instance)) for p in (default, kerb, back)]
    assert max(counts) - min(counts) <= 2
    d_kerb = _distances_from_street(tiny_world, kerb)
    d_back = _distances_from_street(tiny_world, back)
    # feet within 1.2 m of the kerb (plates and arms reach out 1-2 m), none at the back
    assert np.median(d_kerb) < half + 1.2 and np.median(d_back) > half + sw - 1.5
    assert np.median(d_kerb) < np.median(d_back)


def test_furniture_style_options_ride_on_the_furniture_draw():
    for seed in range(10):
        on = dataclasses.replace(REALISTIC_STREETS, p_furniture=1.0)
        styled = dataclasses.replace(on, furniture_kerb_share=1.0, furniture_plain_plates=True)
        a = draw_variation(on, np.random.default_rng(seed))
        b = draw_variation(styled, np.random.default_rng(seed))
        assert a.furniture_kerb_share == 0.75 and not a.furniture_plain_plates
        assert b.furniture_kerb_share == 1.0 and b.furniture_plain_plates
        assert dataclasses.replace(b, furniture_kerb_share=0.75, furniture_plain_plates=False) == a
        # without furniture the style options draw nothing and stay at their defaults
        off = dataclasses.replace(styled, p_furniture=0.0)
        c = draw_variation(off, np.random.default_rng(seed))
        assert c == draw_variation(REALISTIC_STREETS, np.random.default_rng(seed))
    assert cache_fields(Variation(furniture_spacing=6.0, furniture_kerb_share=1.0)) == {
        "furniture_spacing": 6.0,
        "furniture_kerb_share": 1.0,
    }
    with pytest.raises(ConfigError, match="furniture_kerb_share"):
        RealismConfig(furniture_kerb_share=1.5)
    with pytest.raises(ConfigError, match="furniture_plain_plates"):
        RealismConfig(furniture_plain_plates="yes")
