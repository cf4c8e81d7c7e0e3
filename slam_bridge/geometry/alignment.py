"""Umeyama's rotation and scale between two centred point sets: the one core of every
similarity fit (the SLAM's georeferencing, the evaluation's alignment, the benches' fits)."""

from __future__ import annotations

import numpy as np

from slam_bridge.errors import SlamError

__all__ = ["rotation_and_scale"]


def rotation_and_scale(
    a: np.ndarray, b: np.ndarray, H: np.ndarray, *, fix_scale: bool, name: str
) -> tuple[float, np.ndarray]:
    """Umeyama's rotation and scale of centred point sets, ``b ~ s R a``.

    Args:
        a: ``(N, D)`` centred source points.
        b: ``(N, D)`` centred targets.
        H: ``(D, D)`` the cross-covariance ``b^T a`` (plus any extra pair a caller weighs in).
        fix_scale: keep ``s = 1``.
        name: the caller, named in the errors.

    Returns:
        ``(s, R (D, D))``, ``R`` a proper rotation.

    Raises:
        SlamError: coincident source points, a non-positive scale.
    """
    U, _, Vt = np.linalg.svd(H)
    D = np.eye(H.shape[0])
    D[-1, -1] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ D @ Vt
    if fix_scale:
        return 1.0, R
    var = float(np.sum(a * a))
    if var < 1e-12:
        raise SlamError(f"{name}: the source points coincide")
    s = float(np.sum(b * (a @ R.T)) / var)
    if not s > 0:
        raise SlamError(f"{name}: non-positive scale {s}")
    return s, R
