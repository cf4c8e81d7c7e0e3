"""Tests for the Dirichlet false-positive filter (thesis eqs. 4.3-4.9)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from scipy.stats import dirichlet as sp_dirichlet

from geoseg.classes import BUILDING, NUM_CLASSES
from geoseg.dirichlet import (
    FORMAT_VERSION,
    DirichletFilter,
    MaxProbabilityFilter,
    dirichlet_cost,
    dirichlet_cost_grad,
    load_filter,
    sufficient_statistics,
    temper,
)
from geoseg.errors import GeosegError

ALPHAS = [
    np.array([0.3, 0.5, 5.0, 0.8, 0.2, 0.4, 0.6, 0.9]),
    np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]),
    np.array([0.15, 0.25, 12.0, 0.3, 0.5, 0.2, 0.7, 0.35]),
    np.array([2.5, 0.7]),
]


def _building_alpha() -> np.ndarray:
    a = np.full(NUM_CLASSES, 0.5)
    a[BUILDING] = 8.0
    a[3] = 2.0  # building often confused with vegetation
    return a


@pytest.mark.parametrize("alpha", [ALPHAS[0], ALPHAS[1]])
@pytest.mark.parametrize("lam", [0.0, 3.0])
def test_gradient_matches_central_differences(alpha: np.ndarray, lam: float) -> None:
    x = np.random.default_rng(1).dirichlet(alpha, size=500)
    log_t, m = sufficient_statistics(x)
    a0 = alpha * 1.3 + 0.1
    grad = dirichlet_cost_grad(a0, log_t, m, lam)
    h = 1e-6
    num = np.empty_like(a0)
    for i in range(a0.size):
        e = np.zeros_like(a0)
        e[i] = h
        num[i] = (dirichlet_cost(a0 + e, log_t, m, lam) - dirichlet_cost(a0 - e, log_t, m, lam)) / (
            2 * h
        )
    np.testing.assert_allclose(grad, num, rtol=1e-5, atol=1e-4)


def test_cost_is_negative_log_likelihood() -> None:
    alpha = ALPHAS[0]
    x = np.random.default_rng(2).dirichlet(alpha, size=200)
    x = np.clip(x, 1e-12, 1)
    x /= x.sum(axis=1, keepdims=True)
    log_t, m = sufficient_statistics(x)
    a = alpha * 0.9
    nll = -sp_dirichlet.logpdf(x.T, a).sum()
    assert dirichlet_cost(a, log_t, m, lam=0.0) == pytest.approx(nll, rel=1e-10)


@pytest.mark.parametrize("alpha", ALPHAS)
def test_recovers_known_alpha(alpha: np.ndarray) -> None:
    x = np.random.default_rng(0).dirichlet(alpha, size=100_000)
    f = DirichletFilter(num_classes=alpha.size, building_class=0).fit(x)
    rel = np.abs(f.alpha / alpha - 1.0)
    assert rel.max() < 0.05, (f.alpha, alpha)


def test_fit_float32_inputs_and_fast() -> None:
    alpha = _building_alpha()
    x = np.random.default_rng(0).dirichlet(alpha, size=200_000).astype(np.float32)
    t0 = time.perf_counter()
    f = DirichletFilter().fit(x)
    assert time.perf_counter() - t0 < 5.0
    assert np.abs(f.alpha / alpha - 1).max() < 0.05


def test_log_density_matches_scipy() -> None:
    alpha = ALPHAS[1]
    x = np.random.default_rng(3).dirichlet(alpha, size=50)
    f = DirichletFilter(alpha=alpha)
    np.testing.assert_allclose(f.log_density(x), sp_dirichlet.logpdf(x.T, alpha), rtol=1e-10)
    # (H, W, K) input keeps the spatial shape
    assert f.log_density(x[:48].reshape(6, 8, 8)).shape == (6, 8)


@pytest.mark.parametrize("cls", [DirichletFilter, MaxProbabilityFilter])
def test_threshold_gives_requested_false_rejection(cls) -> None:
    alpha = _building_alpha()
    rng = np.random.default_rng(4)
    train = rng.dirichlet(alpha, size=20_000)
    calib = rng.dirichlet(alpha, size=20_000)
    held_out = rng.dirichlet(alpha, size=20_000)
    f = cls().fit(train)
    for rate in (0.05, 0.15, 0.3):
        f.threshold_for_false_rejection(calib, rate)
        # exact on the calibration set itself (score > threshold is kept)
        assert np.mean(f.score(calib) <= f.threshold) == pytest.approx(rate, abs=1e-4)
        # close on held-out samples of the same distribution
        assert np.mean(f.score(held_out) <= f.threshold) == pytest.approx(rate, abs=0.015)


def test_filter_keeps_building_pixels_and_drops_confused_ones() -> None:
    f = DirichletFilter(alpha=_building_alpha())
    rng = np.random.default_rng(5)
    f.threshold_for_false_rejection(rng.dirichlet(_building_alpha(), size=5000), 0.1)
    # a building-argmax pixel confusing building with sky (not the learned confusion)
    bad = np.full(NUM_CLASSES, 0.015)
    bad[BUILDING], bad[6] = 0.46, 0.45
    good = np.full(NUM_CLASSES, 0.01)
    good[BUILDING], good[3] = 0.8, 0.14
    other = np.full(NUM_CLASSES, 0.01)
    other[0] = 0.93
    probs = np.stack([bad, good, other, good]).reshape(2, 2, NUM_CLASSES)
    keep = f.filter(probs)
    assert keep.shape == (2, 2) and keep.dtype == bool
    np.testing.assert_array_equal(keep, [[False, True], [False, True]])
    # explicit labels override the argmax
    labels = np.full((2, 2), BUILDING)
    labels[1, 1] = 0
    np.testing.assert_array_equal(f.filter(probs, labels), [[False, True], [False, False]])
    # the baseline keeps the confused pixel at a threshold that keeps the good one
    base = MaxProbabilityFilter()
    base.threshold = 0.45
    assert base.filter(probs).tolist() == [[True, True], [False, True]]


def test_point_rule_mean_and_weight() -> None:
    alpha = _building_alpha()
    f = DirichletFilter(alpha=alpha)
    rng = np.random.default_rng(6)
    f.threshold_for_false_rejection(rng.dirichlet(alpha, size=5000), 0.1)
    obs = rng.dirichlet(alpha, size=(5, 3))  # 5 points, 3 observations each
    res = f.classify_points(obs)
    mean = obs.mean(axis=1)
    np.testing.assert_allclose(res.mean_probs, mean)
    np.testing.assert_allclose(res.score, f.log_density(mean))
    np.testing.assert_allclose(res.weight, np.exp(f.log_density(mean)))
    np.testing.assert_array_equal(res.is_building, f.log_density(mean) > f.threshold)
    assert ((res.normalized_weight >= 0) & (res.normalized_weight <= 1)).all()
    # ragged observation counts
    ragged = f.classify_points([obs[0], obs[1, :1], obs[2, :2]])
    np.testing.assert_allclose(ragged.mean_probs[1], obs[1, 0])
    np.testing.assert_allclose(ragged.mean_probs[2], obs[2, :2].mean(axis=0))


@pytest.mark.parametrize("cls", [DirichletFilter, MaxProbabilityFilter])
def test_save_load_round_trip(tmp_path, cls) -> None:
    alpha = _building_alpha()
    x = np.random.default_rng(7).dirichlet(alpha, size=3000)
    f = cls().fit(x)
    f.threshold_for_false_rejection(x, 0.2)
    path = f.save(tmp_path / "sub" / "filter.json")
    g = cls.load(path)
    h = load_filter(path)
    assert type(g) is cls and type(h) is cls
    assert g.threshold == f.threshold
    np.testing.assert_array_equal(g.score(x), f.score(x))
    np.testing.assert_array_equal(g.filter(x), f.filter(x))
    np.testing.assert_array_equal(g.calibration, f.calibration)
    assert json.loads(path.read_text())["version"] == FORMAT_VERSION


def test_load_errors(tmp_path) -> None:
    f = DirichletFilter(alpha=_building_alpha())
    path = f.save(tmp_path / "f.json")
    data = json.loads(path.read_text())
    with pytest.raises(GeosegError, match="max_probability"):
        MaxProbabilityFilter.load(path)
    for key, value, msg in [
        ("version", 99, "version"),
        ("format", "other", "format"),
        ("kind", "nope", "kind"),
        ("alpha", [1.0, -1.0], "alpha"),
    ]:
        bad = dict(data, **{key: value})
        p = tmp_path / f"bad_{key}.json"
        p.write_text(json.dumps(bad))
        with pytest.raises(GeosegError, match=msg):
            load_filter(p)
    (tmp_path / "garbage.json").write_text("{not json")
    with pytest.raises(GeosegError, match="garbage.json"):
        load_filter(tmp_path / "garbage.json")
    with pytest.raises(GeosegError, match="no such"):
        load_filter(tmp_path / "missing.json")


def test_bad_inputs() -> None:
    alpha = _building_alpha()
    good = np.random.default_rng(8).dirichlet(alpha, size=10)
    f = DirichletFilter()
    with pytest.raises(GeosegError, match="not fitted"):
        f.log_density(good)
    f.fit(np.random.default_rng(9).dirichlet(alpha, size=1000))
    with pytest.raises(GeosegError, match="threshold"):
        f.filter(good)
    nan = good.copy()
    nan[0, 0] = np.nan
    neg = good.copy()
    neg[0, 0], neg[0, 1] = -0.1, neg[0, 1] + 0.1 + neg[0, 0]
    unnorm = good * 1.5
    for bad, msg in [
        (nan, "NaN"),
        (neg, ">= 0"),
        (unnorm, "sum to 1"),
        (good[:, :5], "K = 8"),
        (good.astype(int), "floating"),
    ]:
        with pytest.raises(GeosegError, match=msg):
            f.log_density(bad)
        with pytest.raises(GeosegError, match=msg):
            DirichletFilter().fit(bad)
    f.threshold = 0.0
    with pytest.raises(GeosegError, match="labels"):
        f.filter(good, np.zeros(3, dtype=int))
    with pytest.raises(GeosegError, match="rate"):
        f.threshold_for_false_rejection(good, 1.5)
    with pytest.raises(GeosegError):
        DirichletFilter(building_class=8)
    with pytest.raises(GeosegError, match="point_probs"):
        f.classify_points(good)  # (N, K) is not (N, V, K)


def test_fit_statistics_matches_fit_streaming() -> None:
    alpha = _building_alpha()
    x = np.random.default_rng(10).dirichlet(alpha, size=20_000)
    lt1, m1 = sufficient_statistics(x[:7000])
    lt2, m2 = sufficient_statistics(x[7000:])
    streamed = DirichletFilter().fit_statistics(lt1 + lt2, m1 + m2)
    direct = DirichletFilter().fit(x)
    np.testing.assert_allclose(streamed.alpha, direct.alpha, rtol=1e-5)
    with pytest.raises(GeosegError, match="log_t"):
        DirichletFilter().fit_statistics(np.ones(NUM_CLASSES), 10)
    with pytest.raises(GeosegError, match="m:"):
        DirichletFilter().fit_statistics(lt1, 1)


def test_dirichlet_beats_max_probability_at_same_false_rejection() -> None:
    """Building/road confusions (fig. 4.7 (b)) are caught by the shape of the distribution."""
    rng = np.random.default_rng(0)
    a_true = np.full(NUM_CLASSES, 0.5)
    a_true[BUILDING], a_true[3] = 8.0, 3.0  # true buildings: confused with vegetation
    a_fp = np.full(NUM_CLASSES, 0.5)
    a_fp[BUILDING], a_fp[0] = 8.0, 3.0  # false positives: road pixels called building
    true = rng.dirichlet(a_true, size=30_000)
    true = true[true.argmax(1) == BUILDING]
    fp = rng.dirichlet(a_fp, size=10_000)
    fp = fp[fp.argmax(1) == BUILDING]
    train, calib, test = np.array_split(true, 3)
    removed = {}
    for cls in (DirichletFilter, MaxProbabilityFilter):
        f = cls().fit(train)
        f.threshold_for_false_rejection(calib, 0.15)
        assert 1 - f.filter(test).mean() == pytest.approx(0.15, abs=0.02)
        removed[cls.kind] = 1 - f.filter(fp).mean()
    assert removed["dirichlet"] > 0.6
    assert removed["dirichlet"] > 2 * removed["max_probability"]


def test_temper_is_the_softmax_of_scaled_logits() -> None:
    logits = np.random.default_rng(3).normal(0.0, 4.0, size=(50, NUM_CLASSES))
    probs = np.exp(logits - logits.max(1, keepdims=True))
    probs /= probs.sum(1, keepdims=True)
    for t in (0.5, 1.0, 4.0):
        expected = np.exp(logits / t - (logits / t).max(1, keepdims=True))
        expected /= expected.sum(1, keepdims=True)
        np.testing.assert_allclose(temper(probs, t), expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(temper(probs, 4.0).argmax(1), probs.argmax(1))
    for bad in (0.0, -1.0, float("nan"), True):
        with pytest.raises(GeosegError, match="temperature"):
            temper(probs, bad)
        with pytest.raises(GeosegError, match="temperature"):
            DirichletFilter(temperature=bad)


def test_tempered_filter_recovers_alpha_and_round_trips(tmp_path) -> None:
    """Vectors sharpened by 1/T are modelled, at temperature T, by the Dirichlet they came from."""
    alpha = ALPHAS[0]
    x = np.random.default_rng(11).dirichlet(alpha, size=100_000)
    sharp = temper(x, 1.0 / 3.0)  # what an over-confident network would output
    f = DirichletFilter(temperature=3.0).fit(sharp)
    np.testing.assert_allclose(f.alpha, alpha, rtol=0.05)
    rows = x[:500].min(1) > 1e-9  # cubes of smaller values fall under the eps floor
    np.testing.assert_allclose(
        f.log_density(sharp[:500][rows]), sp_dirichlet(f.alpha).logpdf(x[:500][rows].T), rtol=1e-6
    )
    lt, m = sufficient_statistics(sharp, temperature=3.0)
    streamed = DirichletFilter(temperature=3.0).fit_statistics(lt, m)
    np.testing.assert_allclose(streamed.alpha, f.alpha, rtol=1e-5)
    f.threshold_for_false_rejection(sharp[:2000], 0.1)
    loaded = load_filter(f.save(tmp_path / "tempered.json"))
    assert loaded.temperature == 3.0
    np.testing.assert_allclose(loaded.score(sharp[:100]), f.score(sharp[:100]))


def _road_patch_with_building_pixel() -> np.ndarray:
    """``(7, 7, K)`` map: confident road everywhere except one weak building pixel at (3, 3)."""
    road, weak = np.full(NUM_CLASSES, 0.02), np.full(NUM_CLASSES, 0.02)
    road[0] = 1.0 - 0.02 * (NUM_CLASSES - 1)
    weak[0] = 0.30
    weak[BUILDING] = 1.0 - weak[0] - 0.02 * (NUM_CLASSES - 2)
    probs = np.tile(road, (7, 7, 1))
    probs[3, 3] = weak
    return probs


@pytest.mark.parametrize("cls", [DirichletFilter, MaxProbabilityFilter])
def test_window_smooths_box_means_and_round_trips(tmp_path, cls) -> None:
    probs = _road_patch_with_building_pixel()
    assert probs[3, 3].argmax() == BUILDING
    f = cls(window=3, **({"alpha": _building_alpha()} if cls is DirichletFilter else {}))
    smooth = f.smooth(probs)
    np.testing.assert_allclose(smooth[3, 3], (8 * probs[0, 0] + probs[3, 3]) / 9)
    np.testing.assert_allclose(smooth[0, 0], probs[0, 0])  # edge pixels repeat: all road
    np.testing.assert_allclose(smooth.sum(-1), 1.0)
    batch = f.smooth(np.stack([probs, probs[::-1]]))  # leading axes are frames
    np.testing.assert_allclose(batch[0], smooth)
    np.testing.assert_allclose(batch[1], smooth[::-1])
    np.testing.assert_array_equal(cls().smooth(probs), probs)  # window 1: per pixel
    one_hot = np.eye(NUM_CLASSES)[np.random.default_rng(0).integers(0, NUM_CLASSES, (9, 9))]
    assert (f.smooth(one_hot) >= 0).all()  # exact zeros stay valid probabilities
    # the lone building pixel passes per pixel but not once its road neighbourhood counts
    scores = f.score(np.stack([smooth[3, 3], probs[3, 3]]))
    assert scores[0] < scores[1]
    f.threshold = thr = float(scores.mean())
    per_pixel = cls(**({"alpha": _building_alpha()} if cls is DirichletFilter else {}))
    per_pixel.threshold = thr
    assert per_pixel.filter(probs)[3, 3] and per_pixel.filter(probs).sum() == 1
    assert not f.filter(probs).any()
    loaded = load_filter(f.save(tmp_path / "w.json"))
    assert loaded.window == 3
    np.testing.assert_array_equal(loaded.filter(probs), f.filter(probs))
    for bad in (0, 2, -1, 1.0, True):
        with pytest.raises(GeosegError, match="window"):
            cls(window=bad)
    with pytest.raises(GeosegError, match="H, W, K"):
        f.smooth(probs[0])


@pytest.mark.parametrize("window", [1, 3, 5])
def test_smooth_at_equals_the_smoothed_map_at_the_pixels(window: int) -> None:
    rng = np.random.default_rng(window)
    probs = rng.dirichlet(np.ones(NUM_CLASSES), size=(7, 9)).astype(np.float32)
    f = MaxProbabilityFilter(window=window)
    rows, cols = np.array([0, 3, 6, 6, 2]), np.array([0, 4, 8, 0, 8])  # corners and edges
    np.testing.assert_allclose(f.smooth_at(probs, rows, cols), f.smooth(probs)[rows, cols])
    assert f.smooth_at(probs, rows[:0], cols[:0]).shape == (0, NUM_CLASSES)
    with pytest.raises(GeosegError, match="outside"):
        f.smooth_at(probs, np.array([7]), np.array([0]))
    with pytest.raises(GeosegError, match="differ"):
        f.smooth_at(probs, rows, cols[:2])
    with pytest.raises(GeosegError, match="H, W, K"):
        f.smooth_at(probs[0], rows, cols)
    bad = probs.copy()
    bad[3, 4, 0] = np.nan
    with pytest.raises(GeosegError, match="NaN"):
        f.smooth_at(bad, rows, cols)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("threshold", float("nan"), "threshold: expected a finite number"),
        ("threshold", float("inf"), "threshold: expected a finite number"),
        ("threshold", "8", "threshold: expected a finite number"),
        ("threshold", True, "threshold: expected a finite number"),
        ("calibration", [0.0, float("nan"), 1.0], "calibration"),
        ("calibration", [2.0, 1.0], "non-decreasing"),
        ("calibration", "quantiles", "calibration"),
        ("window", 8.9, "window: expected an integer"),
        ("window", True, "window: expected an integer"),
        ("window", "8", "window: expected an integer"),
        ("window", 4, "window"),
        ("num_classes", 8.0, "num_classes: expected an integer"),
        ("building_class", True, "building_class: expected an integer"),
        ("building_class", 9, "building_class"),
        ("alpha", [1.0] * 7, "alpha: expected 8 numbers"),
        ("alpha", [1.0] * 7 + [float("nan")], "alpha"),
        ("alpha", [1.0] * 7 + ["2"], "alpha"),
        ("lam", float("inf"), "lam"),
        ("eps", float("nan"), "eps"),
        ("temperature", 0, "temperature"),
        ("temperature", None, "temperature"),
        ("version", True, "version"),
        ("extra_key", 1, "unknown key"),
    ],
)
def test_every_field_of_a_filter_file_is_type_checked(tmp_path, key, value, message) -> None:
    """NaN thresholds (which reject every pixel), NaN calibrations (NaN weights) and coerced
    values (8.9, true, "8") are refused on load, naming the file and the field."""
    f = DirichletFilter(alpha=_building_alpha())
    f.threshold_for_false_rejection(np.random.default_rng(0).dirichlet(_building_alpha(), 500), 0.1)
    data = json.loads(f.save(tmp_path / "f.json").read_text())
    data[key] = value
    data.pop("sha256")  # a hand-edited file: only the field checks speak
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(data))
    with pytest.raises(GeosegError, match=message) as info:
        load_filter(path)
    assert "edited.json" in str(info.value)


def test_a_threshold_given_at_call_time_must_be_finite() -> None:
    f = DirichletFilter(alpha=_building_alpha())
    probs = np.random.default_rng(0).dirichlet(_building_alpha(), 10)
    with pytest.raises(GeosegError, match="threshold"):
        f.filter(probs, threshold=float("nan"))
