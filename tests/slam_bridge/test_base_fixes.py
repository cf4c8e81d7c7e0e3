"""Frames localised against an image base become fixes (``slam_bridge.system.base_fixes``)."""

from __future__ import annotations

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

    def __init__(self, answers: dict[int, dict]) -> None:
        self.answers = answers
        self.asked: list[int] = []

    def localize(self, images, names=None, sequence=None):
        out = []
        for image in images:
            assert image.shape == (24, 32, 3) and image.dtype == np.uint8  # grey made RGB
            i = int(image[0, 0, 0])
            self.asked.append(i)
            out.append(QueryResult(name=str(i), gps=None, position=dict(self.answers[i])))
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


@pytest.mark.parametrize(
    "field, value",
    [("every_s", 0.0), ("weight", -1.0), ("max_residual_m", float("nan")), ("batch", 0)],
)
def test_bad_settings_are_refused(field, value):
    with pytest.raises(SlamError, match=field):
        BaseFixConfig(**{field: value})
