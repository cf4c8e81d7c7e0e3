"""Landmarks of the chapter-3 experiment: sampling, honest visibility, measurement model."""

from __future__ import annotations

import numpy as np
import pytest

from geoseg.synth import build_world, drive
from geoseg.synth.world import TerrainConfig, WorldConfig
from slam_bridge.errors import SlamError
from slam_bridge.experiments.fusion_ch3 import SequenceConfig  # noqa: F401  (import check of the stage module)
from slam_bridge.experiments.landmarks import (
    LandmarkConfig,
    Landmarks,
    SceneCaster,
    sample_landmarks,
    simulate_observations,
    visible_observations,
)


def _tiny_world():
    return build_world(
        WorldConfig(
            seed=5,
            preset="light",
            blocks_x=2,
            blocks_y=2,
            block_size=70.0,
            node_jitter=4.0,
            removed_street_share=0.0,
            terrain=TerrainConfig(skirt=60.0, mesh_spacing=6.0),
        )
    )


@pytest.fixture(scope="module")
def tiny():
    world = _tiny_world()
    traj = drive(world, rig="car", length_m=40.0, fps=5.0, seed=1, image_size=(320, 240))
    return world, traj


def _wall_caster() -> SceneCaster:
    """A 10 m x 5 m wall in the plane x = 10 (two triangles)."""
    v = np.array([[10.0, -5.0, -2.0], [10.0, 5.0, -2.0], [10.0, 5.0, 3.0], [10.0, -5.0, 3.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return SceneCaster(v, f)


def _camera_looking_x() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # camera z (forward) = world x, camera x (right) = world -y, camera y (down) = world -z
    R_wc = np.stack([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], axis=1)[None]
    t_wc = np.zeros((1, 3))
    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    return K, R_wc, t_wc


def test_point_behind_wall_hidden_point_in_front_visible():
    caster = _wall_caster()
    K, R_wc, t_wc = _camera_looking_x()
    X = np.array([[5.0, 0.5, 0.2], [15.0, -0.5, 0.1], [9.98, 1.0, 0.5], [10.2, 1.0, 0.5]])
    n = np.tile([-1.0, 0.0, 0.0], (4, 1))
    lm = Landmarks(X_w=X, kind=np.ones(4, np.uint8), normal_w=n)
    kf, pt, uv = visible_observations(caster, lm, K, R_wc, t_wc, (320, 240), LandmarkConfig())
    # in front (5 m) and on the wall's near face are visible; behind it (15 m, 0.2 m behind) are not
    assert pt.tolist() == [0, 2]
    assert np.all(kf == 0)
    assert np.all((uv >= 0) & (uv <= [319, 239]))


def test_first_hit_distance():
    caster = _wall_caster()
    s = caster.first_hit(np.zeros((2, 3)), np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    assert s[0] == pytest.approx(10.0, abs=1e-4)
    assert np.isinf(s[1])


def test_sample_and_see_tiny_world(tiny):
    world, traj = tiny
    cfg = LandmarkConfig()
    lm = sample_landmarks(world, traj.t_wc[:, :2], cfg, seed=0)
    assert len(lm) > 100 and np.all(np.isfinite(lm.X_w))
    assert {0, 1} <= set(np.unique(lm.kind).tolist())  # ground and facades
    caster = SceneCaster.from_world(world)
    kf, pt, uv = visible_observations(
        caster, lm, traj.K, traj.R_wc, traj.t_wc, traj.image_size, cfg
    )
    assert np.bincount(kf, minlength=len(traj)).min() > 20  # every frame sees points
    # every observation is in front, within range, inside the image; sorted by keyframe
    R, t = traj.R_wc[kf], traj.t_wc[kf]
    z = np.einsum("mji,mj->mi", R, lm.X_w[pt] - t)[:, 2]
    assert np.all((z >= cfg.min_depth_m) & (z <= cfg.max_depth_m))
    assert np.all(np.diff(kf) >= 0)
    # honesty: the segment from the camera to each visible point crosses no surface
    d = lm.X_w[pt] - t
    dist = np.linalg.norm(d, axis=1)
    s = caster.first_hit(t, d / dist[:, None])
    assert np.all(s >= dist - cfg.tol_m)


def test_measurement_model():
    rng = np.random.default_rng(0)
    M = 20000
    uv_true = rng.random((M, 2)) * [319, 239]
    cfg = LandmarkConfig(noise_px=1.0, outlier_share=0.05)
    obs = simulate_observations(np.zeros(M, int), np.arange(M), uv_true, (320, 240), cfg, seed=3)
    assert obs.is_outlier.mean() == pytest.approx(0.05, abs=0.01)
    e = (obs.uv - uv_true)[~obs.is_outlier]
    assert e.std() == pytest.approx(1.0, rel=0.05)
    out = obs.uv[obs.is_outlier]
    assert np.all((out >= 0) & (out <= [319, 239]))  # gross mismatches fall in the image


def test_bad_config():
    with pytest.raises(SlamError):
        LandmarkConfig(outlier_share=1.5)
    with pytest.raises(SlamError):
        LandmarkConfig(min_depth_m=10.0, max_depth_m=5.0)
