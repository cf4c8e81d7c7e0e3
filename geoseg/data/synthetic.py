"""Synthetic training frames rendered on the fly from many cities and conditions, with a cache.

:class:`SyntheticDataset` maps an index to one rendered frame. Sample ``i`` is fully determined
by ``(config, i)``: its city (``seeds[i % len(seeds)]``, round robin, the occluder preset
alternating over ``presets``), its rig (car or tram), its condition, the drive it is taken from and the pose
along that drive, plus a small yaw jitter, all drawn from a generator seeded with
``(sample_seed, i)``. The same index always gives the same frame, in any process, whatever
``frames`` is (so datasets of different lengths share their common prefix in the cache).

Held-out data: ``heldout_seeds`` (the evaluation city) and ``heldout_conditions`` (a condition
the networks never see) are refused in ``seeds`` / ``conditions`` unless ``allow_heldout`` is
set, which only evaluation sets do. Defaults: training cities 1-12, validation city 13
(:data:`VAL_SEEDS`), evaluation city :data:`EVAL_SEEDS` = 1000 under every condition including
``sun_low`` (:data:`HELDOUT_CONDITIONS`).

Cache (``cache_dir``): one compressed ``.npz`` per sample, named by the SHA-256 of (world config
and seed, condition, pose, size, :data:`RENDER_VERSION`) under a two-character sub-folder; the
pose enters as what determines it (rig, drive, position along the drive, yaw jitter), and so does
the appearance draw (:mod:`geoseg.synth.realism`) when the realism options are on, so a warm
cache is read without building any world. Writes are atomic (temporary file + ``os.replace``); an unreadable or incomplete
entry is logged, re-rendered and rewritten. Normals are stored as float16 (< 0.1 degree) and
every sample, cached or fresh, goes through the same float16 rounding, so a cached sample equals
a freshly rendered one bit for bit.

Worlds (a few seconds each to build) and drives are cached per process, keyed by the process id:
a DataLoader worker never reuses an embree scene built in its parent (embree is not fork-safe),
it builds its own on first use.

:class:`PatchDataset` cuts the naive CNN's 46x46 patches around class-balanced centres from the
frames of a frame dataset (any dataset yielding ``{"image", "labels"}``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm.auto import tqdm

from geoseg.classes import IGNORE_INDEX, NUM_CLASSES
from geoseg.config import check_range, from_dict, to_dict
from geoseg.data.npz_cache import read_npz, write_npz
from geoseg.errors import ConfigError, GeosegError
from geoseg.synth.realism import RealismConfig, Variation, cache_fields, draw_variation
from geoseg.vectors import vector_length

logger = logging.getLogger(__name__)

# Bump when the renderer's output changes: it is part of every cache key.
RENDER_VERSION = 1
TRAIN_SEEDS: tuple[int, ...] = tuple(range(1, 13))
VAL_SEEDS: tuple[int, ...] = (13,)
EVAL_SEEDS: tuple[int, ...] = (1000,)
TRAIN_CONDITIONS: tuple[str, ...] = ("summer_day", "overcast", "dusk", "night", "winter")
HELDOUT_CONDITIONS: tuple[str, ...] = ("sun_low",)
SAMPLE_KEYS = ("image", "labels", "normals", "normal_valid")
_MAX_WORLDS = 16  # per process
_DRIVE_FPS = 5.0  # frames per second of the drives poses are taken from
MIN_KERB_CLEARANCE_M = 1.2  # a car's camera (its middle) stays this far from the kerb
_CACHE_FIELDS = ("rgb", "labels", "normals", "normal_valid")


@dataclass
class SyntheticConfig:
    """What a synthetic dataset renders.

    Attributes:
        world: :class:`~geoseg.synth.world.WorldConfig` keys shared by every city (not ``seed``
            nor ``preset``), e.g. ``{"blocks_x": 3}``.
        presets: occluder presets, alternating over the cities.
        seeds: city seeds of this dataset.
        heldout_seeds: evaluation cities, refused in ``seeds`` unless ``allow_heldout``.
        conditions: appearance conditions drawn uniformly.
        heldout_conditions: conditions refused in ``conditions`` unless ``allow_heldout``.
        allow_heldout: only for evaluation sets.
        rigs: camera rigs drawn uniformly (``car``: forward camera; ``tram``: side camera).
        frames: dataset length.
        drives_per_city: distinct drives (routes) per city and rig that poses are taken from.
        drive_length_m: length of each drive, metres.
        yaw_jitter_deg: uniform yaw perturbation of the camera, +- degrees.
        sample_seed: seeds the per-index draws (another value, other frames).
        hfov_deg: horizontal field of view (None: the rig's default, 70 degrees).
        realism: per-frame appearance randomisation
            (:class:`~geoseg.synth.realism.RealismConfig`, all off by default): each sample
            draws its :class:`~geoseg.synth.realism.Variation` from ``(sample_seed, i)``.
        kerb_lane_share: share of each city's car drives that run nearer the kerb (0: none):
            the first ``round(kerb_lane_share * drives_per_city)`` drive ids.
        kerb_lane_m: range of their shift towards the kerb from the middle of the lane, metres
            (spread evenly over those drives; at most 1.4 m, which keeps the camera clear of the
            parked cars of the default 2.2 m parking strip).
        clean_share: share of the samples kept clean (0: none): drawn from ``(sample_seed, i)``,
            such a sample is rendered without the :attr:`realism` options (the plain renderer's
            pixels and labels, its pose unchanged) and transformed by the dataset's
            ``clean_transform`` (training: no colour jitter, no camera effects), so that a
            randomised training set keeps some frames as the held-out synthetic frames look.
        clean_keeps_labels: clean samples keep the realism label option ``bare_crown_label``
            (a labelling convention, not an appearance variation: a clean frame's pixels are the
            plain renderer's either way); False: the plain renderer's labels too.
        narrow_street_share: share of the cities built with :attr:`narrow_street` (0: none):
            the first ``round(narrow_street_share * n)`` cities of each preset, ``n`` the
            cities per preset. Old city centres have streets without parking strips and
            narrow pavements, so the camera sees the facades at a few metres and at a steep
            angle, as the default 12 m carriageway with parking never shows them.
        narrow_street: :class:`~geoseg.synth.world.WorldConfig` keys of those cities, over
            :attr:`world` (default: a 9 m carriageway without parking strips, 2.5 m pavements,
            facades at most 0.3 m behind them); or a list of such variants, which the narrow
            cities of each preset take in turn (e.g. one without parking strips and one with
            them: half the old town's streets lined with parked cars).
    """

    world: dict[str, Any] = field(default_factory=dict)
    presets: list[str] = field(default_factory=lambda: ["light", "dense_occlusion"])
    seeds: list[int] = field(default_factory=lambda: list(TRAIN_SEEDS))
    heldout_seeds: list[int] = field(default_factory=lambda: list(EVAL_SEEDS))
    conditions: list[str] = field(default_factory=lambda: list(TRAIN_CONDITIONS))
    heldout_conditions: list[str] = field(default_factory=lambda: list(HELDOUT_CONDITIONS))
    allow_heldout: bool = False
    rigs: list[str] = field(default_factory=lambda: ["car", "tram"])
    frames: int = 1200
    drives_per_city: int = 8
    drive_length_m: float = 200.0
    yaw_jitter_deg: float = 4.0
    sample_seed: int = 0
    hfov_deg: float | None = None
    realism: RealismConfig = field(default_factory=RealismConfig)
    kerb_lane_share: float = 0.0
    kerb_lane_m: tuple[float, float] = (0.6, 1.4)
    clean_share: float = 0.0
    clean_keeps_labels: bool = True
    narrow_street_share: float = 0.0
    narrow_street: dict[str, Any] | list[dict[str, Any]] = field(
        default_factory=lambda: {
            "street_width": 9.0,
            "parking_width": 0.0,
            "sidewalk_width": 2.5,
            "buildings": {"setback_max": 0.3},
        }
    )

    def __post_init__(self) -> None:
        from geoseg.synth.conditions import CONDITIONS
        from geoseg.synth.trajectory import RIG_DEFAULTS

        for key in ("presets", "seeds", "conditions", "rigs"):
            if not getattr(self, key):
                raise ConfigError(f"synth.{key}: expected at least one entry")
        if self.frames < 1 or self.drives_per_city < 1:
            raise ConfigError(
                f"synth.frames / synth.drives_per_city: expected >= 1, got {self.frames}, "
                f"{self.drives_per_city}"
            )
        if self.drive_length_m <= 0 or self.yaw_jitter_deg < 0:
            raise ConfigError("synth.drive_length_m > 0 and synth.yaw_jitter_deg >= 0 expected")
        if not self.narrow_variants:
            raise ConfigError("synth.narrow_street: expected a mapping or a non-empty list of them")
        sections = [("world", self.world)] + [("narrow_street", v) for v in self.narrow_variants]
        for section, keys in sections:  # WorldConfig keys, all but these two
            for key in ("seed", "preset"):
                if key in keys:
                    raise ConfigError(
                        f"synth.{section}.{key}: set it with synth.seeds / synth.presets"
                    )
        unknown = sorted(set(self.conditions) - set(CONDITIONS))
        if unknown:
            raise ConfigError(f"synth.conditions: unknown {unknown}; known {sorted(CONDITIONS)}")
        bad_rigs = sorted(set(self.rigs) - set(RIG_DEFAULTS))
        if bad_rigs:
            raise ConfigError(f"synth.rigs: unknown {bad_rigs}; known {sorted(RIG_DEFAULTS)}")
        if not self.allow_heldout:
            seeds = sorted(set(self.seeds) & set(self.heldout_seeds))
            if seeds:
                raise ConfigError(
                    f"synth.seeds: {seeds} are held-out evaluation cities (synth.heldout_seeds); "
                    "training and validation data must not use them"
                )
            conds = sorted(set(self.conditions) & set(self.heldout_conditions))
            if conds:
                raise ConfigError(
                    f"synth.conditions: {conds} are held-out conditions "
                    "(synth.heldout_conditions); training data must not use them"
                )
        check_range("synth.kerb_lane_share", self.kerb_lane_share, 0.0, 1.0)
        check_range("synth.clean_share", self.clean_share, 0.0, 1.0)
        check_range("synth.narrow_street_share", self.narrow_street_share, 0.0, 1.0)
        if not isinstance(self.clean_keeps_labels, bool):
            raise ConfigError(
                f"synth.clean_keeps_labels: expected true or false, got {self.clean_keeps_labels!r}"
            )
        for i, value in enumerate(self.kerb_lane_m):
            check_range(f"synth.kerb_lane_m[{i}]", value, 0.0, 1.4)
        if self.kerb_lane_m[0] > self.kerb_lane_m[1]:
            raise ConfigError(f"synth.kerb_lane_m: expected low <= high, got {self.kerb_lane_m}")
        for seed in self.seeds:  # validate the world keys (shared and narrow) now
            self.world_config(seed)

    def lane_shift(self, rig: str, drive_id: int, seed: int) -> float:
        """How far drive ``drive_id`` of ``rig`` in city ``seed`` runs from the middle of its
        lane towards the kerb, metres (0 for the tram, and for the car unless
        :attr:`kerb_lane_share`): at most as far as keeps the camera
        :data:`MIN_KERB_CLEARANCE_M` from the kerb (a street without parking strips)."""
        n = round(self.kerb_lane_share * self.drives_per_city)
        if rig != "car" or drive_id >= n:
            return 0.0
        lo, hi = self.kerb_lane_m
        shift = lo + (hi - lo) * (drive_id + 0.5) / n
        world = self.world_config(seed)
        return float(min(shift, world.lane_offset + world.parking_width - MIN_KERB_CLEARANCE_M))

    @property
    def narrow_variants(self) -> list[dict[str, Any]]:
        """The :attr:`narrow_street` variants (one when it is a single mapping)."""
        ns = self.narrow_street
        return [ns] if isinstance(ns, Mapping) else list(ns)

    def narrow_variant(self, seed: int) -> dict[str, Any] | None:
        """The :attr:`narrow_street` keys city ``seed`` (one of :attr:`seeds`) is built with,
        or None for a city of :attr:`world` alone. The ``k``-th narrow city of a preset takes
        variant ``k mod len(variants)``."""
        if self.narrow_street_share <= 0 or seed not in self.seeds:
            return None
        per_preset = -(-len(self.seeds) // len(self.presets))
        rank = self.seeds.index(seed) // len(self.presets)
        if rank >= round(self.narrow_street_share * per_preset):
            return None
        variants = self.narrow_variants
        return variants[rank % len(variants)]

    def is_narrow(self, seed: int) -> bool:
        """Whether city ``seed`` (one of :attr:`seeds`) is built with :attr:`narrow_street`."""
        return self.narrow_variant(seed) is not None

    def world_config(self, seed: int) -> Any:
        """The :class:`~geoseg.synth.world.WorldConfig` of city ``seed``."""
        from geoseg.synth.world import WorldConfig

        preset = self.presets[self.seeds.index(seed) % len(self.presets)]
        data = dict(self.world)
        narrow = self.narrow_variant(seed)
        if narrow is not None:  # one level deep: `buildings` keys join the shared ones
            for key, value in narrow.items():
                shared = data.get(key)
                both_dicts = isinstance(shared, Mapping) and isinstance(value, Mapping)
                data[key] = {**shared, **value} if both_dicts else value
        data.update(seed=int(seed), preset=preset)
        return from_dict(WorldConfig, data, where="synth.world")


def synthetic_config(
    data: Mapping[str, Any] | None = None, *, split: str | None = None
) -> SyntheticConfig:
    """Build a :class:`SyntheticConfig` from a ``data.synth`` mapping and a split.

    The mapping holds the shared keys plus optional per-split sections, e.g.
    ``{"world": {...}, "train": {"frames": 1200}, "val": {"seeds": [13], "frames": 64}}``;
    the ``split`` section's keys override the shared ones. Defaults per split: ``val`` uses
    :data:`VAL_SEEDS` and 64 frames, ``test`` the evaluation city :data:`EVAL_SEEDS` under every
    condition (``allow_heldout``).

    Raises:
        ConfigError: unknown keys (named as ``data.synth.<key>``) or invalid values.
    """
    data = dict(data or {})
    splits = {k: data.pop(k) for k in ("train", "val", "test") if k in data}
    merged: dict[str, Any] = {}
    if split == "val":
        merged.update(seeds=list(VAL_SEEDS), frames=64)
    elif split == "test":
        merged.update(
            seeds=list(EVAL_SEEDS),
            frames=64,
            conditions=list(TRAIN_CONDITIONS + HELDOUT_CONDITIONS),
            allow_heldout=True,
            sample_seed=1,
        )
    merged.update(data)
    section = splits.get(split or "", None) or {}
    if not isinstance(section, Mapping):
        raise ConfigError(f"data.synth.{split}: expected a mapping, got {type(section).__name__}")
    merged.update(section)
    where = f"data.synth.{split}" if split in splits else "data.synth"
    return from_dict(SyntheticConfig, merged, where=where)


# ----------------------------------------------------------------------------- per-process caches
_WORLDS: OrderedDict[str, Any] = OrderedDict()
_DRIVES: dict[tuple, Any] = {}
_OWNER = {"pid": None}


def _own_caches() -> None:
    """Drop worlds/drives inherited from a parent process (embree scenes are not fork-safe)."""
    if _OWNER["pid"] != os.getpid():
        _WORLDS.clear()
        _DRIVES.clear()
        _OWNER["pid"] = os.getpid()


def _config_key(config: Any) -> str:
    return hashlib.sha256(json.dumps(to_dict(config), sort_keys=True).encode()).hexdigest()


def get_world(config: Any) -> Any:
    """The :class:`~geoseg.synth.world.World` of ``config``, built once per process (LRU)."""
    from geoseg.synth.world import build_world

    _own_caches()
    key = _config_key(config)
    world = _WORLDS.get(key)
    if world is None:
        world = build_world(config)
        _WORLDS[key] = world
        while len(_WORLDS) > _MAX_WORLDS:
            _WORLDS.popitem(last=False)
    else:
        _WORLDS.move_to_end(key)
    return world


def _get_drive(world: Any, world_key: str, rig: str, drive_id: int, cfg: SyntheticConfig, size):
    from geoseg.synth.trajectory import drive

    shift = cfg.lane_shift(rig, drive_id, world.config.seed)
    key = (world_key, rig, drive_id, cfg.drive_length_m, tuple(size), cfg.hfov_deg, shift)
    traj = _DRIVES.get(key)
    if traj is None:
        length = cfg.drive_length_m
        for _ in range(4):  # a short street network: halve the length until a route fits
            try:
                traj = drive(
                    world,
                    rig=rig,
                    length_m=length,
                    fps=_DRIVE_FPS,
                    seed=drive_id,
                    image_size=(size[1], size[0]),
                    hfov_deg=cfg.hfov_deg,
                    lane_offset=world.config.lane_offset + shift if shift else None,
                )
                break
            except GeosegError:
                length /= 2
        if traj is None:
            raise GeosegError(f"synth: no drive of {cfg.drive_length_m} m fits this city")
        _DRIVES[key] = traj
    return traj


# ----------------------------------------------------------------------------- the dataset
@dataclass(frozen=True)
class SampleSpec:
    """Everything that defines sample ``index`` (see the module docstring)."""

    index: int
    seed: int
    preset: str
    rig: str
    condition: str
    drive_id: int
    frame_share: float
    yaw_deg: float
    variation: Variation | None = None
    clean: bool = False


class SyntheticDataset(Dataset):
    """Frames rendered from the synthetic world, deterministic per index, optionally cached.

    Args:
        config: what to render (:class:`SyntheticConfig`).
        size: ``(H, W)`` of the rendered frames.
        cache_dir: folder of the on-disk cache (None: no cache).
        transform: applied to ``{"image", "labels", "normals"}`` (e.g.
            :func:`geoseg.data.transforms.build_transforms`); ``normal_valid`` is recomputed from
            the transformed normals.
        clean_transform: applied instead of ``transform`` to the clean samples
            (:attr:`SyntheticConfig.clean_share`; None: ``transform``).

    Each sample is ``{"image": (3, H, W) float32 in [0, 1], "labels": (H, W) int64,
    "normals": (3, H, W) float32 unit camera-frame normals (zero where invalid),
    "normal_valid": (H, W) bool, "index", "seed", "condition", "rig"}``.
    """

    def __init__(
        self,
        config: SyntheticConfig | None = None,
        *,
        size: tuple[int, int] = (240, 320),
        cache_dir: str | os.PathLike | None = None,
        transform: Callable[[dict[str, Any]], Mapping[str, Any]] | None = None,
        clean_transform: Callable[[dict[str, Any]], Mapping[str, Any]] | None = None,
    ) -> None:
        self.config = config or SyntheticConfig()
        if not isinstance(self.config, SyntheticConfig):
            raise GeosegError(f"config: expected a SyntheticConfig, got {type(config).__name__}")
        if len(size) != 2 or any(int(s) < 1 for s in size):
            raise GeosegError(f"size: expected positive (H, W), got {size!r}")
        self.size = (int(size[0]), int(size[1]))
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.transform = transform
        self.clean_transform = clean_transform
        self._world_keys = {s: _config_key(self.config.world_config(s)) for s in self.config.seeds}
        self.renders = 0  # frames rendered by this process (not read from the cache)

    def __len__(self) -> int:
        return self.config.frames

    def spec(self, index: int) -> SampleSpec:
        """The draws of sample ``index`` (no rendering)."""
        cfg = self.config
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        city = index % len(cfg.seeds)  # round robin: sample i does not depend on ``frames``
        rng = np.random.default_rng(np.random.SeedSequence([cfg.sample_seed, index, 4242]))
        seed = cfg.seeds[city]
        return SampleSpec(
            index=index,
            seed=seed,
            preset=cfg.presets[city % len(cfg.presets)],
            rig=cfg.rigs[int(rng.integers(len(cfg.rigs)))],
            condition=cfg.conditions[int(rng.integers(len(cfg.conditions)))],
            drive_id=int(rng.integers(cfg.drives_per_city)),
            frame_share=float(rng.random()),
            yaw_deg=float(rng.uniform(-cfg.yaw_jitter_deg, cfg.yaw_jitter_deg)),
            variation=self._variation(index),
            clean=self._clean(index),
        )

    def _clean(self, index: int) -> bool:
        """Whether sample ``index`` is kept clean (:attr:`SyntheticConfig.clean_share`)."""
        if self.config.clean_share <= 0:
            return False
        rng = np.random.default_rng(np.random.SeedSequence([self.config.sample_seed, index, 4444]))
        return bool(rng.random() < self.config.clean_share)

    def _variation(self, index: int) -> Variation | None:
        """Sample ``index``'s appearance draw (None when the realism options are all off or
        the sample is clean, but for the label option of :attr:`SyntheticConfig.clean_keeps_labels`)."""
        realism = self.config.realism
        if not realism.enabled:
            return None
        if self._clean(index):
            if self.config.clean_keeps_labels and realism.bare_crown_label:
                return Variation(bare_crown_label=True)  # the plain image, the crown labels
            return None
        rng = np.random.default_rng(np.random.SeedSequence([self.config.sample_seed, index, 4343]))
        return draw_variation(self.config.realism, rng)

    def _camera(self, spec: SampleSpec) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, float]:
        world = get_world(self.config.world_config(spec.seed))
        traj = _get_drive(
            world, self._world_keys[spec.seed], spec.rig, spec.drive_id, self.config, self.size
        )
        k = min(int(spec.frame_share * len(traj)), len(traj) - 1)
        yaw = np.radians(spec.yaw_deg)
        # yaw about the world's up axis, applied to the camera-to-world rotation
        c, s = np.cos(yaw), np.sin(yaw)
        R_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        R_wc = R_z @ traj.R_wc[k]
        return world, traj.K, R_wc, traj.t_wc[k], float(traj.timestamps[k])

    def cache_key(self, spec: SampleSpec) -> str:
        """SHA-256 of everything that determines the rendered pixels: the world config (with
        its seed), the condition, the pose (the rig, drive, position along it and yaw that
        define it deterministically), the size and :data:`RENDER_VERSION`. Computing it needs
        no world, so a warm cache is read without building any city."""
        payload = {
            "world": to_dict(self.config.world_config(spec.seed)),
            "condition": spec.condition,
            "rig": spec.rig,
            "drive": [spec.drive_id, self.config.drive_length_m, _DRIVE_FPS, self.config.hfov_deg],
            "frame_share": repr(spec.frame_share),
            "yaw_deg": repr(spec.yaw_deg),
            "size": list(self.size),
            "version": RENDER_VERSION,
        }
        shift = self.config.lane_shift(spec.rig, spec.drive_id, spec.seed)
        if shift:  # (absent when off: the older keys stay valid)
            payload["drive"].append(repr(shift))
        if spec.variation is not None:  # (absent when off: the older keys stay valid)
            payload["variation"] = repr(spec.variation)
            later = cache_fields(spec.variation)  # later options, at their defaults: absent
            if later:
                payload["variation_later"] = repr(sorted(later.items()))
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()

    def _cache_path(self, key: str) -> Path | None:
        return None if self.cache_dir is None else self.cache_dir / key[:2] / f"{key}.npz"

    def is_cached(self, index: int) -> bool:
        """Whether sample ``index`` has a cache file (not decoded: see :meth:`render_arrays`)."""
        path = self._cache_path(self.cache_key(self.spec(index)))
        return path is not None and path.is_file()

    def render_arrays(self, index: int) -> dict[str, np.ndarray]:
        """The raw arrays of sample ``index`` (from the cache when present): ``rgb (H, W, 3)
        uint8, labels (H, W) uint8, normals (3, H, W) float16, normal_valid (H, W) bool``."""
        spec = self.spec(index)
        path = self._cache_path(self.cache_key(spec))
        if path is not None and path.is_file():
            arrays = _read_entry(path, self.size)
            if arrays is not None:
                return arrays
        from geoseg.synth.renderer import render

        world, K, R_wc, t_wc, time_s = self._camera(spec)

        frame = render(
            world,
            K,
            R_wc,
            t_wc,
            (self.size[1], self.size[0]),
            spec.condition,
            time_s=time_s,
            variation=spec.variation,
        )
        self.renders += 1
        arrays = {
            "rgb": np.ascontiguousarray(frame.rgb, dtype=np.uint8),
            "labels": np.ascontiguousarray(frame.labels, dtype=np.uint8),
            "normals": np.ascontiguousarray(frame.normals, dtype=np.float16),
            "normal_valid": np.ascontiguousarray(frame.normal_valid, dtype=bool),
        }
        if path is not None:
            write_npz(path, arrays)
        return arrays

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        index %= len(self)
        spec = self.spec(index)
        a = self.render_arrays(index)
        valid = torch.from_numpy(a["normal_valid"].copy())
        normals = torch.from_numpy(a["normals"].astype(np.float32))
        normals = normals * valid[None]
        sample: dict[str, Any] = {
            "image": torch.from_numpy(a["rgb"]).permute(2, 0, 1).float().div_(255.0),
            "labels": torch.from_numpy(a["labels"].astype(np.int64)),
            "normals": normals,
        }
        transform = self.transform
        if spec.clean and self.clean_transform is not None:
            transform = self.clean_transform
        if transform is not None:
            sample = dict(transform(sample))
        sample["normal_valid"] = vector_length(sample["normals"], 0) > 0.5
        sample.update(index=index, seed=spec.seed, condition=spec.condition, rig=spec.rig)
        return sample


def _read_entry(path: Path, size: tuple[int, int]) -> dict[str, np.ndarray] | None:
    """A cache entry's arrays, or None (logged) when it is unreadable or malformed."""
    h, w = size
    expected = {"rgb": (h, w, 3), "labels": (h, w), "normals": (3, h, w), "normal_valid": (h, w)}
    arrays = read_npz(path, _CACHE_FIELDS)
    if arrays is None:
        return None
    try:
        for key, shape in expected.items():
            if arrays[key].shape != shape:
                raise ValueError(f"{key} has shape {arrays[key].shape}, expected {shape}")
        lab = arrays["labels"]
        if not ((lab < NUM_CLASSES) | (lab == IGNORE_INDEX)).all():
            raise ValueError("labels outside the class range")
        return {
            "rgb": arrays["rgb"].astype(np.uint8, copy=False),
            "labels": arrays["labels"].astype(np.uint8, copy=False),
            "normals": arrays["normals"].astype(np.float16, copy=False),
            "normal_valid": arrays["normal_valid"].astype(bool, copy=False),
        }
    except ValueError as err:
        logger.warning("cache entry %s is malformed (%s); rendering it again", path, err)
        return None


def prerender(
    dataset: SyntheticDataset,
    indices: Sequence[int] | None = None,
    *,
    num_workers: int = 0,
    progress: bool = True,
) -> int:
    """Fill ``dataset``'s cache up front (a tqdm bar shows progress).

    Args:
        dataset: a dataset with a ``cache_dir``.
        indices: samples to render (default: all); those already cached are skipped.
        num_workers: DataLoader worker processes rendering in parallel (0: this process).
        progress: show the bar.

    Returns:
        The number of samples rendered.

    Raises:
        GeosegError: the dataset has no cache directory.
    """
    if dataset.cache_dir is None:
        raise GeosegError("prerender: the dataset has no cache_dir (nothing would be kept)")
    indices = list(range(len(dataset)) if indices is None else indices)
    # cached entries are not decoded here: a corrupt one is re-rendered when it is first read
    indices = [i for i in indices if not dataset.is_cached(i)]
    raw = _ArraysOnly(dataset, indices)
    loader = torch.utils.data.DataLoader(
        raw, batch_size=None, num_workers=num_workers, collate_fn=_identity
    )
    for _ in tqdm(loader, total=len(indices), desc="prerender", disable=not progress):
        pass
    return len(indices)


def _identity(x: Any) -> Any:
    return x


class _ArraysOnly(Dataset):
    def __init__(self, dataset: SyntheticDataset, indices: list[int]) -> None:
        self.dataset, self.indices = dataset, indices

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> int:
        self.dataset.render_arrays(self.indices[i])
        return i


# ----------------------------------------------------------------------------- patches
class PatchDataset(Dataset):
    """Class-balanced 46x46 patches around pixels of a frame dataset (naive CNN training).

    Patch ``i`` comes from frame ``frames[i // patches_per_frame]``; its centre is drawn, with a
    generator seeded by ``(seed, frame)``, by first picking a class uniformly among the classes
    present in the frame, then a pixel of that class uniformly (ignored pixels never). Decoded
    frames are kept in memory per process (``(H, W, 3)`` uint8 + labels) so that the many
    patches of one frame cost one render/decode.

    Args:
        frames: a dataset of ``{"image": (3, H, W) float in [0, 1], "labels": (H, W)}`` samples
            (no normalisation: it is applied to the patch).
        patches_per_frame: patches drawn from each frame.
        num_frames: how many of ``frames`` to use (default all).
        patch_size: side of the patch (the naive CNN's 46).
        normalize: ``{"mean": [3], "std": [3]}`` applied to the patch (None: leave in [0, 1]).
        seed: seeds the centres.
        hflip: probability of a horizontal flip of the patch.

    Each sample is ``{"image": (3, P, P) float32, "labels": () int64, "yx": (2,) int64,
    "frame": int}``.
    """

    def __init__(
        self,
        frames: Dataset,
        *,
        patches_per_frame: int = 64,
        num_frames: int | None = None,
        patch_size: int = 46,
        normalize: Mapping[str, Sequence[float]] | None = None,
        seed: int = 0,
        hflip: float = 0.0,
    ) -> None:
        if patches_per_frame < 1:
            raise GeosegError(f"patches_per_frame: expected >= 1, got {patches_per_frame}")
        n = len(frames)  # type: ignore[arg-type]
        self.num_frames = n if num_frames is None else min(int(num_frames), n)
        if self.num_frames < 1:
            raise GeosegError("frames: the frame dataset is empty")
        self.frames = frames
        self.patches_per_frame = int(patches_per_frame)
        self.patch_size = int(patch_size)
        self.seed = int(seed)
        self.hflip = float(hflip)
        self.mean = self.std = None
        if normalize is not None:
            self.mean = torch.tensor(normalize["mean"], dtype=torch.float32)[:, None, None]
            self.std = torch.tensor(normalize["std"], dtype=torch.float32)[:, None, None]
        self._cache: dict[int, tuple[torch.Tensor, np.ndarray, np.ndarray]] = {}
        self._pid: int | None = None

    def __len__(self) -> int:
        return self.num_frames * self.patches_per_frame

    def _frame(self, f: int) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
        if self._pid != os.getpid():
            self._cache, self._pid = {}, os.getpid()
        entry = self._cache.get(f)
        if entry is None:
            sample = self.frames[f]
            image = torch.as_tensor(sample["image"]).float()
            labels = torch.as_tensor(sample["labels"]).numpy().astype(np.uint8)  # ids <= 255
            rgb = (image.clamp(0, 1) * 255).round().to(torch.uint8)
            entry = (rgb, labels, self._centres(f, labels))
            self._cache[f] = entry
        return entry

    def _centres(self, f: int, labels: np.ndarray) -> np.ndarray:
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, f, 4646]))
        flat = labels.reshape(-1)
        present = [c for c in range(NUM_CLASSES) if (flat == c).any()]
        if not present:
            raise GeosegError(f"frames[{f}]: no labelled pixel to draw a patch centre from")
        pixels = {c: np.flatnonzero(flat == c) for c in present}
        classes = rng.choice(present, self.patches_per_frame)
        picks = np.array([pixels[c][rng.integers(len(pixels[c]))] for c in classes])
        w = labels.shape[1]
        return np.stack([picks // w, picks % w], axis=1).astype(np.int64)

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} patches")
        f, k = divmod(index, self.patches_per_frame)
        rgb, labels, centres = self._frame(f)
        y, x = (int(v) for v in centres[k])
        p = self.patch_size
        lo, hi = p // 2, p - 1 - p // 2
        h, w = labels.shape
        rows = np.clip(np.arange(y - lo, y + hi + 1), 0, h - 1)
        cols = np.clip(np.arange(x - lo, x + hi + 1), 0, w - 1)
        patch = rgb[:, rows][:, :, cols].float().div_(255.0)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, index, 4747]))
        if self.hflip and rng.random() < self.hflip:
            patch = patch.flip(-1)
        if self.mean is not None:
            patch = (patch - self.mean) / self.std
        return {
            "image": patch.contiguous(),
            "labels": torch.tensor(int(labels[y, x]), dtype=torch.int64),
            "yx": torch.tensor([y, x], dtype=torch.int64),
            "frame": f,
        }


def describe(config: SyntheticConfig) -> dict[str, Any]:
    """Plain-data summary of a synthetic dataset (for model cards)."""
    return dataclasses.asdict(config)


__all__ = [
    "EVAL_SEEDS",
    "HELDOUT_CONDITIONS",
    "RENDER_VERSION",
    "TRAIN_CONDITIONS",
    "VAL_SEEDS",
    "PatchDataset",
    "SampleSpec",
    "SyntheticConfig",
    "SyntheticDataset",
    "get_world",
    "prerender",
    "synthetic_config",
]
