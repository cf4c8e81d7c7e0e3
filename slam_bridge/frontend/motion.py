"""The image motion between two frames, from descriptors: the tracker's fallback prediction.

Lucas-Kanade reaches a few tens of pixels from its starting point (about
``2 ** levels * window / 2``). The front end starts each track at a constant-velocity prediction,
which fails when the image motion changes abruptly: a vehicle that turns sharply at a corner
(tens of degrees within a frame or two: flows of 100-500 px), or stops turning. Most tracks are
then lost in one frame, with the map's points still in view.

:class:`GlobalMotion` estimates the frame-to-frame motion without a prediction: ORB
features (``cv2.ORB``, oriented, multi-scale) of both frames, matched by Hamming distance with a
ratio test, and a homography fitted by RANSAC. A homography is the exact image motion of a pure
rotation (``H = K R K^-1``) and of a plane; in a turn the rotation dominates, and the homography's
error on the nearer points (a little translation) stays within Lucas-Kanade's reach, which then
refines each track from its prediction. It is only a prediction: the tracks it leads to pass the
same forward-backward and epipolar checks as any other.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["GlobalMotion", "MotionEstimate"]


@dataclass
class MotionEstimate:
    """A frame-to-frame homography.

    Attributes:
        H: ``(3, 3)`` maps pixels of the first frame to the second.
        inliers: RANSAC inliers among the matches.
        matches: matches after the ratio test.
    """

    H: np.ndarray
    inliers: int
    matches: int

    def apply(self, uv: np.ndarray) -> np.ndarray:
        """``(N, 2)`` float32: the pixels ``uv`` ``(N, 2)`` mapped by the homography."""
        if uv.shape[0] == 0:
            return np.zeros((0, 2), dtype=np.float32)
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.perspectiveTransform(pts, self.H).reshape(-1, 2).astype(np.float32)


class GlobalMotion:
    """Homography between two grayscale frames from ORB matches (module docstring).

    Args:
        features: most ORB features per frame.
        ratio: best / second-best Hamming distance of a match must be below this.
        threshold_px: RANSAC inlier threshold (pixels; loose: the homography is a prediction,
            and nearer points move off it).
        min_inliers: fewer inliers: no estimate.
        min_inlier_share: fewer inliers among the matches: no estimate.
    """

    def __init__(
        self,
        features: int = 1000,
        ratio: float = 0.8,
        threshold_px: float = 8.0,
        min_inliers: int = 15,
        min_inlier_share: float = 0.3,
    ) -> None:
        self.ratio = ratio
        self.threshold_px = threshold_px
        self.min_inliers = min_inliers
        self.min_inlier_share = min_inlier_share
        self._orb = cv2.ORB_create(nfeatures=features)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def estimate(
        self, gray0: np.ndarray, gray1: np.ndarray, seed: int = 0
    ) -> MotionEstimate | None:
        """The homography from ``gray0`` to ``gray1`` (``(H, W)`` uint8 each), or None (too few
        features, matches or inliers)."""
        k0, d0 = self._orb.detectAndCompute(gray0, None)
        k1, d1 = self._orb.detectAndCompute(gray1, None)
        if d0 is None or d1 is None or len(k0) < self.min_inliers or len(k1) < 2:
            return None
        pairs = self._matcher.knnMatch(d0, d1, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < self.ratio * p[1].distance]
        if len(good) < self.min_inliers:
            return None
        p0 = np.float32([k0[m.queryIdx].pt for m in good])
        p1 = np.float32([k1[m.trainIdx].pt for m in good])
        cv2.setRNGSeed(seed)
        H, mask = cv2.findHomography(p0, p1, cv2.RANSAC, self.threshold_px)
        if H is None or mask is None or not np.all(np.isfinite(H)):
            return None
        n_in = int(mask.sum())
        if n_in < max(self.min_inliers, self.min_inlier_share * len(good)):
            return None
        return MotionEstimate(H, n_in, len(good))
