"""Pose-graph links: frozen references and entry information weights."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slam_bridge.factors.pose_graph_dpc import dpc_whitener
from slam_bridge.geometry.lie import so3_exp
from slam_bridge.slam.hybrid_problem import HybridWindowConfig, build_hybrid_problem
from slam_bridge.slam.links import LinkMemory
from slam_bridge.testing.scenes import street_scene


@pytest.mark.parametrize("kind", ["dpc", "mpc"])
def test_pose_graph_references_are_frozen_at_entry(kind):
    """A link's reference (DPC's S_hat, MPC's epipolar offsets) is the relative pose it had when
    it entered the pose graph, so after a bend of the chain the pose-graph terms still vanish at
    the entry poses, not at the bent ones; a link's entry information replaces the constant D."""
    sc = street_scene(12, points_per_camera=15, noise_px=1.0, seed=2)
    D = np.full(6, 1e4)
    wcfg = HybridWindowConfig(l=8, n=3, pose_graph=kind, D=D, mpc_relative=True)

    def build(R_wc, t_wc):
        return build_hybrid_problem(
            R_wc, t_wc, sc.X_w, sc.K, np.arange(12), sc.obs_cameras, sc.obs_points, sc.uv, wcfg
        )

    links = LinkMemory(D, 1.0, (1e-6, 1e-5))
    entry = build(sc.R_wc, sc.t_wc)
    info = np.diag(np.arange(1.0, 7.0)) * 1e3
    if kind == "dpc":
        links.information[(5, 6)] = info
    links.freeze(entry)
    assert sorted(links.relative) == [(3, 4), (4, 5), (5, 6), (6, 7)]
    # bend the chain (keyframes 5, 6) as a fusion would
    R_b, t_b = sc.R_wc.copy(), sc.t_wc.copy()
    R_b[5:7] = so3_exp(np.array([0.0, 0.01, 0.0]))[None] @ R_b[5:7]
    t_b[5:7] += np.array([0.05, -0.03, 0.02])
    bent = build(R_b, t_b)
    fam = [f for f in bent.vision if f.name.startswith("pose_graph")]
    assert fam and all(f.cost(bent.state) < 1e-12 for f in fam)  # re-taken: at rest when bent
    links.freeze(bent)
    fam = [f for f in bent.vision if f.name.startswith("pose_graph")]
    at_entry = dataclasses.replace(bent.state, R_wc=entry.state.R_wc, t_wc=entry.state.t_wc)
    assert all(f.cost(at_entry) < 1e-9 for f in fam)
    assert sum(f.cost(bent.state) for f in fam) > 1.0
    if kind == "dpc":
        (dpc,) = fam
        pairs = [tuple(p) for p in bent.camera_ids[dpc.pairs].tolist()]
        k = pairs.index((5, 6))
        np.testing.assert_allclose(dpc.whitener[k], dpc_whitener(info))
        np.testing.assert_allclose(dpc.whitener[k - 1], dpc_whitener(D))
    else:  # the baseline lengths come from the frozen references too
        links.add_length_terms(bent, 5e-3)
        length = bent.vision[-1]
        assert length.name == "baseline_length"
        assert length.cost(at_entry) < 1e-12 < length.cost(bent.state)
    links.forget_from(5)
    assert sorted(links.relative) == [(3, 4)] and (5, 6) not in links.information


def test_entry_information_is_the_windows_marginal_on_the_next_link():
    """The link the pose graph gains next, ``(z_{n+1}, z_{n+2})``, is weighed by the inverse of
    its relative pose's marginal covariance in the window (times the scale): SPD, linear in the
    scale, and stiffer when the window's points are measured more precisely."""
    sc = street_scene(12, points_per_camera=15, noise_px=1.0, seed=2)

    def entry(sigma: float, scale: float):
        wcfg = HybridWindowConfig(l=8, n=3, D=np.full(6, 1e4), reprojection_sigma=sigma)
        prob = build_hybrid_problem(
            sc.R_wc, sc.t_wc, sc.X_w, sc.K, np.arange(12), sc.obs_cameras, sc.obs_points,
            sc.uv, wcfg,
        )  # fmt: skip
        links = LinkMemory(np.full(6, 1e4), scale, (1e-6, 1e-5))
        links.remember_entry_information(prob)
        (item,) = links.information.items()
        return item

    key, D1 = entry(1.0, 1.0)
    assert key == (7, 8)  # z_{n+1}, z_{n+2} of the window 4..11 with n = 3
    np.testing.assert_allclose(D1, D1.T, rtol=1e-9)
    assert np.linalg.eigvalsh(D1).min() > 0
    np.testing.assert_allclose(entry(1.0, 10.0)[1], 10.0 * D1, rtol=1e-9)
    # halving the pixel sigma quadruples the reprojection information; the DPC prior of the
    # chain is unchanged, so the link's information grows, by at most x4
    D_half = entry(0.5, 1.0)[1]
    ratio = np.trace(D_half) / np.trace(D1)
    assert 1.5 < ratio <= 4.0 + 1e-6
