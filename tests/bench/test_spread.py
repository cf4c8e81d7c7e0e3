"""A bench's figures over renders (``bench/spread.py``): means, sample stds, per-render values,
shared settings and figures a render could not measure."""

import importlib.util
import math
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _over_renders():
    spec = importlib.util.spec_from_file_location("spread", ROOT / "bench" / "spread.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.over_renders


def test_mean_std_and_every_render_value():
    renders = {
        "1": {"recall": 0.8, "k": 3, "moved": 1.0, "method": "rays", "lost": float("nan")},
        "2": {"recall": 0.9, "k": 3, "moved": 2.0, "method": "rays", "lost": 0.5},
        "3": {"recall": 1.0, "k": 3, "moved": 3.0, "method": "rays", "lost": 1.5},
    }
    res = _over_renders()(renders, spread=["recall", "lost"])
    assert res["recall"] == pytest.approx(0.9)
    assert res["recall_std"] == pytest.approx(0.1)  # sample std (n - 1)
    assert res["per_render"]["recall"] == [0.8, 0.9, 1.0]
    assert res["k"] == 3 and "k" not in res["per_render"]  # a setting: one value
    assert res["moved"] == 2.0 and "moved_std" not in res  # no spread asked: the mean
    assert res["per_render"]["moved"] == [1.0, 2.0, 3.0]
    assert res["method"] == "rays"
    # a NaN is a figure that render could not measure: left out of the mean, null per render
    assert res["lost"] == pytest.approx(1.0)
    assert res["lost_std"] == pytest.approx(math.sqrt(0.5))
    assert res["per_render"]["lost"] == [None, 0.5, 1.5]
    assert list(res)[:2] == ["recall", "recall_std"]  # the std beside its figure


def test_one_render_has_no_spread():
    res = _over_renders()({"1": {"recall": 0.8}}, spread=["recall"])
    assert res["recall"] == 0.8 and res["recall_std"] == 0.0
