"""Building constraints in the fusion: the provider's rows, and the loop pulling the facade
points of a tiny chapter-3 drive onto the exact building model (oracle association)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from geoseg.synth import build_world
from geoseg.synth.world import SurfaceKind
from slam_bridge.bridge.association import Association, nearest_facades
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError
from slam_bridge.experiments.landmarks import sample_landmarks
from slam_bridge.slam.loop import KnownStartPoses, run_slam


def _two_facades() -> Facades:
    return Facades(
        p0=np.array([[0.0, 0.0], [10.0, 0.0]]),
        p1=np.array([[10.0, 0.0], [10.0, 10.0]]),
        z_min=np.zeros(2),
        z_max=np.full(2, 10.0),
        normal=np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0]]),
        d=np.array([0.0, 10.0]),
        true_facade_id=np.array([-1, -1]),
    )


def test_rows_of_the_window_points():
    a = Association(np.array([1, -1, 0, 1]), np.array([0.5, 0.0, 2.0, 0.0]), "bayes")
    c = BuildingConstraints(_two_facades(), sigma_m=0.3, weight=2.0, association=a)
    # state points are map points 3, 2, 0 and 7 (7: newer than the association)
    problem = SimpleNamespace(point_ids=np.array([3, 2, 0, 7]))
    (f,) = c.factors(None, problem, 0)
    np.testing.assert_array_equal(f.points, [1, 2])  # map points 2 and 0; 3 has weight 0
    np.testing.assert_allclose(f.normals_w, [[0, -1, 0], [1, 0, 0]])
    np.testing.assert_allclose(f.offsets, [0.0, 10.0])
    np.testing.assert_allclose(f.weights, [4.0, 1.0])
    assert c.factors(None, SimpleNamespace(point_ids=np.array([1, 3])), 0) == []
    assert BuildingConstraints(_two_facades()).factors(None, problem, 0) == []  # none yet
    capped = BuildingConstraints(_two_facades(), weight=2.0, window_weight=2.5, association=a)
    (f,) = capped.factors(None, problem, 0)
    np.testing.assert_allclose(f.weights, [2.0, 0.5])  # 4 : 1, summing to 2.5
    loose = BuildingConstraints(_two_facades(), weight=2.0, window_weight=50.0, association=a)
    np.testing.assert_allclose(loose.factors(None, problem, 0)[0].weights, [4.0, 1.0])


@pytest.mark.parametrize(
    "facade, weight, message",
    [
        ([0, 2], [1.0, 1.0], "facade ids"),
        ([0, -2], [1.0, 1.0], "facade ids"),
        ([0, 1], [1.0, -1.0], "weights"),
        ([0, 1], [1.0, np.nan], "weights"),
        ([0, 1], [1.0], "differ"),
    ],
)
def test_bad_associations(facade, weight, message):
    c = BuildingConstraints(_two_facades())
    with pytest.raises(SlamError, match=message):
        c.update(Association(np.array(facade), np.array(weight), "bayes"))


def test_facade_points_pulled_onto_the_model(noisy):
    """``n = 0`` with known start poses, vision only against vision + exact facades: the
    associated points end nearer their planes and the keyframes nearer the truth (measured:
    0.64 -> 0.17 m from the planes, 0.147 -> 0.030 m mean keyframe error)."""
    cfg, seq = noisy
    world = build_world(cfg.world)
    lm = sample_landmarks(world, seq.trajectory.t_wc[:, :2], cfg.landmarks, seed=cfg.seed)
    assert len(lm) == seq.num_points  # the landmarks of the sequence
    table = world.facades()
    facades = Facades(
        p0=table.p0,
        p1=table.p1,
        z_min=table.z_min,
        z_max=table.z_max,
        normal=table.normal,
        d=np.einsum("fi,fi->f", table.normal[:, :2], table.p0),
        true_facade_id=table.facade_id,
    )
    facade, _ = nearest_facades(facades, lm.X_w, radius_m=0.2)
    facade[lm.kind != SurfaceKind.FACADE] = -1
    oracle = Association(facade, (facade >= 0).astype(float), "oracle")
    assert oracle.associated.sum() > 100

    def run(providers):
        start = KnownStartPoses(
            seq.R_wc_true, seq.t_wc_true, cfg.slam.tracking.outlier_gate_px,
            cfg.start_keyframes, cfg.slam.mapping,
        )  # fmt: skip
        return run_slam(seq.source(), "ba", start, providers, cfg.slam)

    def plane_distance(res):
        m = res.map
        q = np.flatnonzero(oracle.associated[: m.num_points] & m.triangulated)
        f = oracle.facade[q]
        return np.abs(np.einsum("qi,qi->q", m.X_w[q], facades.normal[f]) - facades.d[f]).mean()

    def keyframe_error(res):
        return np.linalg.norm(res.map.t_wc - seq.t_wc_true, axis=1).mean()

    vision = run([])
    fused = run([BuildingConstraints(facades, association=oracle)])
    assert any("building" in r.constraints for r in fused.records)
    assert plane_distance(fused) < 0.5 * plane_distance(vision)
    assert keyframe_error(fused) < 0.5 * keyframe_error(vision)
    assert all(r.zeta < 1.05 * r.zeta_star + 1e-9 for r in fused.records if r.zeta_star > 0)
