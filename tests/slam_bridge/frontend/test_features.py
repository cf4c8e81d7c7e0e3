"""Stateless helpers of the front end (:mod:`slam_bridge.frontend.features`)."""

from __future__ import annotations

import numpy as np

from slam_bridge.frontend import features as ft


def test_local_flow_check_leaves_isolated_tracks_alone():
    """A cluster of tracks moving 10 px right, one of them stuck; far away, one track moving
    otherwise (another surface): the stuck one fails, the isolated one is not judged by the
    cluster once its neighbours lie beyond the radius."""
    rng = np.random.default_rng(0)
    cluster = rng.uniform(100, 140, size=(12, 2))
    uv0 = np.vstack([cluster, [[500.0, 400.0]]]).astype(np.float32)
    uv1 = uv0 + np.float32([10.0, 0.0])
    uv1[0] = uv0[0]  # stuck
    uv1[-1] = uv0[-1] + np.float32([-20.0, 5.0])  # isolated, another motion
    nb = ft.neighbours(uv1, 8)
    strict = ft.flow_consistent(uv0, uv1, nb, 3.0, 0.3)
    assert not strict[0] and strict[1:-1].all() and not strict[-1]
    loose = ft.flow_consistent(uv0, uv1, nb, 3.0, 0.3, radius=60.0)
    assert not loose[0] and loose[1:].all()
