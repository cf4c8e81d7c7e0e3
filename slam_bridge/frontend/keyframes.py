"""When a tracked frame becomes a keyframe.

The rule, checked after every tracked frame (the first frame is always a keyframe, and a frame is
never a keyframe twice since each frame is tracked once):

1. **spacing** (when the caller gives ``distance(t0, t1) -> metres``, built from wheel odometry
   or GPS): the distance driven since the last keyframe reaches ``spacing_m``;
   **parallax** (without it): the median image displacement, since the last keyframe, of the
   tracks that the last keyframe holds reaches ``parallax_px`` (pixels at ``reference_width``,
   scaled by ``W / reference_width``; rotation counts too: it is a flow, not a
   rotation-compensated parallax);
2. **tracks**: the share of the last keyframe's tracks still tracked falls below
   ``min_tracked_share`` (whichever mode: the map must get a keyframe before its tracks are gone);
   **scarce**: their number falls below ``min_tracked`` while some of them were lost since the
   last keyframe. Where few tracks live long (open, nearly featureless ground at the edge of
   town, the near road racing past), the share rule waits for the spacing while the few tracks
   that continue from keyframe to keyframe die: the map then gets neither enough tracks shared
   by consecutive keyframes (the loop's two-view bridge needs 15) nor new points before the old
   ones leave the view. A keyframe as soon as they become scarce keeps both (at the cost of
   keyframes only where tracks are scarce; a stopped vehicle loses no track, so makes none);
3. **turn**: the tracker's constant-velocity prediction failed and its recovery found the
   tracks again (:mod:`slam_bridge.frontend.motion`): the image moves abruptly (a sharp turn,
   tens of degrees a frame), the view changes within a few frames, and the tracks shared with
   the last keyframe would be gone before the spacing is driven;
4. **gap**: ``max_frame_gap`` frames since the last keyframe (None: no limit).

A stopped vehicle thus makes keyframes only through rule 3 (spacing mode) or when its view
changes (parallax mode, rule 2).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from slam_bridge.errors import SlamError

__all__ = ["KeyframeConfig", "KeyframeRule"]

DistanceFn = Callable[[float, float], float]


@dataclass
class KeyframeConfig:
    """The keyframe rule (module docstring).

    Attributes:
        spacing_m: metres driven between keyframes, when a distance callable is given.
        parallax_px: median track displacement since the last keyframe, pixels at
            ``reference_width`` (without a distance callable).
        min_tracked_share: a keyframe when fewer than this share of the last keyframe's tracks
            remain.
        min_tracked: a keyframe when fewer than this many of the last keyframe's tracks remain
            and at least one of them was lost since (0: off).
        max_frame_gap: a keyframe at the latest this many frames after the last (None: never
            forced).
        reference_width: image width at which ``parallax_px`` is given.
    """

    spacing_m: float = 2.0
    parallax_px: float = 24.0
    min_tracked_share: float = 0.6
    min_tracked: int = 50
    max_frame_gap: int | None = 10
    reference_width: int = 640

    def __post_init__(self) -> None:
        for key in ("spacing_m", "parallax_px", "reference_width"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
                raise SlamError(f"KeyframeConfig.{key}: expected a number > 0, got {value!r}")
        if not 0.0 <= self.min_tracked_share <= 1.0:
            raise SlamError(
                f"KeyframeConfig.min_tracked_share: expected a share in [0, 1], got "
                f"{self.min_tracked_share!r}"
            )
        n = self.min_tracked
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise SlamError(f"KeyframeConfig.min_tracked: expected an integer >= 0, got {n!r}")
        gap = self.max_frame_gap
        if gap is not None and (isinstance(gap, bool) or not isinstance(gap, int) or gap < 1):
            raise SlamError(
                f"KeyframeConfig.max_frame_gap: expected an integer >= 1 or None, got {gap!r}"
            )


class KeyframeRule:
    """Decides whether a tracked frame is a keyframe (module docstring).

    Args:
        config: the thresholds.
        image_width: ``W`` of the images (scales ``parallax_px``).
        distance: optional ``distance(t0, t1) -> metres`` driven between two timestamps.
    """

    def __init__(
        self, config: KeyframeConfig, image_width: int, distance: DistanceFn | None = None
    ) -> None:
        self.config = config
        self.distance = distance
        self.parallax_px = config.parallax_px * image_width / config.reference_width

    def decide(
        self,
        frame_gap: int,
        t_keyframe: float,
        t_frame: float,
        tracked_share: float,
        median_flow_px: float,
        tracked: int | None = None,
        lost: int = 0,
        turned: bool = False,
    ) -> str | None:
        """The reason this frame is a keyframe, or None.

        Args:
            frame_gap: frames since the last keyframe (>= 1).
            t_keyframe: the last keyframe's timestamp.
            t_frame: this frame's timestamp.
            tracked_share: share of the last keyframe's tracks still tracked (0 when it had
                none).
            median_flow_px: median displacement of those tracks since the last keyframe
                (NaN when none is left).
            tracked: how many of the last keyframe's tracks are still tracked (None: the
                ``scarce`` rule is not checked).
            lost: how many of them were lost since the last keyframe.
            turned: the tracker recovered from a failed prediction at this frame.

        Returns:
            ``"spacing"``, ``"parallax"``, ``"tracks"``, ``"scarce"``, ``"turn"``, ``"gap"`` or
            None.
        """
        if frame_gap < 1:
            return None
        cfg = self.config
        if self.distance is not None:
            d = float(self.distance(t_keyframe, t_frame))
            if not d == d:  # NaN: no odometry here; fall back on the image
                if median_flow_px >= self.parallax_px:
                    return "parallax"
            elif d >= cfg.spacing_m:
                return "spacing"
        elif median_flow_px >= self.parallax_px:
            return "parallax"
        if tracked_share < cfg.min_tracked_share:
            return "tracks"
        if tracked is not None and tracked < cfg.min_tracked and lost > 0:
            return "scarce"
        if turned:
            return "turn"
        if cfg.max_frame_gap is not None and frame_gap >= cfg.max_frame_gap:
            return "gap"
        return None
