"""A tiny chapter-3 drive for the SLAM-loop tests: ``tiny_experiment`` builds its config;
``noiseless`` and ``noisy`` are ``(config, sequence)`` pairs (40 m without noise or outliers;
60 m with 1 px noise and 3 % gross outliers)."""

from __future__ import annotations

import pytest

from geoseg.synth.world import TerrainConfig, WorldConfig
from slam_bridge.experiments.fusion_ch3 import ExperimentConfig, SequenceConfig, make_sequence
from slam_bridge.experiments.landmarks import LandmarkConfig
from slam_bridge.slam.config import SlamConfig
from slam_bridge.slam.fusion import FusionConfig
from slam_bridge.slam.windows import WindowConfig

TINY_WORLD = dict(
    seed=5,
    preset="light",
    blocks_x=2,
    blocks_y=2,
    block_size=70.0,
    node_jitter=4.0,
    removed_street_share=0.0,
    terrain=TerrainConfig(skirt=60.0, mesh_spacing=6.0),
)


def small_slam() -> SlamConfig:
    """``l = 8``, ``n = 4``: hybrid windows on a drive of a few tens of keyframes."""
    return SlamConfig(
        window=WindowConfig(l=8, n=4, ba_iterations=8), fusion=FusionConfig(iterations=8)
    )


def tiny_experiment(noise_px: float = 1.0, outliers: float = 0.03, length_m: float = 40.0):
    return ExperimentConfig(
        world=WorldConfig(**TINY_WORLD),
        sequence=SequenceConfig(length_m=length_m, fps=10.0, seed=1, image_size=(640, 480)),
        landmarks=LandmarkConfig(noise_px=noise_px, outlier_share=outliers),
        slam=small_slam(),
    )


@pytest.fixture(scope="session")
def noiseless():
    cfg = tiny_experiment(noise_px=0.0, outliers=0.0)
    return cfg, make_sequence(cfg)


@pytest.fixture(scope="session")
def noisy():
    cfg = tiny_experiment(length_m=60.0)
    return cfg, make_sequence(cfg)
