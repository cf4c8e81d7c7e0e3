"""Repeated traversals of one tram route under several conditions, and their layer-21 features.

The relocalisation data of thesis §5.1: the same route driven several times (the thesis's two
428-image tram sequences, spring and winter, ~5 km), here rendered from the synthetic world.

* :class:`RouteSpec`: one city, one tram route (``geoseg.synth.trajectory.drive``, side-looking
  camera), keyframes every ``spacing_m`` metres of track, one traversal per condition. By
  default every traversal has **the same keyframe poses** (only the appearance and the moving
  vehicles differ: traversal ``k`` is rendered at world time ``t + k * time_offset_s``);
  ``offset_m`` shifts traversal ``k`` by ``k * offset_m`` metres along the track and
  ``yaw_jitter_deg`` turns its cameras by a seeded uniform yaw, for realistic (not
  pixel-aligned) repeats.
* :func:`render_route`: renders the traversals (one :class:`RouteTraversal` each: RGB images and
  camera-to-world poses), with an on-disk cache of one compressed ``.npz`` per traversal named
  by the SHA-256 of everything that determines its pixels (as :mod:`geoseg.data.synthetic`).
* :class:`TrunkFeatureExtractor`: the frozen ENet trunk (layers 1-21) of an ``enet`` or
  ``joint`` model, RGB uint8 ``(B, H, W, 3)`` -> ``(B, 128, ceil(H/8), ceil(W/8))`` features,
  exactly the ``"features"`` output of the full network (same padding and normalisation).
* :func:`traversal_features`: a traversal's features through an extractor, cached as float16
  ``.npz`` keyed by the traversal's key and the trunk's weight fingerprint.
* :func:`route_specs`: the routes of a split (training cities, validation city, held-out
  evaluation city) with deterministic per-city condition draws.

Frames (docs/architecture.md, conventions): world metric, z up; ``X_w = R_wc X_c + t_wc``; OpenCV camera frame.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

from geoseg.config import from_dict, to_dict
from geoseg.data.npz_cache import read_npz, write_npz
from geoseg.errors import ConfigError, GeosegError

logger = logging.getLogger(__name__)

__all__ = [
    "FEATURE_VERSION",
    "RouteFeatures",
    "RouteSpec",
    "RouteTraversal",
    "TrunkFeatureExtractor",
    "keyframe_poses",
    "render_route",
    "route_features",
    "route_specs",
    "traversal_features",
]

# Bump when the layer-21 extraction changes: it is part of every feature cache key.
FEATURE_VERSION = 1
_FRAME_FIELDS = ("images", "R_wc", "t_wc", "timestamps", "K")


# ============================================================================ specification


@dataclass
class RouteSpec:
    """One tram route in one city, driven once per condition.

    Attributes:
        seed: city seed (:class:`~geoseg.synth.world.WorldConfig` ``seed``).
        preset: occluder preset of the city (``light`` or ``dense_occlusion``).
        world: further ``WorldConfig`` keys (not ``seed`` / ``preset``), e.g. a bigger city.
        route_seed: picks the route (``drive(seed=...)``).
        length_m: track length covered by the keyframes, metres.
        spacing_m: track distance between consecutive keyframes, metres.
        conditions: one appearance condition per traversal (>= 1; usually 2).
        size: ``(H, W)`` of the rendered images.
        hfov_deg: horizontal field of view (None: the tram rig's 70 degrees).
        offset_m: traversal ``k`` starts ``k * offset_m`` metres further along the track.
        yaw_jitter_deg: traversals ``k >= 1``: uniform yaw perturbation (about the world's up
            axis) of each camera, +- degrees, seeded by ``(seed, route_seed, k)``.
        time_offset_s: traversal ``k`` is rendered at world time ``t + k * time_offset_s``
            (moving vehicles elsewhere).
        fps: frame rate of the underlying drive (keyframes are picked from its frames; 20 Hz
            at the tram's 7 m/s gives a 0.35 m resolution along the track).
    """

    seed: int = 1000
    preset: str = "light"
    world: dict[str, Any] = field(default_factory=lambda: {"blocks_x": 6, "blocks_y": 5})
    route_seed: int = 0
    length_m: float = 5000.0
    spacing_m: float = 11.7
    conditions: list[str] = field(default_factory=lambda: ["summer_day", "winter"])
    size: tuple[int, int] = (240, 320)
    hfov_deg: float | None = None
    offset_m: float = 0.0
    yaw_jitter_deg: float = 0.0
    time_offset_s: float = 600.0
    fps: float = 20.0

    def __post_init__(self) -> None:
        from geoseg.synth.conditions import CONDITIONS

        if not self.conditions:
            raise ConfigError("route.conditions: expected at least one condition")
        unknown = sorted(set(self.conditions) - set(CONDITIONS))
        if unknown:
            raise ConfigError(f"route.conditions: unknown {unknown}; known {sorted(CONDITIONS)}")
        for key in ("length_m", "spacing_m", "fps"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"route.{key}: expected > 0, got {getattr(self, key)}")
        if self.spacing_m > self.length_m:
            raise ConfigError(
                f"route.spacing_m: expected <= length_m ({self.length_m}), got {self.spacing_m}"
            )
        for key in ("offset_m", "yaw_jitter_deg", "time_offset_s"):
            if getattr(self, key) < 0:
                raise ConfigError(f"route.{key}: expected >= 0, got {getattr(self, key)}")
        if len(self.size) != 2 or min(int(s) for s in self.size) < 1:
            raise ConfigError(f"route.size: expected positive (H, W), got {self.size}")
        self.size = (int(self.size[0]), int(self.size[1]))
        for key in ("seed", "preset"):
            if key in self.world:
                raise ConfigError(f"route.world.{key}: set it with route.{key}")
        self.world_config()  # validate now

    def world_config(self) -> Any:
        """The :class:`~geoseg.synth.world.WorldConfig` of the city."""
        from geoseg.synth.world import WorldConfig

        data = {**self.world, "seed": int(self.seed), "preset": self.preset}
        return from_dict(WorldConfig, data, where="route.world")

    @property
    def num_keyframes(self) -> int:
        """Keyframes per traversal: ``floor(length_m / spacing_m) + 1``."""
        return int(np.floor(self.length_m / self.spacing_m + 1e-9)) + 1

    def traversal_key(self, k: int) -> str:
        """SHA-256 of everything that determines traversal ``k``'s pixels and poses."""
        from geoseg.data.synthetic import RENDER_VERSION

        if not 0 <= k < len(self.conditions):
            raise GeosegError(f"k: expected a traversal index in [0, {len(self.conditions)})")
        payload = {
            "world": to_dict(self.world_config()),
            "route_seed": self.route_seed,
            "length_m": repr(float(self.length_m)),
            "spacing_m": repr(float(self.spacing_m)),
            "size": list(self.size),
            "hfov_deg": self.hfov_deg,
            "offset_m": repr(float(self.offset_m) * k),
            "yaw_jitter_deg": repr(float(self.yaw_jitter_deg) if k else 0.0),
            "time_offset_s": repr(float(self.time_offset_s) * k),
            "fps": repr(float(self.fps)),
            "condition": self.conditions[k],
            "k": k if self.yaw_jitter_deg and k else 0,
            "render_version": RENDER_VERSION,
        }
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def route_specs(
    seeds: Sequence[int],
    *,
    conditions: Sequence[str],
    conditions_per_route: int = 2,
    presets: Sequence[str] = ("light", "dense_occlusion"),
    draw_seed: int = 0,
    **spec_kwargs: Any,
) -> list[RouteSpec]:
    """One :class:`RouteSpec` per city, with ``conditions_per_route`` distinct conditions each.

    The conditions of city ``seeds[i]`` are drawn without replacement from ``conditions`` with
    ``numpy.random.default_rng((draw_seed, seeds[i], 5151))``; its route seed is
    ``draw_seed + i``; presets alternate over the cities.

    Args:
        seeds: city seeds.
        conditions: the pool of conditions.
        conditions_per_route: traversals per route, ``1 <= n <= len(conditions)``.
        presets: occluder presets, alternating.
        draw_seed: seeds the condition draws and the routes.
        **spec_kwargs: further :class:`RouteSpec` fields (``world``, ``length_m``...).

    Returns:
        The specs, in the order of ``seeds``.
    """
    if not seeds:
        raise ConfigError("seeds: expected at least one city")
    if not 1 <= conditions_per_route <= len(conditions):
        raise ConfigError(
            f"conditions_per_route: expected 1..{len(conditions)}, got {conditions_per_route}"
        )
    out = []
    for i, seed in enumerate(seeds):
        rng = np.random.default_rng(np.random.SeedSequence([int(draw_seed), int(seed), 5151]))
        pick = rng.choice(len(conditions), size=conditions_per_route, replace=False)
        out.append(
            RouteSpec(
                seed=int(seed),
                preset=presets[i % len(presets)],
                route_seed=int(draw_seed) + i,
                conditions=[conditions[j] for j in pick],
                **spec_kwargs,
            )
        )
    return out


# ============================================================================ poses and renders


@dataclass
class RouteTraversal:
    """One rendered traversal (``N`` keyframes).

    Attributes:
        condition: appearance condition.
        key: the cache key (:meth:`RouteSpec.traversal_key`).
        images: ``(N, H, W, 3)`` uint8 RGB.
        R_wc: ``(N, 3, 3)`` float64 camera-to-world rotations.
        t_wc: ``(N, 3)`` float64 camera centres, world frame, metres.
        timestamps: ``(N,)`` float64 world times, seconds.
        K: ``(3, 3)`` float64 intrinsics.
        from_cache: True when read from the cache rather than rendered.
    """

    condition: str
    key: str
    images: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    timestamps: np.ndarray
    K: np.ndarray
    from_cache: bool = False

    def __len__(self) -> int:
        return int(self.t_wc.shape[0])

    @property
    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``(R_wc (N, 3, 3), t_wc (N, 3))``: a traversal for :mod:`geoseg.data.pairs`."""
        return self.R_wc, self.t_wc


def _yaw(R_wc: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """Rotate ``(N, 3, 3)`` camera-to-world rotations by ``(N,)`` yaws about the world z axis."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    z, o = np.zeros_like(c), np.ones_like(c)
    R_z = np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], 1)
    return R_z @ R_wc


def keyframe_poses(world: Any, spec: RouteSpec) -> list[dict[str, np.ndarray]]:
    """Keyframe poses of every traversal of ``spec`` (no rendering).

    Args:
        world: the city of ``spec`` (``build_world(spec.world_config())``).
        spec: the route.

    Returns:
        One ``{"R_wc": (N, 3, 3), "t_wc": (N, 3), "timestamps": (N,), "K": (3, 3)}`` per
        condition, ``N = spec.num_keyframes``.
    """
    from geoseg.synth.trajectory import drive

    n = spec.num_keyframes
    n_trav = len(spec.conditions)
    extra = spec.offset_m * (n_trav - 1) + 2.0 * spec.spacing_m
    h, w = spec.size
    traj = drive(
        world,
        rig="tram",
        length_m=spec.length_m + extra,
        fps=spec.fps,
        seed=spec.route_seed,
        image_size=(w, h),
        hfov_deg=spec.hfov_deg,
    )
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(traj.t_wc, axis=0), axis=1))])
    out = []
    for k in range(n_trav):
        target = k * spec.offset_m + spec.spacing_m * np.arange(n)
        idx = np.clip(np.searchsorted(arc, target), 0, len(arc) - 1)
        prev = np.clip(idx - 1, 0, len(arc) - 1)
        idx = np.where(np.abs(arc[prev] - target) < np.abs(arc[idx] - target), prev, idx)
        R_wc = traj.R_wc[idx].copy()
        if k and spec.yaw_jitter_deg:
            rng = np.random.default_rng(np.random.SeedSequence([spec.seed, spec.route_seed, k, 77]))
            yaw = np.radians(rng.uniform(-spec.yaw_jitter_deg, spec.yaw_jitter_deg, size=n))
            R_wc = _yaw(R_wc, yaw)
        out.append(
            {
                "R_wc": R_wc,
                "t_wc": traj.t_wc[idx].copy(),
                "timestamps": traj.timestamps[idx] + k * spec.time_offset_s,
                "K": traj.K.copy(),
            }
        )
    return out


def _cache_file(cache_dir: Path | None, kind: str, key: str) -> Path | None:
    return None if cache_dir is None else Path(cache_dir) / kind / key[:2] / f"{key}.npz"


def render_route(
    spec: RouteSpec,
    *,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
) -> list[RouteTraversal]:
    """Render every traversal of ``spec`` (from the cache when present).

    Args:
        spec: the route.
        cache_dir: cache folder (``<cache_dir>/frames/<key[:2]>/<key>.npz``); None: no cache.
        progress: tqdm bars while rendering.

    Returns:
        One :class:`RouteTraversal` per condition, in the order of ``spec.conditions``.
    """
    from geoseg.data.synthetic import get_world
    from geoseg.synth.renderer import render

    cache = None if cache_dir is None else Path(cache_dir)
    n, (h, w) = spec.num_keyframes, spec.size
    out: list[RouteTraversal | None] = []
    missing = []
    for k, cond in enumerate(spec.conditions):
        key = spec.traversal_key(k)
        data = read_npz(_cache_file(cache, "frames", key), _FRAME_FIELDS)
        if data is not None and data["images"].shape != (n, h, w, 3):
            logger.warning("cache entry for %s has shape %s; rendering again", key, data["images"])
            data = None
        if data is None:
            out.append(None)
            missing.append(k)
            continue
        out.append(RouteTraversal(cond, key, from_cache=True, **data))
    if missing:
        world = get_world(spec.world_config())
        poses = keyframe_poses(world, spec)
        for k in missing:
            cond, p = spec.conditions[k], poses[k]
            images = np.empty((n, h, w, 3), dtype=np.uint8)
            t0 = time.perf_counter()
            bar = tqdm(range(n), desc=f"render {cond} (city {spec.seed})", disable=not progress)
            for i in bar:
                frame = render(
                    world,
                    p["K"],
                    p["R_wc"][i],
                    p["t_wc"][i],
                    (w, h),
                    cond,
                    time_s=float(p["timestamps"][i]),
                )
                images[i] = frame.rgb
            logger.info(
                "rendered %d %s keyframes of city %d in %.1f s (%.3f s each)",
                n,
                cond,
                spec.seed,
                time.perf_counter() - t0,
                (time.perf_counter() - t0) / n,
            )
            trav = RouteTraversal(cond, spec.traversal_key(k), images=images, **p)
            path = _cache_file(cache, "frames", trav.key)
            if path is not None:
                write_npz(path, {f: getattr(trav, f) for f in _FRAME_FIELDS})
            out[k] = trav
    return [t for t in out if t is not None]


# ============================================================================ layer-21 features


def _fingerprint(module: nn.Module, normalization: Mapping[str, Any]) -> str:
    h = hashlib.sha256()
    for name, t in sorted(module.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    h.update(json.dumps({k: list(map(float, v)) for k, v in normalization.items()}).encode())
    return h.hexdigest()


class TrunkFeatureExtractor:
    """The frozen ENet trunk (layers 1-21): RGB images -> layer-21 features.

    Args:
        model: an ``enet`` or ``joint`` network (anything with a ``trunk`` returning
            ``(features, indices1, indices2)``); put in eval mode, gradients off.
        normalization: ``{"mean": [3], "std": [3]}`` for images in [0, 1].
        device: where the trunk runs.
        batch_size: images per forward pass.

    Attributes:
        fingerprint: SHA-256 of the trunk's weights and the normalisation (cache key).
    """

    def __init__(
        self,
        model: nn.Module,
        *,
        normalization: Mapping[str, Sequence[float]] | None = None,
        device: str | torch.device = "cpu",
        batch_size: int = 16,
    ) -> None:
        from geoseg.infer import DEFAULT_NORMALIZATION

        trunk = getattr(model, "trunk", None)
        if not isinstance(trunk, nn.Module):
            raise GeosegError(
                f"model: expected an ENet/joint network with a layer-21 trunk, got "
                f"{type(model).__name__}"
            )
        if batch_size < 1:
            raise GeosegError(f"batch_size: expected >= 1, got {batch_size}")
        norm = dict(normalization or DEFAULT_NORMALIZATION)
        self.device = torch.device(device)
        self.trunk = trunk.to(self.device).eval()
        for p in self.trunk.parameters():
            p.requires_grad_(False)
        self.batch_size = int(batch_size)
        self.mean = torch.tensor(norm["mean"], dtype=torch.float32)[None, :, None, None]
        self.std = torch.tensor(norm["std"], dtype=torch.float32)[None, :, None, None]
        self.fingerprint = _fingerprint(self.trunk, norm)

    @classmethod
    def from_checkpoint(
        cls, path: str | os.PathLike, *, device: str | torch.device = "cpu", batch_size: int = 16
    ) -> TrunkFeatureExtractor:
        """Load an ``enet``/``joint`` model checkpoint (``model.pt``, :mod:`geoseg.infer`)."""
        from geoseg.infer import load_model_checkpoint

        model, ckpt = load_model_checkpoint(path)
        return cls(
            model, normalization=ckpt.get("normalization"), device=device, batch_size=batch_size
        )

    def __call__(self, images: np.ndarray) -> np.ndarray:
        """Layer-21 features of RGB images.

        Args:
            images: ``(B, H, W, 3)`` uint8 RGB.

        Returns:
            ``(B, 128, ceil(H/8), ceil(W/8))`` float32.
        """
        from geoseg.models.enet import pad_to_multiple

        images = np.asarray(images)
        if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
            raise GeosegError(
                f"images: expected (B, H, W, 3) uint8, got {images.shape} {images.dtype}"
            )
        if images.shape[0] == 0:
            raise GeosegError("images: empty batch")
        out = []
        with torch.inference_mode():
            for s in range(0, images.shape[0], self.batch_size):
                x = torch.from_numpy(images[s : s + self.batch_size]).permute(0, 3, 1, 2)
                x = (x.float() / 255.0 - self.mean) / self.std
                feats, _, _ = self.trunk(pad_to_multiple(x.to(self.device)))
                out.append(feats.float().cpu().numpy())
        return np.concatenate(out)


def traversal_features(
    traversal: RouteTraversal,
    extractor: TrunkFeatureExtractor,
    *,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
) -> np.ndarray:
    """Layer-21 features of a traversal's images, cached per (traversal, trunk weights).

    Args:
        traversal: the images.
        extractor: the frozen trunk.
        cache_dir: cache folder (``<cache_dir>/features/<key[:2]>/<key>.npz``); None: no cache.
        progress: tqdm bar while extracting.

    Returns:
        ``(N, 128, h, w)`` float16 (the cache's precision; cast to float32 before use).
    """
    key = hashlib.sha256(
        f"{traversal.key}|{extractor.fingerprint}|{FEATURE_VERSION}".encode()
    ).hexdigest()
    path = _cache_file(None if cache_dir is None else Path(cache_dir), "features", key)
    data = read_npz(path, ("features",))
    if data is not None and data["features"].shape[0] == len(traversal):
        return data["features"]
    t0 = time.perf_counter()
    chunks = []
    step = max(extractor.batch_size, 1)
    for s in tqdm(
        range(0, len(traversal), step),
        desc=f"layer-21 {traversal.condition}",
        disable=not progress,
    ):
        chunks.append(extractor(traversal.images[s : s + step]).astype(np.float16))
    feats = np.concatenate(chunks)
    logger.info(
        "layer-21 features of %d keyframes in %.1f s (%.4f s each)",
        len(traversal),
        time.perf_counter() - t0,
        (time.perf_counter() - t0) / len(traversal),
    )
    if path is not None:
        write_npz(path, {"features": feats})
    return feats


@dataclass
class RouteFeatures:
    """The traversals of one route with their features (what the heads train on).

    Attributes:
        spec: the route.
        traversals: one :class:`RouteTraversal` per condition.
        features: per traversal, ``(N, 128, h, w)`` float16 torch tensors.
        aligned: the route's traversals at its first traversal's poses, when the traversals
            beyond ``spec``'s come from it (its first traversal is ``spec``'s first).
    """

    spec: RouteSpec
    traversals: list[RouteTraversal]
    features: list[torch.Tensor]
    aligned: RouteSpec | None = None


def route_features(
    spec: RouteSpec,
    extractor: TrunkFeatureExtractor,
    *,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
    keep_images: bool = True,
) -> RouteFeatures:
    """Render (or read) a route and compute (or read) its layer-21 features.

    Args:
        spec: the route.
        extractor: the frozen trunk.
        cache_dir: shared cache folder (frames and features).
        progress: tqdm bars.
        keep_images: False drops the images after extraction (``images`` becomes an empty
            ``(0, H, W, 3)`` array) to save memory in the trainers.

    Returns:
        :class:`RouteFeatures`.
    """
    travs = render_route(spec, cache_dir=cache_dir, progress=progress)
    feats = []
    for trav in travs:
        feats.append(
            torch.from_numpy(
                traversal_features(trav, extractor, cache_dir=cache_dir, progress=progress)
            )
        )
        if not keep_images:
            trav.images = np.empty((0, *trav.images.shape[1:]), np.uint8)  # frees the frames
    return RouteFeatures(spec, travs, feats)
