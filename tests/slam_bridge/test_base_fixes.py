"""Frames localised against an image base become fixes (``slam_bridge.system.base_fixes``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from geoseg.reloc.localizer import QueryResult
from slam_bridge.errors import SlamError
from slam_bridge.frontend.frames import FrameList
from slam_bridge.system.base_fixes import (
    BaseConstraints,
    BaseFixConfig,
    base_constraints,
    localise_frames,
)

K = np.array([[100.0, 0, 16], [0, 100.0, 12], [0, 0, 1]])


class ScriptedLocalizer:
    """Answers each frame (its pixel value is its index) with a scripted position."""

    def __init__(self, answers: dict[int, dict], matches: dict | None = None) -> None:
        self.answers = answers
        self.matches = matches or {}
        self.asked: list[int] = []

    def localize(self, images, names=None, sequence=None):
        out = []
        for image in images:
            assert image.shape == (24, 32, 3) and image.dtype == np.uint8  # grey made RGB
            i = int(image[0, 0, 0])
            self.asked.append(i)
            position, matches = dict(self.answers[i]), self.matches.get(i, [])
            out.append(QueryResult(name=str(i), gps=None, matches=matches, position=position))
        return out


def frames(n: int = 20, dt: float = 0.1) -> FrameList:
    images = [np.full((24, 32), i, dtype=np.uint8) for i in range(n)]
    return FrameList(K, (32, 24), np.arange(n) * dt, images)


def rays(x: float, residual: float = 0.1) -> dict:
    return {"method": "ranged rays", "xyz": np.array([x, 2.0, 1.5]), "residuals_m": [residual]}


def test_one_frame_every_period_and_the_gate_decides_which_give_fixes():
    answers = {i: rays(float(i)) for i in range(20)}
    answers[5] = {"method": "best match", "xyz": np.array([50.0, 2.0, 1.5])}  # rays disagree
    answers[10] = rays(10.0, residual=5.0)  # rays agree on a point they all miss
    answers[15] = {"method": "rays", "xyz": None, "degenerate": True}  # nothing found
    localizer = ScriptedLocalizer(answers)
    fixes = localise_frames(
        frames(), "base", BaseFixConfig(every_s=0.5, batch=3), localizer=localizer
    )
    assert localizer.asked == [0, 5, 10, 15]  # every 0.5 s of a 10 Hz drive, in batches
    np.testing.assert_allclose(fixes.timestamps, [0.0, 0.5, 1.0, 1.5])
    np.testing.assert_allclose(fixes.xy[0], [0.0, 2.0])
    np.testing.assert_allclose(fixes.xy[1], [50.0, 2.0])  # the best match's position
    assert np.isnan(fixes.xy[2:]).all()  # residual too large; degenerate
    assert fixes.summary()["base_fixes"] == 2 and fixes.summary()["base_fixes_from_rays"] == 1
    strict = BaseFixConfig(every_s=0.5, best_match=False)
    fixes = localise_frames(frames(), "base", strict, localizer=ScriptedLocalizer(answers))
    assert fixes.accepted == 1 and np.isnan(fixes.xy[1]).all()


def test_fixes_enter_the_fusion_as_the_base_provider():
    answers = {i: rays(float(i)) for i in range(20)}
    fixes = localise_frames(
        frames(), "base", BaseFixConfig(every_s=0.2), localizer=ScriptedLocalizer(answers)
    )
    provider = base_constraints(fixes, BaseFixConfig(weight=0.25), interpolate_gap_s=1.0)
    assert isinstance(provider, BaseConstraints) and provider.name == "base"
    assert provider.weight == 0.25
    np.testing.assert_allclose(provider.fix_at(0.4), [4.0, 2.0])
    np.testing.assert_allclose(provider.fix_at(0.5), [5.0, 2.0])  # between two fixes
    none = {i: {"method": "best match", "xyz": None} for i in range(20)}
    nothing = localise_frames(frames(), "base", localizer=ScriptedLocalizer(none))
    assert base_constraints(nothing, BaseFixConfig(), 1.0) is None


def test_fixes_from_the_base_points_weigh_more_than_guesses():
    answers = {i: {"method": "best match", "xyz": np.array([i + 0.5, 2.0, 1.5])} for i in range(20)}
    for i in (0, 10):  # placed on the base's points
        answers[i] = {"method": "structure", "xyz": np.array([float(i), 2.0, 1.5])}
    cfg = BaseFixConfig(every_s=0.5, structure_weight=16.0, weight=0.5)
    fixes = localise_frames(frames(), "base", cfg, localizer=ScriptedLocalizer(answers))
    summary = fixes.summary()
    assert summary["base_fixes"] == 4 and summary["base_fixes_from_structure"] == 2
    provider = base_constraints(fixes, cfg, interpolate_gap_s=1.0)
    assert provider.weight_at(0.0) == 16.0 and provider.weight_at(0.5) == 0.5
    assert provider.weight_at(0.2) == 0.5  # interpolated with a guess: the lower weight
    np.testing.assert_allclose(provider.fix_at(1.0), [10.0, 2.0])
    with pytest.raises(SlamError, match="weights"):
        BaseConstraints(fixes.timestamps, fixes.xy, np.zeros(4))


class PlacingStructure:
    """Places a frame (pixel value = index) at x = its index when ``placeable`` says so."""

    def __init__(self, placeable) -> None:
        self.placeable = placeable
        self.asked: list[tuple[int, list[int]]] = []

    def locate(self, image, candidates):
        i = int(image[0, 0, 0])
        self.asked.append((i, list(candidates)))
        ok = self.placeable(i)
        t_wc = np.array([float(i), 2.0, 1.5]) if ok else None
        return SimpleNamespace(ok=ok, t_wc=t_wc)


def test_frames_between_localised_ones_are_tracked_on_the_points_where_fixes_predict():
    answers = {
        0: {"method": "structure", "xyz": np.array([0.0, 2.0, 1.5])},
        10: {"method": "best match", "xyz": np.array([10.5, 2.0, 1.5])},
    }
    matches = {0: [{"index": 0}], 10: [{"index": 5}, {"index": 6}]}
    localizer = ScriptedLocalizer(answers, matches)
    localizer.structure = PlacingStructure(lambda i: i not in (9, 11, 13))
    # base images along x every 2 m: those nearest the last fix are tried
    localizer.index = SimpleNamespace(t_wc=np.array([[2.0 * b + 0.5, 2.0, 1.5] for b in range(10)]))
    cfg = BaseFixConfig(every_s=1.0, track_every_s=0.2, track_images=2, track_max_gap_s=0.5)
    fixes = localise_frames(frames(), "base", cfg, localizer=localizer)
    assert localizer.asked == [0, 10]  # retrieval once a second only
    # the base images nearest the position the last two fixes predict (10 m/s along x),
    # then the last localised frame's matches
    assert dict(localizer.structure.asked) == {
        1: [0, 1], 3: [1, 2, 0], 5: [2, 3, 0], 7: [3, 4, 0], 9: [4, 5, 0],
        11: [5, 6],  # the fix of frame 7 is 0.4 s old: x = 11 predicted
        13: [5, 6],  # 0.6 s old: the localised frame 10's matches alone
        15: [5, 6], 17: [8, 9, 5, 6], 19: [9, 8, 5, 6],
    }  # fmt: skip
    np.testing.assert_allclose(
        fixes.timestamps, np.array([0, 1, 3, 5, 7, 9, 10, 11, 13, 15, 17, 19]) / 10
    )
    summary = fixes.summary()
    assert summary["base_fixes_from_structure"] == 8 and fixes.accepted == 9
    assert summary["base_frames_localised"] == 2 and summary["base_frames_tracked"] == 10
    np.testing.assert_allclose(fixes.xy[fixes.timestamps == 1.5], [[15.0, 2.0]])
    none = localise_frames(
        frames(), "base", BaseFixConfig(every_s=1.0, track_every_s=None),
        localizer=ScriptedLocalizer(answers, matches),
    )  # fmt: skip
    assert none.timestamps.size == 2


@pytest.mark.parametrize(
    "field, value",
    [
        ("every_s", 0.0),
        ("weight", -1.0),
        ("structure_weight", 0.0),
        ("max_residual_m", float("nan")),
        ("batch", 0),
    ],
)
def test_bad_settings_are_refused(field, value):
    with pytest.raises(SlamError, match=field):
        BaseFixConfig(**{field: value})
