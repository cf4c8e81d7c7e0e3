"""Settings of the visual front end (:class:`slam_bridge.frontend.image_tracks.ImageTracks`).

:class:`ImageTracksConfig` is a plain dataclass with its defaults next to the code (the stages
it refers to are numbered in :mod:`slam_bridge.frontend.image_tracks`); every field is checked
when it is built, with an error that names it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from slam_bridge.errors import SlamError
from slam_bridge.frontend.keyframes import KeyframeConfig

__all__ = ["ImageTracksConfig"]


@dataclass
class ImageTracksConfig:
    """Settings of :class:`ImageTracks` (the module docstring numbers the stages).

    Attributes:
        max_tracks: most live tracks (corners are topped up to it at keyframes).
        grid: ``(columns, rows)`` of the bucketing grid.
        min_distance_px: least distance between corners (at ``reference_width``).
        quality_level: Shi-Tomasi threshold, share of the strongest corner's response.
        block_size: Shi-Tomasi neighbourhood (pixels).
        border_px: corners and tracks stay this far inside the image (at ``reference_width``).
        gamma_target: the median grey level is mapped to this share of 255 (brighten only);
            None: no normalisation.
        equalize_clip: contrast-limited histogram equalisation (``cv2.createCLAHE``) with this
            clip limit instead of the gamma (None: the gamma).
        equalize_tiles: its tiles per side (1: one global lookup table).
        window_px: Lucas-Kanade window side (odd, pixels). LK moves a window by one
            translation; the views of a surface seen 2 m apart differ by more (scale, shear),
            which biases a wide window along the motion, past 2 px on a tenth of the
            observations with 11 px, on 3 % with 5 px (docs/lessons.md).
        pyramid_levels: LK pyramid levels above the image (reach about
            ``2 ** levels * window_px / 2`` pixels from the prediction).
        lk_iterations: LK iterations per level.
        lk_epsilon: LK convergence threshold (pixels).
        lk_min_eigenvalue: LK's least eigenvalue of the window's gradient matrix (divided by
            the window area); weaker windows fail.
        fb_threshold_px: largest forward-backward distance. A track that LK does not bring
            back within a tenth of a pixel is one whose window matched ambiguously.
        recover_share: when fewer than this share of the established tracks (tracked through a
            frame before) survive a frame, the prediction failed (a sharp turn): the frame's
            motion is estimated from ORB matches (:mod:`slam_bridge.frontend.motion`) and the
            lost tracks are tracked again from it (0: never).
        recover_min_tracks: with fewer established tracks, all tracks count, at half the share
            (corners lose about half of them in their first frame).
        recover_keyframe_tracks: a recovery that finds at least this many tracks again makes
            the frame a keyframe (the keyframe rule's ``turn``).
        epipolar: where the essential-matrix check runs: ``frame``, ``keyframe``, ``both``,
            ``off``.
        ransac_method: ``magsac`` (``cv2.USAC_MAGSAC``) or ``ransac`` (``cv2.RANSAC``).
        ransac_threshold_px: inlier threshold (pixels).
        ransac_confidence: RANSAC confidence.
        min_epipolar_tracks: fewer tracks: no check.
        min_epipolar_motion_px: smaller median displacement: no check.
        min_eigen_ratio: least ``lambda_min / lambda_max`` of a track's LK window (0: off).
        centre_iterations: LK fixed-point iterations for new tracks (0: off).
        centre_max_shift_px: a corner that centring moves further is not used.
        flow_neighbours: neighbours of the local-flow and deformation checks.
        flow_abs_px: local-flow tolerance, pixels (at ``reference_width``).
        flow_rel: local-flow tolerance, share of the neighbours' median displacement.
        flow_radius_px: a track whose neighbours lie farther than this (median distance, at
            ``reference_width``) is not checked: they are on other surfaces, at other depths,
            and move otherwise (None: all are checked).
        max_deformation: a track is renewed when a singular value of its accumulated local
            linear map leaves ``exp(+-max_deformation)`` (None: never).
        max_shear: a track is renewed when the ratio of those singular values exceeds
            ``exp(max_shear)`` (anisotropic deformation: ground and oblique surfaces; None:
            never).
        align: at each keyframe, align every track that started at an earlier keyframe to its
            reference patch (stage 8, :mod:`slam_bridge.frontend.patch_alignment`): the drift
            of frame-to-frame tracking does not accumulate.
        align_half_window: the alignment window is ``2 h + 1`` pixels square.
        align_min_zncc: least correlation of an accepted alignment.
        align_max_shift_px: an alignment that moves a track further is not accepted.
        max_track_keyframes: with ``align`` and a map that tracks the live tracks (not during
            a start), a track ends this many keyframes after its reference keyframe (stage 8):
            the alignment bounds the frame-to-frame drift but not the error of its accumulated
            warp, which grows with the change of view (six drives: 2 px outliers 2.4 % -> 1.9 %
            of the observations, docs/lessons.md; None: tracks live on).
        map_check: the PnP check of the tracks of triangulated points (stage 9).
        map_check_threshold_px: reprojection error above which a track fails it.
        min_map_points: fewer tracked triangulated points: no map check.
        reobserve: match untracked map points at keyframes (stage 11).
        reacquire_keyframes: keyframe images kept to re-acquire, by LK, the untracked map points
            that one of them observed (0: descriptors only).
        match_radius_px: search radius around a point projected with the predicted pose (at
            ``reference_width``).
        match_radius_pnp_px: the same with the map-check pose.
        max_descriptor_distance: largest Hamming distance (of 256 bits) of a match.
        match_ratio: best / second-best distance must be below this.
        refresh_descriptors: store each live track's descriptor again at every keyframe.
        adaptive_grid: scale each cell's quota by the first-frame survival of its new tracks.
        keyframes: the keyframe rule.
        reference_width: image width at which pixel lengths are given.
        seed: OpenCV RNG seed (RANSAC), for deterministic output.
    """

    max_tracks: int = 600
    grid: tuple[int, int] = (8, 6)
    min_distance_px: float = 12.0
    quality_level: float = 0.001
    block_size: int = 3
    border_px: float = 10.0
    gamma_target: float | None = 0.4
    equalize_clip: float | None = 3.0
    equalize_tiles: int = 8
    window_px: int = 5
    pyramid_levels: int = 3
    lk_iterations: int = 20
    lk_epsilon: float = 0.03
    lk_min_eigenvalue: float = 1e-4
    fb_threshold_px: float = 0.1
    recover_share: float = 0.5
    recover_min_tracks: int = 10
    recover_keyframe_tracks: int = 20
    epipolar: Literal["frame", "keyframe", "both", "off"] = "both"
    ransac_method: Literal["magsac", "ransac"] = "magsac"
    ransac_threshold_px: float = 0.7
    ransac_confidence: float = 0.999
    min_epipolar_tracks: int = 15
    min_epipolar_motion_px: float = 1.0
    min_eigen_ratio: float = 0.1
    centre_iterations: int = 3
    centre_max_shift_px: float = 3.0
    flow_neighbours: int = 8
    flow_abs_px: float = 3.0
    flow_rel: float = 0.3
    flow_radius_px: float | None = 60.0
    max_deformation: float | None = None
    max_shear: float | None = None
    align: bool = True
    align_half_window: int = 4
    align_min_zncc: float = 0.8
    align_max_shift_px: float = 2.0
    max_track_keyframes: int | None = 6
    map_check: bool = True
    map_check_threshold_px: float = 1.5
    min_map_points: int = 12
    reobserve: bool = True
    reacquire_keyframes: int = 3
    match_radius_px: float = 12.0
    match_radius_pnp_px: float = 5.0
    max_descriptor_distance: int = 48
    match_ratio: float = 0.8
    refresh_descriptors: bool = True
    adaptive_grid: bool = True
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    reference_width: int = 640
    seed: int = 0

    def __post_init__(self) -> None:
        for key, (ok, expected) in _CHECKS.items():
            if not ok(getattr(self, key)):
                raise SlamError(
                    f"ImageTracksConfig.{key}: expected {expected}, got {getattr(self, key)!r}"
                )


def _number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _integer(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


_POSITIVE_INT = (lambda v: _integer(v) and v > 0, "an integer > 0")
_NATURAL = (lambda v: _integer(v) and v >= 0, "an integer >= 0")
_POSITIVE = (lambda v: _number(v) and v > 0, "a number > 0")
_NON_NEGATIVE = (lambda v: _number(v) and v >= 0, "a number >= 0")
# fmt: off
_CHECKS = {
    **dict.fromkeys(("max_tracks", "block_size", "lk_iterations", "reference_width",
                     "equalize_tiles", "align_half_window"),
                    _POSITIVE_INT),
    **dict.fromkeys(("pyramid_levels", "centre_iterations", "min_epipolar_tracks",
                     "reacquire_keyframes", "recover_min_tracks", "recover_keyframe_tracks"),
                    _NATURAL),
    **dict.fromkeys(("border_px", "lk_min_eigenvalue", "min_epipolar_motion_px", "flow_rel"),
                    _NON_NEGATIVE),
    **dict.fromkeys(("min_distance_px", "quality_level", "lk_epsilon", "fb_threshold_px",
                     "flow_abs_px", "ransac_threshold_px", "match_radius_px",
                     "match_radius_pnp_px", "centre_max_shift_px", "map_check_threshold_px",
                     "align_max_shift_px"),
                    _POSITIVE),
    "flow_neighbours": (lambda v: _integer(v) and v >= 2, "an integer >= 2"),
    "window_px": (lambda v: _integer(v) and v >= 5 and v % 2 == 1, "an odd integer >= 5"),
    "grid": (lambda g: isinstance(g, tuple | list) and len(g) == 2
             and all(_integer(c) and c >= 1 for c in g), "(columns, rows), integers >= 1"),
    "epipolar": (lambda v: v in ("frame", "keyframe", "both", "off"),
                 "frame, keyframe, both or off"),
    "ransac_method": (lambda v: v in ("magsac", "ransac"), "magsac or ransac"),
    "ransac_confidence": (lambda v: _number(v) and 0 < v < 1, "a number in (0, 1)"),
    "gamma_target": (lambda v: v is None or (_number(v) and 0 < v < 1),
                     "None or a number in (0, 1)"),
    **dict.fromkeys(("equalize_clip", "flow_radius_px"),
                    (lambda v: v is None or (_number(v) and v > 0), "None or a number > 0")),
    **dict.fromkeys(("min_eigen_ratio", "recover_share"),
                    (lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)")),
    "max_track_keyframes": (lambda v: v is None or (_integer(v) and v >= 2),
                            "None or an integer >= 2"),
    **dict.fromkeys(("max_deformation", "max_shear"),
                    (lambda v: v is None or (_number(v) and v > 0), "None or a number > 0")),
    "align_min_zncc": (lambda v: _number(v) and -1 <= v <= 1, "a number in [-1, 1]"),
    "match_ratio": (lambda v: _number(v) and 0 < v <= 1, "a number in (0, 1]"),
    "max_descriptor_distance": (lambda v: _integer(v) and 0 <= v <= 256,
                                "an integer in [0, 256]"),
    "min_map_points": (lambda v: _integer(v) and v >= 6, "an integer >= 6"),
}
# fmt: on
