"""Tiny synthetic worlds shared by the synth tests (each builds in well under a second)."""

from __future__ import annotations

import pytest

from geoseg.synth.world import TerrainConfig, World, WorldConfig, build_world


def tiny_config(seed: int = 3, preset: str = "dense_occlusion", **overrides) -> WorldConfig:
    """A 2 x 2 block city, ~140 m across, with a short terrain skirt."""
    values = dict(
        seed=seed,
        preset=preset,
        blocks_x=2,
        blocks_y=2,
        block_size=70.0,
        node_jitter=4.0,
        curved_street_share=0.5,
        removed_street_share=0.0,
        terrain=TerrainConfig(skirt=60.0, mesh_spacing=6.0),
    )
    values.update(overrides)
    return WorldConfig(**values)


@pytest.fixture(scope="session")
def tiny_world() -> World:
    return build_world(tiny_config())


@pytest.fixture(scope="session")
def tiny_light_world() -> World:
    return build_world(tiny_config(seed=5, preset="light"))


@pytest.fixture(scope="session")
def make_tiny_config():
    """The :func:`tiny_config` factory (test modules cannot import conftest by name)."""
    return tiny_config


@pytest.fixture(scope="session")
def first_frame(tiny_world):
    """``first_frame(shows)``: the first frame of a short car drive through the tiny world
    whose labels satisfy ``shows(labels)``, as ``(renderer, (K, R_wc, t_wc, size), time_s,
    frame)``."""
    from geoseg.synth.renderer import Renderer
    from geoseg.synth.trajectory import drive

    renderer = Renderer(tiny_world)
    traj = drive(tiny_world, rig="car", length_m=120.0, fps=2.0, seed=3, image_size=(160, 120))

    def find(shows):
        for i in range(len(traj)):
            pose = (traj.K, traj.R_wc[i], traj.t_wc[i], traj.image_size)
            frame = renderer.render(*pose, time_s=float(traj.timestamps[i]))
            if shows(frame.labels):
                return renderer, pose, float(traj.timestamps[i]), frame
        raise AssertionError("no frame of the drive shows what the test needs")

    return find
