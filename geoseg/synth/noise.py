"""Stateless randomness of the synthetic world's appearance: integer hashes, value noise and
random colours, all pure functions of integer keys (cell coordinates, row or instance ids).

The procedural textures (:mod:`geoseg.synth.textures`) and the per-frame appearance variations
the renderer applies (:mod:`geoseg.synth.realism`, :mod:`geoseg.synth.renderer`) draw from the
same helpers, so they live here, below both: the same keys give the same values from any
viewpoint and in any process.
"""

from __future__ import annotations

import numpy as np

_M1 = np.uint32(0xCC9E2D51)
_M2 = np.uint32(0x1B873593)
_M3 = np.uint32(0x85EBCA6B)
_M4 = np.uint32(0xC2B2AE35)


def hash_u32(*keys: np.ndarray, seed: int = 0) -> np.ndarray:
    """Integer hash of integer-valued arrays (broadcast together) -> uint32 array."""
    h = np.uint32((seed * 0x9E3779B1 + 0x7F4A7C15) & 0xFFFFFFFF)
    for key in keys:
        k = np.asarray(key)
        k = k.astype(np.int32) if k.dtype != np.int32 else k
        h = (h ^ k.view(np.uint32)) * _M1
        h ^= h >> np.uint32(15)
    h *= _M3
    h ^= h >> np.uint32(13)
    h *= _M4
    h ^= h >> np.uint32(16)
    return h


def hash01(*keys: np.ndarray, seed: int = 0) -> np.ndarray:
    """Uniform float32 in [0, 1) from integer keys."""
    return (hash_u32(*keys, seed=seed) >> np.uint32(8)).astype(np.float32) * np.float32(2.0**-24)


def value_noise(x: np.ndarray, y: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth 2D value noise in [0, 1), unit cell size: `(N,)` float32."""
    ix = np.floor(x)
    iy = np.floor(y)
    fx = (x - ix).astype(np.float32)
    fy = (y - iy).astype(np.float32)
    fx = fx * fx * (3 - 2 * fx)
    fy = fy * fy * (3 - 2 * fy)
    ix = ix.astype(np.int64)
    iy = iy.astype(np.int64)
    a = hash01(ix, iy, seed=seed)
    b = hash01(ix + 1, iy, seed=seed)
    c = hash01(ix, iy + 1, seed=seed)
    d = hash01(ix + 1, iy + 1, seed=seed)
    return (a + (b - a) * fx) * (1 - fy) + (c + (d - c) * fx) * fy


def random_colours(key: np.ndarray, seed: int, saturated_share: float) -> np.ndarray:
    """`(N, 3)` float32 colours from integer keys: neutral (white..black) or, for a share
    ``saturated_share``, a random hue of medium saturation."""
    hue = hash01(key, seed=seed * 7 + 1)
    sat_pick = hash01(key, seed=seed * 7 + 2)
    val = hash01(key, seed=seed * 7 + 3)
    saturated = sat_pick < saturated_share
    sat = np.where(saturated, 0.35 + 0.5 * hash01(key, seed=seed * 7 + 4), 0.04 * sat_pick)
    val = np.where(saturated, 0.3 + 0.65 * val, 0.06 + 0.88 * val)
    return hsv_to_rgb(hue, sat, val)


def hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorised HSV (each in [0, 1]) to `(N, 3)` float32 RGB."""
    h6 = (np.asarray(h, np.float32) % 1.0) * 6.0
    s = np.asarray(s, np.float32)
    v = np.asarray(v, np.float32)
    k = np.stack([(5.0 + h6) % 6.0, (3.0 + h6) % 6.0, (1.0 + h6) % 6.0], axis=1)
    f = np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return (v[:, None] * (1.0 - s[:, None] * f)).astype(np.float32)
