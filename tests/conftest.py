"""Fixtures shared across the test tree: the tiny synthetic city most SLAM tests drive through.

``tiny_world_dict`` is its configuration as plain values (what a YAML preset holds);
``make_tiny_world`` builds a :class:`geoseg.synth.world.WorldConfig` from it with overrides
(``make_tiny_world(preset="dense_occlusion")``). A 2 x 2 block city ~140 m across with a short
terrain skirt: it builds in well under a second.
"""

from __future__ import annotations

import copy

import pytest

TINY_WORLD = {
    "seed": 5,
    "preset": "light",
    "blocks_x": 2,
    "blocks_y": 2,
    "block_size": 70.0,
    "node_jitter": 4.0,
    "removed_street_share": 0.0,
    "terrain": {"skirt": 60.0, "mesh_spacing": 6.0},
}


def tiny_world_config(**overrides):
    """The tiny city's :class:`WorldConfig`, with keys overridden."""
    from geoseg.config import from_dict
    from geoseg.synth.world import WorldConfig

    return from_dict(WorldConfig, {**copy.deepcopy(TINY_WORLD), **overrides})


@pytest.fixture(scope="session")
def tiny_world_dict() -> dict:
    """The tiny city's configuration as plain values (a fresh copy)."""
    return copy.deepcopy(TINY_WORLD)


@pytest.fixture(scope="session")
def make_tiny_world():
    """The :func:`tiny_world_config` factory (test modules cannot import conftest by name)."""
    return tiny_world_config
