"""Align tracks to the patch of their reference keyframe, so that frame-to-frame drift does not
accumulate.

Lucas-Kanade from frame to frame follows a point with a small error at every frame; along a
track's life the errors add up, mostly along the epipolar line (the direction of the flow),
where no geometric check sees them: the point is triangulated at a slightly wrong depth. At a
keyframe, :func:`align_patches` moves each track to where the patch around its
*reference* pixel (the keyframe where the track started) best matches the current image, the
patch warped by the track's local linear map ``A`` (the image's deformation since the
reference, from the neighbouring tracks' motion): the feature alignment of semi-direct visual
odometry (Forster et al., SVO, 2014), here with the warp from the image rather than from the
map.

The alignment is Gauss-Newton on the translation and an affine change of brightness:
``min_{d, a, b} sum_o (I(p + d + o) - a T(o) - b)^2`` over the offsets ``o`` of a
``(2h + 1) x (2h + 1)`` window, ``T(o) = R(r + A^-1 o)`` the reference image ``R`` sampled
around the reference pixel ``r`` (bilinear, ``cv2.remap``), all tracks at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam_bridge.frontend.features import Gradients, gradients

__all__ = ["Alignment", "reference_patches", "align_patches"]


@dataclass
class Alignment:
    """Result of :func:`align_patches` for ``N`` tracks.

    Attributes:
        uv: ``(N, 2)`` float32 aligned pixels (the input where not ``ok``).
        shift: ``(N,)`` distance the alignment moved each track (pixels; where not ``ok``,
            the move it found and that was not applied).
        zncc: ``(N,)`` zero-mean normalised cross-correlation of the warped reference patch
            and the current one where the alignment ended (in ``[-1, 1]``; 0 for a flat
            patch).
        ok: ``(N,)`` bool: converged, moved at most ``max_shift`` and ``zncc >= min_zncc``.
    """

    uv: np.ndarray
    shift: np.ndarray
    zncc: np.ndarray
    ok: np.ndarray


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` ``(H, W)`` float32 at ``x, y`` ``(N, P)`` (border
    replicated)."""
    return cv2.remap(
        image,
        x.astype(np.float32),
        y.astype(np.float32),
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def _zncc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(N,)`` ZNCC of the rows of ``a`` and ``b`` ``(N, P)`` (0 for a flat row)."""
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    den = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    return np.where(den > 1e-9, (a * b).sum(axis=1) / np.maximum(den, 1e-9), 0.0)


def _offsets(half_window: int) -> tuple[np.ndarray, np.ndarray]:
    """``(P,)`` x and y offsets of the pixels of a ``2 h + 1`` square window, row-major."""
    off = np.arange(-half_window, half_window + 1, dtype=np.float64)
    ox, oy = np.meshgrid(off, off)
    return ox.ravel(), oy.ravel()


def reference_patches(
    reference: np.ndarray, ref_uv: np.ndarray, A: np.ndarray, half_window: int
) -> tuple[np.ndarray, np.ndarray]:
    """The reference patches warped into the current image's frame.

    Args:
        reference: ``(H, W)`` image where the patches were taken.
        ref_uv: ``(N, 2)`` their centres in it.
        A: ``(N, 2, 2)`` local linear maps from the reference to the current image.
        half_window: the window is ``2 h + 1`` pixels square.

    Returns:
        ``(T (N, P) float64, ok (N,) bool)``: ``T(o) = R(r + A^-1 o)`` over the window's
        offsets ``o`` (row-major, ``P = (2 h + 1)^2``); ok where ``A`` is invertible.
    """
    ox, oy = _offsets(half_window)
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    ok = np.abs(det) > 1e-6
    Ainv = np.broadcast_to(np.eye(2), A.shape).copy()
    Ainv[ok] = np.linalg.inv(A[ok])
    rx = ref_uv[:, :1] + Ainv[:, 0, :1] * ox + Ainv[:, 0, 1:] * oy  # (N, P)
    ry = ref_uv[:, 1:] + Ainv[:, 1, :1] * ox + Ainv[:, 1, 1:] * oy
    return _sample(np.asarray(reference, dtype=np.float32), rx, ry).astype(np.float64), ok


def align_patches(
    T: np.ndarray,
    current: np.ndarray,
    uv: np.ndarray,
    *,
    grads: Gradients | None = None,
    iterations: int = 10,
    max_shift: float = 2.0,
    min_zncc: float = 0.8,
) -> Alignment:
    """Move the tracks ``uv`` to where their patches ``T`` match ``current`` best (module
    docstring).

    Args:
        T: ``(N, P)`` the tracks' reference patches (:func:`reference_patches`).
        current: ``(H, W)`` the current image.
        uv: ``(N, 2)`` their tracked pixels in ``current`` (the starting point).
        grads: ``current``'s 3x3 Sobel gradients
            (:func:`slam_bridge.frontend.features.gradients`), when already computed.
        iterations: Gauss-Newton iterations (steps clipped to 1 pixel).
        max_shift: a track moved further than this (pixels) is not aligned.
        min_zncc: least ZNCC of the aligned patches.

    Returns:
        The :class:`Alignment`.
    """
    uv0 = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n = uv0.shape[0]
    if n == 0:
        z = np.zeros(0)
        return Alignment(np.zeros((0, 2), np.float32), z, z, np.zeros(0, dtype=bool))
    ox, oy = _offsets(int(round(np.sqrt(T.shape[1]))) // 2)
    cur = np.asarray(current, dtype=np.float32)
    grads = gradients(cur) if grads is None else grads
    gx_img, gy_img = grads.Ix / 8.0, grads.Iy / 8.0  # a 3x3 Sobel is 8x the derivative
    p = uv0.copy()
    gain, bias = np.ones(n), np.zeros(n)
    step = np.full(n, np.inf)
    active = np.ones(n, dtype=bool)
    for _ in range(iterations):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        x, y = p[idx, :1] + ox, p[idx, 1:] + oy
        img, gx, gy = (_sample(a, x, y).astype(np.float64) for a in (cur, gx_img, gy_img))
        t = T[idx]
        r = img - gain[idx, None] * t - bias[idx, None]  # (M, P)
        J = np.stack([gx, gy, -t, -np.ones_like(t)], axis=2)  # (M, P, 4)
        H = np.einsum("mpi,mpj->mij", J, J) + 1e-6 * np.eye(4)
        delta = -np.linalg.solve(H, np.einsum("mpi,mp->mi", J, r)[..., None])[..., 0]
        norm = np.linalg.norm(delta[:, :2], axis=1)
        p[idx] += delta[:, :2] * np.minimum(1.0, 1.0 / np.maximum(norm, 1e-12))[:, None]
        gain[idx] += delta[:, 2]
        bias[idx] += delta[:, 3]
        step[idx] = np.minimum(norm, 1.0)
        active[idx] = norm > 0.01
    zncc = _zncc(_sample(cur, p[:, :1] + ox, p[:, 1:] + oy).astype(np.float64), T)
    shift = np.linalg.norm(p - uv0, axis=1)
    ok = (step < 0.1) & (shift <= max_shift) & (zncc >= min_zncc)
    return Alignment(np.where(ok[:, None], p, uv0).astype(np.float32), shift, zncc, ok)
