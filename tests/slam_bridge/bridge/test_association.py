"""Facade tables and the three association methods on a one-building scene.

The building is the box ``[10, 20] x [-5, 5] x [0, 10]`` m; the camera stands at
``(0, 0, 1.5)``. Points: ``A`` on the west facade, ``B`` a tree 1.5 m in front of it, ``C`` a
building point 0.5 m south of the south-west corner whose network normal faces west, ``D`` far
from every facade, ``E`` not triangulated.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from geoseg.dirichlet import DirichletFilter
from geoseg.errors import GeosegError
from geoseg.synth.buildings import FacadePlanes
from slam_bridge.bridge.association import (
    associate_bayes,
    associate_dirichlet,
    associate_raycast,
    nearest_facades,
    plane_posterior,
)
from slam_bridge.bridge.facades import Facades
from slam_bridge.errors import SlamError

BUILDING, VEGETATION = 0, 1
SOUTH, EAST, NORTH, WEST = range(4)
POINTS = np.array(
    [
        [10.0, 1.0, 3.0],  # A
        [8.5, -1.0, 3.0],  # B
        [10.5, -5.5, 3.0],  # C
        [50.0, 50.0, 3.0],  # D
        [np.nan, np.nan, np.nan],  # E
    ]
)
CAMERA = np.array([0.0, 0.0, 1.5])


def _planes() -> FacadePlanes:
    corners = np.array([[10.0, -5.0], [20.0, -5.0], [20.0, 5.0], [10.0, 5.0]])
    p0, p1 = corners, np.roll(corners, -1, axis=0)
    edge = p1 - p0
    normal = np.column_stack([edge[:, 1], -edge[:, 0], np.zeros(4)]) / 10.0  # outward
    return FacadePlanes(
        plane_id=np.arange(4),
        building_id=np.zeros(4, np.int64),
        edge_index=np.arange(4),
        p0=p0,
        p1=p1,
        z_min=np.zeros(4),
        z_max=np.full(4, 10.0),
        normal=normal,
        d=np.einsum("fi,fi->f", normal[:, :2], p0),
        true_facade_id=np.arange(4),
    )


@pytest.fixture
def facades(tmp_path) -> Facades:
    return Facades.read_csv(_planes().write_csv(tmp_path / "facades.csv"))


def test_read_and_distances(facades):
    np.testing.assert_allclose(facades.normal[WEST], [-1, 0, 0])
    np.testing.assert_array_equal(facades.true_facade_id, np.arange(4))
    D = facades.distances(np.array([[10.0, 1.0, 3.0], [10.5, -5.5, 3.0], [15.0, -8.0, 14.0]]))
    np.testing.assert_allclose(D[0], [6.0, 10.0, 4.0, 0.0])
    np.testing.assert_allclose(D[1, [SOUTH, WEST]], [0.5, np.sqrt(0.5)])
    np.testing.assert_allclose(D[2, SOUTH], 5.0)  # 3 m off the wall, 4 m above its top


@pytest.mark.parametrize(
    "column, value, message",
    [
        ("nx", "0.9", "length"),
        ("d", "nan", "finite"),
        ("d", "3.0", "off its plane"),
        ("z_max", "-1", "z_max"),
        ("y0", "abc", "not a number"),
    ],
)
def test_bad_tables(tmp_path, column, value, message):
    path = _planes().write_csv(tmp_path / "facades.csv")
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    row = lines[4].split(",")  # the west facade
    row[header.index(column)] = value
    lines[4] = ",".join(row)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(GeosegError, match=message):
        Facades.read_csv(path)


def test_missing_columns_and_file(tmp_path):
    path = tmp_path / "facades.csv"
    path.write_text("x0,y0,x1,y1\n0,0,1,1\n")
    with pytest.raises(SlamError, match="z_min"):
        Facades.read_csv(path)
    with pytest.raises(SlamError, match="no such file"):
        Facades.read_csv(tmp_path / "none.csv")


def test_eq_4_14_by_hand():
    """N = +x; candidates facing +x (s = 1), 60 degrees off (s = 0.5), away (s = -1) at 1, 0.5,
    0.2 m: Beta(s; 10, 1) = 10 s^9 gives 10, 0.01953, 0; softmax(-d) ~ e^-1, e^-0.5, e^-0.2."""
    normals = np.array([[1.0, 0, 0], [0.5, np.sqrt(0.75), 0], [-1.0, 0, 0]])
    post = plane_posterior(np.array([1.0, 0, 0]), normals, np.array([1.0, 0.5, 0.2]))
    a, b = 10 * np.exp(-1.0), 10 * 0.5**9 * np.exp(-0.5)  # 3.67879, 0.01185
    np.testing.assert_allclose(post, [a / (a + b), b / (a + b), 0.0], rtol=1e-9)
    np.testing.assert_allclose(post[:2], [0.996790, 0.003210], atol=1e-6)


def test_eq_4_14_cut_below_zero():
    """The Beta(10, 1) prior is cut at s < 0: a facade facing away never wins, however near."""
    normals = np.array([[0.0, 1.0, 0], [-0.001, -1.0, 0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    post = plane_posterior(np.array([1.0, 0, 0]), normals, np.array([5.0, 0.0]))
    assert post[1] == 0.0 and post[0] == 0.0  # s = 0 and s < 0: both zero, nothing sums to 1
    post = plane_posterior(np.array([0.0, 1.0, 0]), normals, np.array([5.0, 0.0]))
    np.testing.assert_allclose(post, [1.0, 0.0])


def test_nearest_facades(facades):
    facade, dist = nearest_facades(facades, POINTS, radius_m=3.0)
    np.testing.assert_array_equal(facade, [WEST, WEST, SOUTH, -1, -1])
    np.testing.assert_allclose(dist[:3], [0.0, 1.5, 0.5])
    assert np.isinf(dist[3:]).all()


def test_raycast_associates_the_tree(facades):
    """The baseline: the ray through the tree hits the building behind it."""
    mesh = trimesh.creation.box(extents=(10, 10, 10))
    mesh.apply_translation([15, 0, 5])
    a = associate_raycast(facades, mesh, POINTS, np.tile(CAMERA, (5, 1)))
    np.testing.assert_array_equal(a.facade, [WEST, WEST, -1, -1, -1])  # C: its ray misses
    np.testing.assert_array_equal(a.weight, [1, 1, 0, 0, 0])


def _dirichlet() -> DirichletFilter:
    rng = np.random.default_rng(0)
    f = DirichletFilter(num_classes=3, building_class=BUILDING, alpha=[20.0, 1.0, 1.0])
    f.threshold_for_false_rejection(rng.dirichlet([20.0, 1.0, 1.0], size=2000), 0.05)
    return f


def test_dirichlet_drops_the_tree(facades):
    probs = np.array(
        [[0.9, 0.05, 0.05], [0.1, 0.8, 0.1], [0.92, 0.04, 0.04], [0.9, 0.05, 0.05], [np.nan] * 3]
    )
    f = _dirichlet()
    a = associate_dirichlet(facades, POINTS, probs, f)
    np.testing.assert_array_equal(a.facade, [WEST, -1, SOUTH, -1, -1])  # C: the nearest
    expected = f.classify_points(probs[[0, 2]][:, None, :]).weight
    np.testing.assert_allclose(a.weight[[0, 2]], expected)
    assert np.all(a.weight[[1, 3, 4]] == 0)


def test_bayes_uses_labels_and_normals(facades):
    labels = np.array([BUILDING, VEGETATION, BUILDING, BUILDING, BUILDING])
    normals = np.tile([-1.0, 0.0, 0.0], (5, 1))  # all face west
    a = associate_bayes(facades, POINTS, labels, normals, BUILDING)
    # the tree is not a building point; C goes to the west facade its normal faces, although
    # the south facade is nearer
    np.testing.assert_array_equal(a.facade, [WEST, -1, WEST, -1, -1])
    assert a.weight[0] == pytest.approx(1.0) and a.weight[2] == pytest.approx(1.0)
    normals[0] = np.nan  # no normal evidence: no association
    assert associate_bayes(facades, POINTS, labels, normals, BUILDING).facade[0] == -1
    with pytest.raises(SlamError, match="unit"):
        associate_bayes(facades, POINTS, labels, 2 * np.tile([-1.0, 0, 0], (5, 1)), BUILDING)


def test_near_pairs_equal_the_full_table(tmp_path):
    """The k-d tree's candidate pairs are exactly the (point, facade) pairs of the full distance
    table within the radius, on a GIS model of a rendered city and random points."""
    from geoseg.synth import build_world
    from geoseg.synth.buildings import build_building_model
    from geoseg.synth.world import WorldConfig

    world = build_world(WorldConfig(seed=2, blocks_x=2, blocks_y=2))
    model = build_building_model(world.buildings, seed=2, streets=world.streets)
    facades = Facades.read_csv(model.planes.write_csv(tmp_path / "facades.csv"))
    rng = np.random.default_rng(0)
    lo, hi = facades.p0.min(axis=0) - 10, facades.p0.max(axis=0) + 10
    points = np.column_stack([rng.uniform(lo, hi, (3000, 2)), rng.uniform(-2, 30, 3000)])
    points[::50] = np.nan
    for radius in (0.5, 3.0):
        pt, fc, d = facades.near(points, radius)
        D = facades.distances(np.nan_to_num(points, nan=1e9))
        want_pt, want_fc = np.nonzero(D <= radius)
        got = sorted(zip(pt.tolist(), fc.tolist(), strict=True))
        assert got == sorted(zip(want_pt.tolist(), want_fc.tolist(), strict=True))
        np.testing.assert_allclose(d, D[pt, fc])
        assert np.all(np.diff(pt) >= 0)


def test_bayes_matches_the_posterior_point_by_point(tmp_path):
    """The vectorised eq. 4.14 gives each point the facade and weight of
    :func:`plane_posterior` over its candidates."""
    from geoseg.synth import build_world
    from geoseg.synth.buildings import build_building_model
    from geoseg.synth.world import WorldConfig

    world = build_world(WorldConfig(seed=2, blocks_x=2, blocks_y=2))
    model = build_building_model(world.buildings, seed=2, streets=world.streets)
    facades = Facades.read_csv(model.planes.write_csv(tmp_path / "facades.csv"))
    rng = np.random.default_rng(1)
    lo, hi = facades.p0.min(axis=0), facades.p0.max(axis=0)
    points = np.column_stack([rng.uniform(lo, hi, (500, 2)), rng.uniform(0, 20, 500)])
    normals = rng.normal(size=(500, 3)) * [1, 1, 0.2]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    labels = np.where(rng.random(500) < 0.8, BUILDING, VEGETATION)
    a = associate_bayes(facades, points, labels, normals, BUILDING, 3.0)
    D = facades.distances(points)
    checked = 0
    for q in range(500):
        cand = np.flatnonzero(D[q] <= 3.0)
        if labels[q] != BUILDING or cand.size == 0:
            assert a.facade[q] == -1
            continue
        post = plane_posterior(normals[q], facades.normal[cand], D[q, cand])
        if post.max() == 0:
            assert a.facade[q] == -1
            continue
        assert a.facade[q] == cand[post.argmax()] and a.weight[q] == pytest.approx(post.max())
        checked += 1
    assert checked > 50
