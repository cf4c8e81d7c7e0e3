"""Shared fixtures for slam_bridge tests: a small synthetic street scene.

``street`` (noisy, 1 px) and ``street_noiseless`` are :class:`slam_bridge.testing.scenes.StreetScene`
objects: 8 cameras 1 m apart along a street, facade + ground points each seen by 3-8
consecutive cameras. ``make_street`` is the builder, for other sizes. ``ba_problem`` turns a scene
into ``(state, factor)`` with the first two cameras fixed (gauge, including scale) and a perturbed
start.

A tiny chapter-3 drive for the SLAM-loop and bridge tests: ``tiny_experiment`` builds its config;
``noiseless`` and ``noisy`` are ``(config, sequence)`` pairs (40 m without noise or outliers;
60 m with 1 px noise and 3 % gross outliers).
"""

from __future__ import annotations

import numpy as np
import pytest

from slam_bridge.ba.state import BAState
from slam_bridge.experiments.fusion_ch3 import ExperimentConfig, SequenceConfig, make_sequence
from slam_bridge.experiments.landmarks import LandmarkConfig
from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.slam.config import SlamConfig
from slam_bridge.slam.fusion import FusionConfig
from slam_bridge.slam.windows import WindowConfig
from slam_bridge.testing.scenes import StreetScene, perturb, street_scene


@pytest.fixture
def make_street():
    """The :func:`slam_bridge.testing.scenes.street_scene` builder."""
    return street_scene


@pytest.fixture(scope="session")
def street() -> StreetScene:
    """8 cameras, 20 points per camera, 1 px noise."""
    return street_scene(8, points_per_camera=20, noise_px=1.0, seed=0)


@pytest.fixture(scope="session")
def street_noiseless() -> StreetScene:
    """Same geometry, noise-free observations."""
    return street_scene(8, points_per_camera=20, noise_px=0.0, seed=0)


def make_ba_problem(
    scene: StreetScene, n_fixed: int = 2, perturbed: bool = True, seed: int = 1, **kw
) -> tuple[BAState, ReprojectionFactor]:
    """``(state, reprojection factor)`` of a scene; the first ``n_fixed`` cameras fixed."""
    if perturbed:
        R, t, X = perturb(scene.R_wc, scene.t_wc, scene.X_w, seed=seed)
        R[:n_fixed], t[:n_fixed] = scene.R_wc[:n_fixed], scene.t_wc[:n_fixed]
    else:
        R, t, X = scene.R_wc.copy(), scene.t_wc.copy(), scene.X_w.copy()
    fixed = np.zeros(scene.R_wc.shape[0], dtype=bool)
    fixed[:n_fixed] = True
    state = BAState(R, t, X, camera_fixed=fixed)
    factor = ReprojectionFactor(scene.K, scene.obs_cameras, scene.obs_points, scene.uv, **kw)
    return state, factor


@pytest.fixture
def ba_problem():
    """The :func:`make_ba_problem` helper."""
    return make_ba_problem


def small_slam() -> SlamConfig:
    """``l = 8``, ``n = 4``: hybrid windows on a drive of a few tens of keyframes."""
    return SlamConfig(
        window=WindowConfig(l=8, n=4, ba_iterations=8), fusion=FusionConfig(iterations=8)
    )


def tiny_experiment(world, noise_px: float = 1.0, outliers: float = 0.03, length_m: float = 40.0):
    return ExperimentConfig(
        world=world,
        sequence=SequenceConfig(length_m=length_m, fps=10.0, seed=1, image_size=(640, 480)),
        landmarks=LandmarkConfig(noise_px=noise_px, outlier_share=outliers),
        slam=small_slam(),
    )


@pytest.fixture(scope="session")
def noiseless(make_tiny_world):
    cfg = tiny_experiment(make_tiny_world(), noise_px=0.0, outliers=0.0)
    return cfg, make_sequence(cfg)


@pytest.fixture(scope="session")
def noisy(make_tiny_world):
    cfg = tiny_experiment(make_tiny_world(), length_m=60.0)
    return cfg, make_sequence(cfg)
