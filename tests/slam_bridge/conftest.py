"""Shared fixtures for slam_bridge tests: a small synthetic street scene.

``street`` (noisy, 1 px) and ``street_noiseless`` are :class:`slam_bridge.scenes.StreetScene`
objects: 8 cameras 1 m apart along a street, facade + ground points each seen by 3-8
consecutive cameras. ``make_street`` is the builder, for other sizes. ``ba_problem`` turns a scene
into ``(state, factor)`` with the first two cameras fixed (gauge, including scale) and a perturbed
start.
"""

from __future__ import annotations

import numpy as np
import pytest

from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.problem import BAState
from slam_bridge.scenes import StreetScene, perturb, street_scene


@pytest.fixture
def make_street():
    """The :func:`slam_bridge.scenes.street_scene` builder."""
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
