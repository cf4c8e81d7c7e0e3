"""The vertical direction in a keyframe from its vertical line segments (vertical vanishing point).

GPS fixes give positions in x, y and the DEM gives z, so they hold a trajectory's heading and
pitch, but not its roll about the direction of travel: rotating a straight stretch of the map
about the line through its camera centres moves none of them. Monocular SLAM lets that roll
drift, and a DEM whose altitude error varies along the road tilts the map to follow it. In a
street, the vertical edges of buildings, windows, poles and doors are the classic cure (the
Manhattan-world assumption): their images meet at the vertical vanishing point, whose direction
``K^-1 v`` is gravity in the camera frame.

1. Line segments by OpenCV's LSD (:func:`detect_segments`).
2. Each segment's interpretation plane (through the camera centre and the segment) has a unit
   normal ``n``; a 3D vertical line's plane contains the vertical ``d``: ``n . d = 0``.
3. Only segments longer than ``min_length_px`` whose plane passes within ``gate_deg`` of the
   vertical the SLAM predicts are candidates (:func:`vertical_direction`): the SLAM's own
   estimate is good to a degree or two, which rules out nearly all non-vertical edges.
4. ``d`` minimises ``sum_i w_i (n_i . d)^2`` (``w_i`` the segment lengths: long edges are the
   most precise), by iteratively re-weighted least squares from the prediction with Tukey
   weights whose cut-off shrinks from the gate to ``inlier_deg`` (deterministic, no sampling).
5. Its covariance in the plane orthogonal to ``d``: the inverse of the segments' information
   (each normal's angle known to ``endpoint_sigma_px / length``) plus ``floor_deg^2`` for
   what that leaves out (edges slightly off vertical, lens distortion). A level forward camera
   sees its roll precisely (the segments' slopes) and its pitch poorly (their convergence).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geoseg.errors import ConfigError, check_shape

__all__ = ["VerticalLinesConfig", "VerticalEstimate", "detect_segments", "vertical_direction"]


@dataclass
class VerticalLinesConfig:
    """How the vertical direction is measured from line segments (module docstring).

    Attributes:
        min_length_px: shortest segment used.
        gate_deg: farthest a candidate segment's plane may pass from the predicted vertical.
        inlier_deg: final Tukey cut-off of the fit.
        min_segments: fewest inlier segments for a measurement.
        endpoint_sigma_px: standard deviation of a segment end across the segment.
        floor_deg: standard deviation added to the fit's own, per axis.
    """

    min_length_px: float = 40.0
    gate_deg: float = 4.0
    inlier_deg: float = 0.3
    min_segments: int = 8
    endpoint_sigma_px: float = 0.5
    floor_deg: float = 0.2

    def __post_init__(self) -> None:
        for name in ("min_length_px", "gate_deg", "inlier_deg", "endpoint_sigma_px", "floor_deg"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: expected > 0, got {getattr(self, name)}")
        if self.inlier_deg > self.gate_deg:
            raise ConfigError(
                f"inlier_deg: expected <= gate_deg ({self.gate_deg}), got {self.inlier_deg}"
            )
        if self.min_segments < 2:
            raise ConfigError(f"min_segments: expected >= 2, got {self.min_segments}")


@dataclass(frozen=True)
class VerticalEstimate:
    """The vertical measured in one image.

    Attributes:
        down_c: ``(3,)`` unit vector, world down in the camera frame.
        basis: ``(2, 3)`` orthonormal rows spanning the plane orthogonal to ``down_c``.
        covariance: ``(2, 2)`` covariance (rad^2) of ``down_c``'s error along ``basis``.
        num_segments: inlier segments.
    """

    down_c: np.ndarray
    basis: np.ndarray
    covariance: np.ndarray
    num_segments: int


_LSD = None


def detect_segments(gray: np.ndarray) -> np.ndarray:
    """Line segments of an image (OpenCV's LSD).

    Args:
        gray: ``(H, W)`` uint8 image (or ``(H, W, 3)`` RGB, converted).

    Returns:
        ``(N, 4)`` float64 ``x0, y0, x1, y1`` pixels.
    """
    global _LSD
    if gray.ndim == 3:
        gray = cv2.cvtColor(gray, cv2.COLOR_RGB2GRAY)
    if _LSD is None:
        _LSD = cv2.createLineSegmentDetector()
    lines = _LSD.detect(gray)[0]
    return np.zeros((0, 4)) if lines is None else lines.reshape(-1, 4).astype(np.float64)


def vertical_direction(
    segments: np.ndarray,
    K: np.ndarray,
    predicted_down_c: np.ndarray,
    config: VerticalLinesConfig | None = None,
) -> VerticalEstimate | None:
    """Gravity's direction in the camera frame from an image's vertical segments.

    Args:
        segments: ``(N, 4)`` pixel segments (:func:`detect_segments`).
        K: ``(3, 3)`` intrinsics.
        predicted_down_c: ``(3,)`` the SLAM's estimate of world down in the camera frame.
        config: thresholds (defaults when None).

    Returns:
        The estimate, or None when fewer than ``min_segments`` segments agree on one or the fit
        is singular (all inliers on one image line).
    """
    cfg = config or VerticalLinesConfig()
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    check_shape("K", np.asarray(K), (3, 3))
    d = np.asarray(predicted_down_c, dtype=np.float64).reshape(3)
    d = d / np.linalg.norm(d)
    length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    segments, length = segments[length >= cfg.min_length_px], length[length >= cfg.min_length_px]
    if len(segments) < cfg.min_segments:
        return None
    K_inv = np.linalg.inv(np.asarray(K, dtype=np.float64))
    ones = np.ones((len(segments), 1))
    a = np.hstack([segments[:, :2], ones]) @ K_inv.T
    b = np.hstack([segments[:, 2:], ones]) @ K_inv.T
    n = np.cross(a, b)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    keep = np.abs(n @ d) < np.sin(np.radians(cfg.gate_deg))
    n, length = n[keep], length[keep]
    if len(n) < cfg.min_segments:
        return None
    # a normal's angle is known to ~ endpoint_sigma / length (pixels over pixels)
    info = (length / cfg.endpoint_sigma_px) ** 2
    inliers = np.zeros(len(n), dtype=bool)
    for cut_deg in np.geomspace(cfg.gate_deg, cfg.inlier_deg, 5):
        u = (n @ d) / np.sin(np.radians(cut_deg))
        inliers = np.abs(u) < 1.0
        if inliers.sum() < cfg.min_segments:
            return None
        w = length * np.where(inliers, (1.0 - u**2) ** 2, 0.0)
        _, _, Vt = np.linalg.svd(n * np.sqrt(w)[:, None], full_matrices=False)
        d = Vt[2] * np.sign(Vt[2] @ d)
    basis = Vt[:2]
    # information of d's tangent error: each inlier plane measures d's component along its normal
    t = n[inliers] @ basis.T  # (M, 2)
    information = (t * info[inliers, None]).T @ t
    if np.linalg.cond(information) > 1e8:
        return None
    covariance = np.linalg.inv(information) + np.radians(cfg.floor_deg) ** 2 * np.eye(2)
    return VerticalEstimate(d, basis, covariance, int(inliers.sum()))
