"""SO(3) and SE(3): hat, vee, exp, log and their Jacobians (thesis §1.4, eqs. 1.44-1.56).

Conventions (used by every module of ``slam_bridge``):

* **Standard hat.** ``so3_hat(w)`` is the cross-product matrix, ``so3_hat(w) @ v == cross(w, v)``::

      hat(w) = [[ 0, -w3,  w2],
                [ w3,  0, -w1],
                [-w2,  w1,  0]]

  The thesis writes its generator basis differently (eq. 1.44):
  ``sum_i a_i G_i = [[0, a1, -a2], [-a1, 0, a3], [a2, -a3, 0]]``. Both span so(3); the package
  uses the standard ``hat`` internally and :func:`thesis_coefficients` /
  :func:`from_thesis_coefficients` convert: ``a = (-w3, -w2, -w1)``. The basis itself is
  :data:`THESIS_GENERATORS` ``(3, 3, 3)`` with ``THESIS_GENERATORS[i] = G_{i+1}``.
* **SE(3) twists are rotation first**: ``xi = [w (3), v (3)]`` (the thesis writes ``(v, w)`` in
  eq. 1.51; we put the rotation first to match the camera increment ``[dw, dT]`` of
  :mod:`slam_bridge.geometry.camera`). ``se3_exp(xi) = (exp(w), J_l(w) v)`` where ``J_l`` is the
  SO(3) left Jacobian, the thesis's ``W`` of eqs. 1.51-1.53 (the thesis's typeset eq. 1.53 has a
  sign slip on the quadratic term; we use ``W = I + (1 - cos t)/t^2 [w] + (t - sin t)/t^3 [w]^2``).
* **Jacobians.** Left: ``exp(w + dw) ~= exp(J_l(w) dw) exp(w)``; right:
  ``exp(w + dw) ~= exp(w) exp(J_r(w) dw)``; ``J_r(w) = J_l(-w)``. The same definitions hold for
  SE(3) with the 6x6 Jacobians and ``se3_exp``.
* **Poses** are ``(R, t)`` pairs, ``(..., 3, 3)`` and ``(..., 3)``; the 4x4 form is available via
  :func:`se3_to_matrix` / :func:`se3_from_matrix`.

Every function is vectorised over leading dimensions and uses Taylor series below
``_SMALL = 0.1`` rad (series to ``theta^8``, truncation < 1e-17) so that no coefficient suffers
cancellation. ``so3_log`` is stable near ``pi`` (the axis is read from the symmetric part).
"""

from __future__ import annotations

import logging

import numpy as np

from geoseg.errors import GeosegError

logger = logging.getLogger(__name__)

__all__ = [
    "THESIS_GENERATORS",
    "thesis_coefficients",
    "from_thesis_coefficients",
    "so3_hat",
    "so3_vee",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "so3_right_jacobian",
    "so3_left_jacobian_inv",
    "so3_right_jacobian_inv",
    "se3_hat",
    "se3_vee",
    "se3_exp",
    "se3_log",
    "se3_left_jacobian",
    "se3_right_jacobian",
    "se3_left_jacobian_inv",
    "se3_right_jacobian_inv",
    "se3_adjoint",
    "se3_compose",
    "se3_inverse",
    "se3_to_matrix",
    "se3_from_matrix",
]

_SMALL = 0.1

#: The thesis's so(3) generator basis (eq. 1.44), ``(3, 3, 3)``: ``THESIS_GENERATORS[i] = G_{i+1}``
#: so that ``sum_i a_i G_i = [[0, a1, -a2], [-a1, 0, a3], [a2, -a3, 0]]``.
THESIS_GENERATORS = np.array(
    [
        [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        [[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
        [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]],
    ]
)
THESIS_GENERATORS.setflags(write=False)


def _as_vec(name: str, x: np.ndarray, n: int) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] != n:
        raise GeosegError(f"{name}: expected shape (..., {n}), got {x.shape}")
    return x


def _as_mat(name: str, x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim < 2 or x.shape[-2:] != (3, 3):
        raise GeosegError(f"{name}: expected shape (..., 3, 3), got {x.shape}")
    return x


def _coef(theta2: np.ndarray, exact, series: tuple[float, ...]) -> np.ndarray:
    """Evaluate a coefficient of ``theta`` exactly above ``_SMALL`` and by its series below.

    Args:
        theta2: squared angles, any shape.
        exact: ``f(theta) -> value`` valid for ``theta >= _SMALL``.
        series: coefficients ``c_k`` of ``sum_k c_k theta^(2k)``.
    """
    small = theta2 < _SMALL * _SMALL
    theta = np.sqrt(np.where(small, 1.0, theta2))
    with np.errstate(divide="ignore", invalid="ignore"):
        big = exact(theta)
    poly = np.zeros_like(theta2)
    for c in reversed(series):
        poly = poly * theta2 + c
    return np.where(small, poly, big)


def _A(t2):  # sin t / t
    return _coef(t2, lambda t: np.sin(t) / t, (1, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880))


def _B(t2):  # (1 - cos t) / t^2
    return _coef(
        t2,
        lambda t: (1 - np.cos(t)) / t**2,
        (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800),
    )


def _C(t2):  # (t - sin t) / t^3
    return _coef(
        t2,
        lambda t: (t - np.sin(t)) / t**3,
        (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800),
    )


def _D(t2):  # (1 - t sin t / (2 (1 - cos t))) / t^2, the J^-1 quadratic coefficient
    return _coef(
        t2,
        lambda t: (1 - t * np.sin(t) / (2 * (1 - np.cos(t)))) / t**2,
        (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160),
    )


def _E(t2):  # (t^2/2 + cos t - 1) / t^4
    return _coef(
        t2,
        lambda t: (t**2 / 2 + np.cos(t) - 1) / t**4,
        (1 / 24, -1 / 720, 1 / 40320, -1 / 3628800, 1 / 479001600),
    )


def _F(t2):  # (t - sin t - t^3/6) / t^5
    return _coef(
        t2,
        lambda t: (t - np.sin(t) - t**3 / 6) / t**5,
        (-1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800, -1 / 6227020800),
    )


# ----------------------------------------------------------------------------------- generators
def thesis_coefficients(w: np.ndarray) -> np.ndarray:
    """Coefficients ``a`` in the thesis's basis (eq. 1.44) of the rotation vector ``w``.

    Args:
        w: ``(..., 3)`` standard rotation vectors (``so3_hat(w)``).

    Returns:
        ``(..., 3)`` ``a`` with ``sum_i a_i THESIS_GENERATORS[i] == so3_hat(w)``, i.e.
        ``a = (-w3, -w2, -w1)``.
    """
    w = _as_vec("w", w, 3)
    return -w[..., ::-1].copy()


def from_thesis_coefficients(a: np.ndarray) -> np.ndarray:
    """Inverse of :func:`thesis_coefficients`: ``(..., 3)`` ``a`` -> ``(..., 3)`` ``w``."""
    a = _as_vec("a", a, 3)
    return -a[..., ::-1].copy()


# -------------------------------------------------------------------------------------- SO(3)
def so3_hat(w: np.ndarray) -> np.ndarray:
    """Cross-product matrix.

    Args:
        w: ``(..., 3)``.

    Returns:
        ``(..., 3, 3)`` skew-symmetric ``W`` with ``W v = w x v``.
    """
    w = _as_vec("w", w, 3)
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1] = -w[..., 2]
    W[..., 0, 2] = w[..., 1]
    W[..., 1, 0] = w[..., 2]
    W[..., 1, 2] = -w[..., 0]
    W[..., 2, 0] = -w[..., 1]
    W[..., 2, 1] = w[..., 0]
    return W


def so3_vee(W: np.ndarray) -> np.ndarray:
    """Inverse of :func:`so3_hat`; reads the antisymmetric part ``(W - W^T) / 2``.

    Args:
        W: ``(..., 3, 3)``.

    Returns:
        ``(..., 3)``.
    """
    W = _as_mat("W", W)
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula (eq. 1.49).

    Args:
        w: ``(..., 3)`` rotation vectors (angle = norm, radians).

    Returns:
        ``(..., 3, 3)`` rotation matrices.
    """
    w = _as_vec("w", w, 3)
    t2 = np.einsum("...i,...i->...", w, w)
    W = so3_hat(w)
    return np.eye(3) + _A(t2)[..., None, None] * W + _B(t2)[..., None, None] * (W @ W)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (eq. 1.50), stable near 0 and near ``pi``.

    For ``cos(theta) > 0`` the antisymmetric part is used (``w = theta / sin(theta) s``); otherwise
    the axis is read from the symmetric part ``(R + R^T)/2 - cos(theta) I = (1 - cos) a a^T`` and
    its sign from the antisymmetric part. At exactly ``pi`` the sign is arbitrary.

    Args:
        R: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 3)`` rotation vectors with norm in ``[0, pi]``.
    """
    R = _as_mat("R", R)
    shape = R.shape[:-2]
    Rf = R.reshape(-1, 3, 3)
    s = so3_vee(Rf)  # sin(theta) * axis
    c = np.clip((np.trace(Rf, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    sn = np.linalg.norm(s, axis=-1)
    theta = np.arctan2(sn, c)
    # branch 1: theta < pi/2, theta / sin(theta) well conditioned
    out = _inv_A(theta * theta)[:, None] * s
    near_pi = c <= 0.0
    if np.any(near_pi):
        Rp, cp, sp, tp = Rf[near_pi], c[near_pi], s[near_pi], theta[near_pi]
        M = 0.5 * (Rp + np.swapaxes(Rp, -1, -2)) - cp[:, None, None] * np.eye(3)
        d = np.diagonal(M, axis1=-2, axis2=-1)
        k = np.argmax(d, axis=-1)
        col = np.take_along_axis(M, k[:, None, None], axis=-1)[..., 0]  # (n, 3) = (1-c) a_k a
        axis = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.einsum("ni,ni->n", axis, sp) < 0, -1.0, 1.0)
        out[near_pi] = (sign * tp)[:, None] * axis
    return out.reshape(shape + (3,))


def _inv_A(t2):  # t / sin t, only used for t < pi/2 + margin
    return _coef(
        t2,
        lambda t: t / np.sin(t),
        (1, 1 / 6, 7 / 360, 31 / 15120, 127 / 604800),
    )


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian ``J_l(w) = I + B [w] + C [w]^2`` (the thesis's ``W``, eq. 1.53).

    Args:
        w: ``(..., 3)``.

    Returns:
        ``(..., 3, 3)`` with ``exp(w + dw) ~= exp(J_l dw) exp(w)``.
    """
    w = _as_vec("w", w, 3)
    t2 = np.einsum("...i,...i->...", w, w)
    W = so3_hat(w)
    return np.eye(3) + _B(t2)[..., None, None] * W + _C(t2)[..., None, None] * (W @ W)


def so3_right_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3) right Jacobian ``J_r(w) = J_l(-w)``: ``exp(w + dw) ~= exp(w) exp(J_r dw)``.

    Args:
        w: ``(..., 3)``.

    Returns:
        ``(..., 3, 3)``.
    """
    return so3_left_jacobian(-_as_vec("w", w, 3))


def so3_left_jacobian_inv(w: np.ndarray) -> np.ndarray:
    """Inverse of :func:`so3_left_jacobian`, ``I - [w]/2 + D [w]^2`` (singular at ``2 pi``).

    Args:
        w: ``(..., 3)``.

    Returns:
        ``(..., 3, 3)``.
    """
    w = _as_vec("w", w, 3)
    t2 = np.einsum("...i,...i->...", w, w)
    W = so3_hat(w)
    return np.eye(3) - 0.5 * W + _D(t2)[..., None, None] * (W @ W)


def so3_right_jacobian_inv(w: np.ndarray) -> np.ndarray:
    """Inverse of :func:`so3_right_jacobian`: ``(..., 3)`` -> ``(..., 3, 3)``."""
    return so3_left_jacobian_inv(-_as_vec("w", w, 3))


# -------------------------------------------------------------------------------------- SE(3)
def se3_hat(xi: np.ndarray) -> np.ndarray:
    """Twist ``[w, v]`` to its 4x4 matrix ``[[hat(w), v], [0, 0]]``.

    Args:
        xi: ``(..., 6)`` rotation first.

    Returns:
        ``(..., 4, 4)``.
    """
    xi = _as_vec("xi", xi, 6)
    X = np.zeros(xi.shape[:-1] + (4, 4))
    X[..., :3, :3] = so3_hat(xi[..., :3])
    X[..., :3, 3] = xi[..., 3:]
    return X


def se3_vee(X: np.ndarray) -> np.ndarray:
    """Inverse of :func:`se3_hat`: ``(..., 4, 4)`` -> ``(..., 6)`` ``[w, v]``."""
    X = np.asarray(X, dtype=np.float64)
    if X.ndim < 2 or X.shape[-2:] != (4, 4):
        raise GeosegError(f"X: expected shape (..., 4, 4), got {X.shape}")
    return np.concatenate([so3_vee(X[..., :3, :3]), X[..., :3, 3]], axis=-1)


def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SE(3) exponential (eq. 1.51): ``(exp(w), J_l(w) v)``.

    Args:
        xi: ``(..., 6)`` twists ``[w, v]``.

    Returns:
        ``R (..., 3, 3)``, ``t (..., 3)``.
    """
    xi = _as_vec("xi", xi, 6)
    w, v = xi[..., :3], xi[..., 3:]
    return so3_exp(w), np.einsum("...ij,...j->...i", so3_left_jacobian(w), v)


def se3_log(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """SE(3) logarithm (eq. 1.52): ``[log(R), J_l(log R)^-1 t]``.

    Args:
        R: ``(..., 3, 3)``.
        t: ``(..., 3)``.

    Returns:
        ``(..., 6)`` twists ``[w, v]``.
    """
    R = _as_mat("R", R)
    t = _as_vec("t", t, 3)
    w = so3_log(R)
    v = np.einsum("...ij,...j->...i", so3_left_jacobian_inv(w), t)
    return np.concatenate([w, v], axis=-1)


def _se3_Q(xi: np.ndarray) -> np.ndarray:
    """The off-diagonal block ``Q(w, v)`` of the SE(3) left Jacobian, ``(..., 3, 3)``."""
    w, v = xi[..., :3], xi[..., 3:]
    t2 = np.einsum("...i,...i->...", w, w)
    Wh, Vh = so3_hat(w), so3_hat(v)
    WV, VW = Wh @ Vh, Vh @ Wh
    WVW = WV @ Wh
    c1 = _C(t2)[..., None, None]
    c2 = _E(t2)[..., None, None]
    c3 = (0.5 * (_E(t2) + 3.0 * _F(t2)))[..., None, None]
    return (
        0.5 * Vh
        + c1 * (WV + VW + WVW)
        + c2 * (Wh @ WV + VW @ Wh - 3.0 * WVW)
        + c3 * (WVW @ Wh + Wh @ WVW)
    )


def se3_left_jacobian(xi: np.ndarray) -> np.ndarray:
    """SE(3) left Jacobian for twists ``[w, v]``: ``[[J_l(w), 0], [Q(w, v), J_l(w)]]``.

    Args:
        xi: ``(..., 6)``.

    Returns:
        ``(..., 6, 6)`` with ``se3_exp(xi + d) ~= se3_exp(J d) * se3_exp(xi)`` (composition).
    """
    xi = _as_vec("xi", xi, 6)
    J = np.zeros(xi.shape[:-1] + (6, 6))
    Jl = so3_left_jacobian(xi[..., :3])
    J[..., :3, :3] = Jl
    J[..., 3:, 3:] = Jl
    J[..., 3:, :3] = _se3_Q(xi)
    return J


def se3_right_jacobian(xi: np.ndarray) -> np.ndarray:
    """SE(3) right Jacobian ``J_r(xi) = J_l(-xi)``: ``(..., 6)`` -> ``(..., 6, 6)``."""
    return se3_left_jacobian(-_as_vec("xi", xi, 6))


def se3_left_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """Inverse of :func:`se3_left_jacobian`: ``[[J^-1, 0], [-J^-1 Q J^-1, J^-1]]``.

    Args:
        xi: ``(..., 6)``.

    Returns:
        ``(..., 6, 6)``.
    """
    xi = _as_vec("xi", xi, 6)
    Ji = so3_left_jacobian_inv(xi[..., :3])
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = Ji
    out[..., 3:, 3:] = Ji
    out[..., 3:, :3] = -Ji @ _se3_Q(xi) @ Ji
    return out


def se3_right_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """Inverse of :func:`se3_right_jacobian`: ``(..., 6)`` -> ``(..., 6, 6)``."""
    return se3_left_jacobian_inv(-_as_vec("xi", xi, 6))


def se3_adjoint(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Adjoint of ``(R, t)`` for twists ``[w, v]``: ``[[R, 0], [hat(t) R, R]]``.

    ``T exp(xi) T^-1 = exp(Ad_T xi)``.

    Args:
        R: ``(..., 3, 3)``.
        t: ``(..., 3)``.

    Returns:
        ``(..., 6, 6)``.
    """
    R = _as_mat("R", R)
    t = _as_vec("t", t, 3)
    A = np.zeros(np.broadcast_shapes(R.shape[:-2], t.shape[:-1]) + (6, 6))
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., 3:, :3] = so3_hat(t) @ R
    return A


def se3_compose(
    R_ab: np.ndarray, t_ab: np.ndarray, R_bc: np.ndarray, t_bc: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``T_ac = T_ab T_bc``; all ``(..., 3, 3)`` / ``(..., 3)``, broadcast."""
    return R_ab @ R_bc, np.einsum("...ij,...j->...i", R_ab, t_bc) + t_ab


def se3_inverse(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T^-1 = (R^T, -R^T t)``; ``(..., 3, 3)``, ``(..., 3)``."""
    Rt = np.swapaxes(R, -1, -2)
    return Rt, -np.einsum("...ij,...j->...i", Rt, t)


def se3_to_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)``, ``(..., 3)`` -> ``(..., 4, 4)`` homogeneous matrices."""
    R = _as_mat("R", R)
    t = _as_vec("t", t, 3)
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], t.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_from_matrix(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(..., 4, 4)`` -> ``R (..., 3, 3)``, ``t (..., 3)``."""
    T = np.asarray(T, dtype=np.float64)
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise GeosegError(f"T: expected shape (..., 4, 4), got {T.shape}")
    return T[..., :3, :3].copy(), T[..., :3, 3].copy()
