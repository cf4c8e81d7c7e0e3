"""Picture keys: the class legend shows each palette colour, the normal key encodes normals the
way the normal maps do."""

from __future__ import annotations

import numpy as np

from geoseg.classes import PALETTE
from geoseg.infer import normals_to_rgb
from geoseg.legends import class_legend, normal_key, sphere_normals


def test_class_legend_holds_every_class_colour() -> None:
    img = class_legend(320, 240)
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8
    colours = {tuple(c) for c in img.reshape(-1, 3)}
    assert all(tuple(c) in colours for c in PALETTE)


def test_normal_key_is_a_sphere_facing_the_camera() -> None:
    n, inside = sphere_normals(101)
    np.testing.assert_allclose(np.linalg.norm(n[:, inside], axis=0), 1.0, atol=1e-5)
    assert (n[2, inside] <= 0).all()  # the visible half faces the camera (-z)
    np.testing.assert_allclose(n[:, 50, 50], [0, 0, -1], atol=0.02)  # centre: facing it
    assert n[1, 2, 50] < -0.9  # top: up (camera y points down)
    key = normal_key(101)
    assert key.shape == (101, 101, 3)
    # away from the text the key's colours are normals_to_rgb of the sphere's normals
    np.testing.assert_array_equal(key[70:80, 45:55], normals_to_rgb(n)[70:80, 45:55])
    assert (key[0, 0] == 255).all()  # outside the sphere: white
