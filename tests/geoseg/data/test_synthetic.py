"""Synthetic frames: aligned typed samples, determinism, the cache, held-out data, patches."""

import dataclasses

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import geoseg.data.synthetic as synthetic
import geoseg.synth.renderer as renderer_module
import geoseg.synth.world as world_module
from geoseg.classes import IGNORE_INDEX, NUM_CLASSES, SKY
from geoseg.config import from_dict
from geoseg.data.synthetic import (
    EVAL_SEEDS,
    HELDOUT_CONDITIONS,
    PatchDataset,
    SyntheticConfig,
    SyntheticDataset,
    prerender,
    synthetic_config,
)
from geoseg.errors import ConfigError

SIZE = (24, 32)


def _config(**kw) -> SyntheticConfig:
    base = dict(seeds=[1], frames=3, conditions=["summer_day", "winter"], drives_per_city=2)
    base.update(kw)
    return SyntheticConfig(**base)


@pytest.fixture
def render_spy(monkeypatch):
    calls = []
    real = renderer_module.render

    def spy(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(renderer_module, "render", spy)
    return calls


def test_samples_are_aligned_and_typed():
    ds = SyntheticDataset(_config(), size=SIZE)
    s = ds[0]
    assert s["image"].shape == (3, *SIZE) and s["image"].dtype == torch.float32
    assert 0.0 <= float(s["image"].min()) and float(s["image"].max()) <= 1.0
    assert s["labels"].shape == SIZE and s["labels"].dtype == torch.int64
    assert s["normals"].shape == (3, *SIZE) and s["normals"].dtype == torch.float32
    assert s["normal_valid"].shape == SIZE and s["normal_valid"].dtype == torch.bool
    lab, valid, n = s["labels"], s["normal_valid"], s["normals"]
    assert ((lab >= 0) & (lab < NUM_CLASSES)).all()
    # sky has no normal, every surface has a unit one
    assert torch.equal(valid, lab != SKY)
    norms = n.norm(dim=0)
    assert torch.allclose(norms[valid], torch.ones(int(valid.sum())), atol=2e-3)
    assert (norms[~valid] == 0).all()
    assert s["seed"] == 1 and s["condition"] in ("summer_day", "winter")
    assert s["rig"] in ("car", "tram")


def test_deterministic_per_index_and_indices_differ():
    a = SyntheticDataset(_config(), size=SIZE)
    b = SyntheticDataset(_config(), size=SIZE)
    s0, t0 = a[1], b[1]
    for key in ("image", "labels", "normals", "normal_valid"):
        assert torch.equal(s0[key], t0[key])
    assert not torch.equal(a[0]["image"], s0["image"])
    # the same index is the same frame whatever the dataset length
    longer = SyntheticDataset(_config(frames=5), size=SIZE)
    assert torch.equal(longer[1]["image"], s0["image"])


def test_cache_is_used_on_second_access(tmp_path, render_spy, monkeypatch):
    ds = SyntheticDataset(_config(), size=SIZE, cache_dir=tmp_path)
    first = ds[2]
    assert len(render_spy) == 1
    synthetic._WORLDS.clear()
    builds = []
    real_build = world_module.build_world
    monkeypatch.setattr(world_module, "build_world", lambda c: builds.append(1) or real_build(c))
    again = SyntheticDataset(_config(), size=SIZE, cache_dir=tmp_path)[2]
    assert len(render_spy) == 1  # read from the cache, not rendered
    assert builds == []  # a warm cache needs no city
    for key in ("image", "labels", "normals", "normal_valid"):
        assert torch.equal(first[key], again[key])
    assert len(list(tmp_path.rglob("*.npz"))) == 1
    assert not list(tmp_path.rglob("*.tmp"))


def test_corrupted_cache_entry_is_rerendered(tmp_path, render_spy):
    ds = SyntheticDataset(_config(), size=SIZE, cache_dir=tmp_path)
    good = ds[0]
    (entry,) = tmp_path.rglob("*.npz")
    entry.write_bytes(b"not a zip file")
    again = ds[0]
    assert len(render_spy) == 2
    assert torch.equal(good["image"], again["image"])
    third = SyntheticDataset(_config(), size=SIZE, cache_dir=tmp_path)[0]  # repaired entry
    assert len(render_spy) == 2 and torch.equal(third["labels"], good["labels"])


def test_prerender_fills_the_cache(tmp_path, render_spy):
    ds = SyntheticDataset(_config(), size=SIZE, cache_dir=tmp_path)
    assert prerender(ds, progress=False) == 3
    assert len(list(tmp_path.rglob("*.npz"))) == 3
    n = len(render_spy)
    for i in range(3):
        ds[i]
    assert len(render_spy) == n
    assert prerender(ds, progress=False) == 0 and len(render_spy) == n  # all cached: skipped


def test_held_out_seed_and_condition_are_refused():
    with pytest.raises(ConfigError, match="held-out evaluation"):
        _config(seeds=[1, EVAL_SEEDS[0]])
    with pytest.raises(ConfigError, match="held-out condition"):
        _config(conditions=["summer_day", HELDOUT_CONDITIONS[0]])
    # evaluation sets opt in explicitly
    test = synthetic_config({}, split="test")
    assert test.allow_heldout and test.seeds == list(EVAL_SEEDS)
    train = synthetic_config({"train": {"frames": 7}}, split="train")
    assert EVAL_SEEDS[0] not in train.seeds
    assert not set(train.conditions) & set(HELDOUT_CONDITIONS)
    ds = SyntheticDataset(_config(seeds=[1, 2], frames=4), size=SIZE)
    assert {ds.spec(i).seed for i in range(len(ds))} == {1, 2}


def test_unknown_synth_key_is_named():
    with pytest.raises(ConfigError, match="data.synth.val.bogus"):
        synthetic_config({"val": {"bogus": 1}}, split="val")
    with pytest.raises(ConfigError, match="synth.world"):
        synthetic_config({"world": {"no_such_key": 1}}, split="train")


def test_works_with_worker_processes():
    ds = SyntheticDataset(_config(frames=2), size=SIZE)
    direct = [ds[i]["labels"] for i in range(2)]
    loader = DataLoader(ds, batch_size=1, num_workers=2)
    got = [b["labels"][0] for b in loader]
    assert all(torch.equal(a, b) for a, b in zip(direct, got))


def test_patch_dataset_is_class_balanced_and_centred():
    frames = SyntheticDataset(_config(frames=2), size=SIZE)
    patches = PatchDataset(frames, patches_per_frame=40, seed=0)
    assert len(patches) == 80
    p = patches[5]
    assert p["image"].shape == (3, 46, 46) and p["labels"].dtype == torch.int64
    y, x = p["yx"].tolist()
    assert int(frames[0]["labels"][y, x]) == int(p["labels"])
    # the centre pixel of the patch is the frame's pixel
    assert torch.allclose(p["image"][:, 23, 23], frames[0]["image"][:, y, x], atol=1 / 255)
    labels = np.array([int(patches[i]["labels"]) for i in range(40)])
    present = np.unique(frames[0]["labels"].numpy())
    present = present[present != IGNORE_INDEX]
    assert set(np.unique(labels)) <= set(present)
    assert len(np.unique(labels)) >= min(3, len(present))  # not dominated by the big classes
    assert torch.equal(patches[5]["image"], PatchDataset(frames, patches_per_frame=40)[5]["image"])


def test_realism_draws_per_index_and_keeps_the_plain_cache_keys():
    from geoseg.synth.realism import REALISTIC

    plain = SyntheticDataset(_config(), size=SIZE)
    assert plain.spec(0).variation is None
    real = SyntheticDataset(_config(realism=REALISTIC), size=SIZE)
    spec = real.spec(0)
    assert spec.variation is not None and spec.variation == real.spec(0).variation
    assert real.spec(1).variation != spec.variation
    # the same pose and condition: the draw alone changes the cache key
    assert dataclasses.replace(spec, variation=None) == plain.spec(0)
    assert real.cache_key(spec) != plain.cache_key(plain.spec(0))
    # the labels are the plain frame's wherever the geometry options did not fire
    no_geometry = dataclasses.replace(REALISTIC, p_bare_trees=0.0, p_lens=0.0)
    varied = SyntheticDataset(_config(realism=no_geometry), size=SIZE)
    assert torch.equal(varied[2]["labels"], plain[2]["labels"])
    assert not torch.equal(varied[2]["image"], plain[2]["image"])
    config = synthetic_config({"realism": {"p_sky": 0.5}}, split="train")
    assert config.realism.p_sky == 0.5


def test_kerb_lane_drives_move_the_car_camera_towards_the_kerb():
    plain = SyntheticDataset(_config(rigs=["car"], frames=6), size=SIZE)
    near = SyntheticDataset(
        _config(rigs=["car"], frames=6, kerb_lane_share=0.5, kerb_lane_m=(1.0, 1.0)), size=SIZE
    )
    seed = near.config.seeds[0]
    assert near.config.lane_shift("car", 0, seed) == 1.0  # drive 0 of 2 runs near the kerb
    assert near.config.lane_shift("car", 1, seed) == 0.0
    assert near.config.lane_shift("tram", 0, seed) == 0.0
    assert plain.config.lane_shift("car", 0, seed) == 0.0
    moved = 0
    for i in range(6):
        spec = near.spec(i)
        assert spec == plain.spec(i)  # the same draws: only the drive's lane moves
        _, _, R_wc, t_near, _ = near._camera(spec)
        _, _, _, t_plain, _ = plain._camera(spec)
        same_key = near.cache_key(spec) == plain.cache_key(spec)
        if spec.drive_id == 0:
            # to the right of the travel direction (the right-hand lane's kerb): camera +x
            assert (t_near - t_plain) @ R_wc[:, 0] > 0.5 and not same_key
            moved += 1
        else:
            np.testing.assert_array_equal(t_near, t_plain)
            assert same_key
    assert moved
    with pytest.raises(ConfigError, match="kerb_lane_m"):
        _config(kerb_lane_m=(0.5, 2.0))
    with pytest.raises(ConfigError, match="kerb_lane_share"):
        _config(kerb_lane_share=1.5)


def test_narrow_street_cities_are_the_first_of_each_preset_and_keep_the_others_keys():
    seeds = [1, 2, 3, 4, 5, 6]  # presets alternate: light, dense, light, dense, ...
    narrow = _config(seeds=seeds, narrow_street_share=0.5, world={"buildings": {"storeys_max": 6}})
    plain = _config(seeds=seeds, world={"buildings": {"storeys_max": 6}})
    # 3 cities per preset, round(0.5 * 3) = 2 of each: the first four seeds
    assert [narrow.is_narrow(s) for s in seeds] == [True] * 4 + [False] * 2
    for seed in seeds:
        world = narrow.world_config(seed)
        if narrow.is_narrow(seed):
            assert (world.street_width, world.parking_width) == (9.0, 0.0)
            assert world.sidewalk_width == 2.5
            assert world.buildings.setback_max == 0.3
            assert world.buildings.storeys_max == 6  # the shared keys stay beside them
            assert world.preset == plain.world_config(seed).preset
        else:
            assert world == plain.world_config(seed)
    # a kerb-lane drive keeps the camera 1.2 m from a kerb without a parking strip
    near = _config(
        seeds=seeds, narrow_street_share=1.0, kerb_lane_share=0.5, kerb_lane_m=(1.4, 1.4)
    )
    world = near.world_config(1)
    assert near.lane_shift("car", 0, 1) == pytest.approx(world.lane_offset - 1.2)
    assert _config(seeds=seeds, kerb_lane_share=0.5, kerb_lane_m=(1.4, 1.4)).lane_shift(
        "car", 0, 1
    ) == pytest.approx(1.4)  # behind the default parking strip: as asked

    plain_ds = SyntheticDataset(_config(seeds=[1, 2], frames=6), size=SIZE)
    narrow_ds = SyntheticDataset(
        _config(seeds=[1, 2], frames=6, narrow_street_share=1.0), size=SIZE
    )
    for i in range(6):
        spec = narrow_ds.spec(i)
        assert spec == plain_ds.spec(i)
        assert narrow_ds.cache_key(spec) != plain_ds.cache_key(spec)  # another city: re-rendered
    with pytest.raises(ConfigError, match="narrow_street_share"):
        _config(narrow_street_share=1.5)
    with pytest.raises(ConfigError, match="narrow_street.seed"):
        _config(narrow_street={"seed": 3})
    with pytest.raises(ConfigError, match="parking_width"):  # checked for every city now
        _config(narrow_street_share=1.0, narrow_street={"street_width": 6.0, "parking_width": 2.0})


def test_narrow_street_variants_are_taken_in_turn_and_keep_a_single_variants_cache_keys():
    seeds = [1, 2, 3, 4, 5, 6, 7, 8]  # presets alternate: light, dense, light, dense, ...
    bare = {"street_width": 9.0, "parking_width": 0.0}
    parked = {"street_width": 11.0, "parking_width": 2.0}
    mixed = _config(seeds=seeds, narrow_street_share=0.75, narrow_street=[bare, parked])
    # 4 cities per preset, round(0.75 * 4) = 3 narrow: ranks 0, 2 bare, rank 1 parked, rank 3 wide
    widths = [
        (mixed.world_config(s).street_width, mixed.world_config(s).parking_width) for s in seeds
    ]
    assert widths[:6] == [(9.0, 0.0)] * 2 + [(11.0, 2.0)] * 2 + [(9.0, 0.0)] * 2
    assert [mixed.is_narrow(s) for s in seeds] == [True] * 6 + [False] * 2
    assert mixed.world_config(7) == _config(seeds=seeds).world_config(7)
    # a one-entry list is the mapping itself: same cities, same cache keys
    single = _config(seeds=seeds[:2], frames=4, narrow_street_share=1.0, narrow_street=bare)
    listed = _config(seeds=seeds[:2], frames=4, narrow_street_share=1.0, narrow_street=[bare])
    a, b = SyntheticDataset(single, size=SIZE), SyntheticDataset(listed, size=SIZE)
    assert [a.cache_key(a.spec(i)) for i in range(4)] == [b.cache_key(b.spec(i)) for i in range(4)]
    with pytest.raises(ConfigError, match="narrow_street"):
        _config(narrow_street=[])
    with pytest.raises(ConfigError, match="narrow_street.preset"):
        _config(narrow_street=[bare, {"preset": "light"}])
    with pytest.raises(ConfigError, match="parking_width"):  # every variant is checked
        bad = {"street_width": 6.0, "parking_width": 2.0}
        _config(seeds=seeds, narrow_street_share=1.0, narrow_street=[bare, bad])


def test_clean_share_renders_some_samples_plain_and_transforms_them_apart():
    from geoseg.synth.realism import REALISTIC

    frames = 12
    plain = SyntheticDataset(_config(frames=frames), size=SIZE)
    real = SyntheticDataset(_config(frames=frames, realism=REALISTIC), size=SIZE)

    def mark(tag):
        def transform(sample):
            return {**sample, "tag": tag}

        return transform

    mixed = SyntheticDataset(
        _config(frames=frames, realism=REALISTIC, clean_share=0.5),
        size=SIZE,
        transform=mark("randomised"),
        clean_transform=mark("clean"),
    )
    clean = [i for i in range(frames) if mixed.spec(i).clean]
    assert 0 < len(clean) < frames  # about half, drawn per index
    assert clean == [i for i in range(frames) if mixed.spec(i).clean]  # deterministic
    for i in range(frames):
        spec = mixed.spec(i)
        # the same pose and condition as without the clean share
        assert dataclasses.replace(spec, variation=None, clean=False) == plain.spec(i)
        if spec.clean:
            # the plain renderer's frame (pixels, labels and cache key)
            assert spec.variation is None
            assert mixed.cache_key(spec) == plain.cache_key(plain.spec(i))
        else:
            # the randomised frames keep their draws and cache keys
            assert spec.variation == real.spec(i).variation
            assert mixed.cache_key(spec) == real.cache_key(real.spec(i))
    i, j = clean[0], next(k for k in range(frames) if k not in clean)
    sample = mixed[i]
    assert sample["tag"] == "clean"
    assert torch.equal(sample["image"], plain[i]["image"])
    assert torch.equal(sample["labels"], plain[i]["labels"])
    assert mixed[j]["tag"] == "randomised"
    assert not SyntheticDataset(_config(frames=frames, realism=REALISTIC)).spec(i).clean
    with pytest.raises(ConfigError, match="clean_share"):
        _config(clean_share=1.5)


def test_clean_samples_keep_the_crown_labels_unless_told_not_to():
    from geoseg.synth.realism import REALISTIC_STREETS, Variation

    frames = 8
    kept = SyntheticDataset(
        _config(frames=frames, realism=REALISTIC_STREETS, clean_share=0.5), size=SIZE
    )
    plain_labels = SyntheticDataset(
        _config(
            frames=frames, realism=REALISTIC_STREETS, clean_share=0.5, clean_keeps_labels=False
        ),
        size=SIZE,
    )
    plain = SyntheticDataset(_config(frames=frames), size=SIZE)
    clean = [i for i in range(frames) if kept.spec(i).clean]
    assert clean
    for i in clean:
        assert kept.spec(i).variation == Variation(bare_crown_label=True)
        assert plain_labels.spec(i).variation is None
        # the image is the plain renderer's either way
        assert torch.equal(kept[i]["image"], plain[i]["image"])
        assert torch.equal(plain_labels[i]["labels"], plain[i]["labels"])
    with pytest.raises(ConfigError, match="clean_keeps_labels"):
        _config(clean_keeps_labels="no")


def test_training_dataset_leaves_clean_samples_without_colour_or_camera_effects():
    from training.config import DataConfig
    from training.frame_data import build_frame_dataset

    synth = {"seeds": [1], "frames": 8, "drives_per_city": 2, "clean_share": 0.5}
    data = from_dict(
        DataConfig,
        {
            "source": "synth",
            "size": list(SIZE),
            "synth": synth,
            "augment": {"hflip": 0.0, "saturation": 0.5, "camera": {"p_noise": 1.0}},
        },
    )
    train = build_frame_dataset(data, "train", normalize=False)
    clean = [i for i in range(8) if train.spec(i).clean]
    noisy = [i for i in range(8) if not train.spec(i).clean]
    assert clean and noisy and train.clean_transform is not None
    bare = SyntheticDataset(train.config, size=SIZE)
    for i in clean:
        assert torch.equal(train[i]["image"], bare[i]["image"])
    for i in noisy:
        assert not torch.equal(train[i]["image"], bare[i]["image"])
    data_plain = dataclasses.replace(data, synth={**synth, "clean_share": 0.0})
    assert build_frame_dataset(data_plain, "train").clean_transform is None
