"""Held-out evaluation (training.evaluate_seg), its panels (training.figures) and
bench/accuracy_seg.py, on 64x48 frames of the evaluation city, 2 frames, stub or random models."""

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from geoseg.classes import BUILDING, IGNORE_INDEX, NUM_CLASSES, ROAD
from geoseg.data.synthetic import EVAL_SEEDS, HELDOUT_CONDITIONS
from geoseg.dirichlet import DirichletFilter, MaxProbabilityFilter
from geoseg.errors import GeosegError
from geoseg.infer import SegmentationResult, save_model_checkpoint
from geoseg.models.registry import get_model
from training import evaluate_seg as ev
from training import figures

ROOT = Path(__file__).resolve().parents[2]
SIZE = (48, 64)


def _load_bench():
    spec = importlib.util.spec_from_file_location("accuracy_seg", ROOT / "bench/accuracy_seg.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _uint8(image: torch.Tensor) -> np.ndarray:
    return (image * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()


@pytest.fixture(scope="module")
def cfg(tmp_path_factory) -> ev.EvalConfig:
    cache = tmp_path_factory.mktemp("eval_cache")
    return ev.EvalConfig(frames=2, size=SIZE, cache_dir=cache, panel_frames=2, progress=False)


@pytest.fixture(scope="module")
def heldout(cfg):
    dataset = ev.heldout_dataset(cfg)
    indices = ev.heldout_indices(dataset, cfg.frames)
    samples = {i: dataset[i] for i in indices}
    return dataset, indices, samples


class Stub:
    """A "model" answering from the ground truth of the frame it is shown, optionally edited."""

    def __init__(self, samples, edit=None):
        self.by_image = {_uint8(s["image"]).tobytes(): (i, s) for i, s in samples.items()}
        self.edit = edit

    def __call__(self, images: np.ndarray) -> SegmentationResult:
        probs, normals = [], []
        for img in images:
            i, s = self.by_image[img.tobytes()]
            lab = s["labels"].numpy().copy()
            nrm = s["normals"].numpy().copy()
            p = np.eye(NUM_CLASSES, dtype=np.float32)[np.where(lab == IGNORE_INDEX, 0, lab)]
            p = p.transpose(2, 0, 1)
            if self.edit is not None:
                p, nrm = self.edit(i, s, p, nrm)
            probs.append(p)
            normals.append(nrm)
        probs = np.stack(probs).astype(np.float32)
        return SegmentationResult(
            probabilities=probs, labels=probs.argmax(1).astype(np.uint8), normals=np.stack(normals)
        )


def _rotate(normals: np.ndarray, mask: np.ndarray, deg: float) -> np.ndarray:
    """Turn the normals `(3, H, W)` under ``mask`` by exactly ``deg`` degrees."""
    out = normals.copy()
    n = normals[:, mask].T.astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    u = np.cross(n, np.array([0.31, 0.52, 0.8]))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    t = np.radians(deg)
    out[:, mask] = (np.cos(t) * n + np.sin(t) * u).T.astype(np.float32)
    return out


def _hand_iou(pairs) -> tuple[float, np.ndarray]:
    cm = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    for pred, lab in pairs:
        keep = lab != IGNORE_INDEX
        np.add.at(cm, (lab[keep], pred[keep]), 1)
    tp = np.diag(cm).astype(float)
    union = cm.sum(0) + cm.sum(1) - tp
    iou = np.where(union > 0, tp / np.maximum(union, 1), np.nan)
    return float(np.nanmean(iou)), iou


# ----------------------------------------------------------------------------- data
def test_heldout_frames_are_the_unseen_city_with_the_unseen_condition(heldout):
    dataset, indices, samples = heldout
    assert list(dataset.config.seeds) == list(EVAL_SEEDS) and len(indices) == 2
    conditions = [samples[i]["condition"] for i in indices]
    assert conditions[0] in HELDOUT_CONDITIONS and conditions[1] not in HELDOUT_CONDITIONS
    more = ev.heldout_indices(dataset, 12)
    assert len(set(more)) == 12 and more[:2] == indices  # deterministic, balanced prefix
    assert len({dataset.spec(i).condition for i in more}) == len(dataset.config.conditions)


def test_config_and_argument_errors(cfg, heldout):
    with pytest.raises(GeosegError, match="frames"):
        ev.EvalConfig(frames=0)
    with pytest.raises(GeosegError, match="at least one"):
        ev.evaluate(cfg)
    dataset, indices, samples = heldout
    with pytest.raises(GeosegError, match="naive/dirichlet"):
        ev.evaluate(cfg, naive=Stub(samples), dataset=dataset, indices=indices)


# ----------------------------------------------------------------------------- planted predictions
def test_perfect_predictor_scores_perfectly(cfg, heldout):
    dataset, indices, samples = heldout
    stub = Stub(samples)
    fig = ev.evaluate(cfg, seg=stub, normals=stub, dataset=dataset, indices=indices).figures
    assert fig["miou"] == pytest.approx(1.0) and fig["building_iou"] == pytest.approx(1.0)
    assert fig["miou_heldout_condition"] == pytest.approx(1.0)
    assert fig["normals_building_mean_deg"] < 0.05
    assert fig["normals_building_median_deg"] <= 0.05  # histogram median: half a 0.05 bin
    assert fig["normals_building_within_11_25"] == 1.0 and fig["normals_all_within_30"] == 1.0
    assert fig["frames"] == 2 and fig["frames_heldout_condition"] == 1
    assert ev.check_targets(fig)["miou"] is True


def test_planted_errors_match_hand_computed_metrics(cfg, heldout):
    dataset, indices, samples = heldout
    w = SIZE[1]

    def edit(i, s, p, nrm):
        lab = s["labels"].numpy()
        left = (lab == BUILDING) & (np.arange(w)[None, :] < w // 3)
        p = p.copy()
        p[:, left] = 0.0
        p[ROAD, left] = 1.0  # left-third building pixels called road
        build = (lab == BUILDING) & (np.linalg.norm(nrm, axis=0) > 0.5)
        return p, _rotate(nrm, build, 10.0 if i == indices[0] else 20.0)

    stub = Stub(samples, edit)
    fig = ev.evaluate(cfg, seg=stub, normals=stub, dataset=dataset, indices=indices).figures

    pairs, counts = [], []
    for i in indices:
        lab = samples[i]["labels"].numpy()
        pred = np.where(lab == IGNORE_INDEX, 0, lab)
        pred[(lab == BUILDING) & (np.arange(w)[None, :] < w // 3)] = ROAD
        pairs.append((pred, lab))
        counts.append(
            int(((lab == BUILDING) & (samples[i]["normals"].norm(dim=0) > 0.5).numpy()).sum())
        )
    miou, iou = _hand_iou(pairs)
    assert 0 < iou[BUILDING] < 1
    assert fig["miou"] == pytest.approx(miou) and fig["building_iou"] == pytest.approx(
        iou[BUILDING]
    )
    held_miou, _ = _hand_iou(pairs[:1])  # the first frame is the held-out condition's
    assert fig["miou_heldout_condition"] == pytest.approx(held_miou)
    n10, n20 = counts
    assert fig["normals_building_pixels"] == n10 + n20
    assert fig["normals_building_mean_deg"] == pytest.approx(
        (10 * n10 + 20 * n20) / (n10 + n20), abs=1e-3
    )
    assert fig["normals_building_median_deg"] == pytest.approx(10.0 if n10 > n20 else 20.0, abs=0.1)
    assert fig["normals_building_within_11_25"] == pytest.approx(n10 / (n10 + n20))
    assert fig["normals_building_within_22_5"] == 1.0


def test_planted_filter_case_matches_hand_counts(cfg, heldout):
    """Three planted groups: A (road pixels, flat distribution), B (road pixels, confident but
    odd distribution) are building false positives; C (left-quarter building pixels, unsure) are
    true building pixels the Dirichlet filter rejects. The filter removes A and B and rejects C;
    the max-probability threshold rejecting as many true pixels removes A only."""
    dataset, indices, samples = heldout
    w = SIZE[1]
    groups = {"A": 0, "B": 0, "C": 0, "n_building": 0}
    vec = {
        "tb": np.r_[[0.01] * 2, 0.93, [0.01] * 5],
        "A": np.r_[[0.1] * 2, 0.3, [0.1] * 5],
        "B": np.r_[0.05, 1e-12, 0.95, [1e-12] * 5],
        "C": np.r_[[0.01] * 2, 0.5, 0.44, [0.01] * 4],
    }

    def masks(lab):
        cols = np.arange(w)[None, :]
        road = lab == ROAD
        return {
            "A": road & (cols % 2 == 0),
            "B": road & (cols % 2 == 1),
            "C": (lab == BUILDING) & (cols < w // 4),
            "tb": (lab == BUILDING) & (cols >= w // 4),
        }

    def edit(i, s, p, nrm):
        p = p.copy()
        for g, m in masks(s["labels"].numpy()).items():
            p[:, m] = vec[g].astype(np.float32)[:, None]
        return p / p.sum(0, keepdims=True), nrm

    for i in indices:
        lab = samples[i]["labels"].numpy()
        for g, m in masks(lab).items():
            if g in groups:
                groups[g] += int(m.sum())
        groups["n_building"] += int((lab == BUILDING).sum())
    assert min(groups.values()) > 0

    dirichlet = DirichletFilter(alpha=[2, 2, 50, 2, 2, 2, 2, 2])
    scores = {g: float(dirichlet.score(v[None])[0]) for g, v in vec.items()}
    assert max(scores["A"], scores["B"], scores["C"]) < scores["tb"]
    dirichlet.threshold = (max(scores["A"], scores["B"], scores["C"]) + scores["tb"]) / 2
    maxprob = MaxProbabilityFilter()
    maxprob.threshold = 0.96
    stub = Stub(samples, edit)
    fig = ev.evaluate(
        cfg, naive=stub, dirichlet=dirichlet, maxprob=maxprob, dataset=dataset, indices=indices
    ).figures

    assert fig["filter_fp_argmax"] == groups["A"] + groups["B"]
    assert fig["filter_building_pixels"] == groups["n_building"]
    assert fig["dirichlet_fp_removed"] == pytest.approx(1.0)
    assert fig["dirichlet_extra_false_rejections"] == pytest.approx(
        groups["C"] / groups["n_building"]
    )
    assert fig["maxprob_extra_false_rejections_same"] == pytest.approx(
        fig["dirichlet_extra_false_rejections"]
    )
    assert fig["maxprob_fp_removed_same_rejections"] == pytest.approx(
        groups["A"] / (groups["A"] + groups["B"])
    )
    assert fig["filter_winner"] == "dirichlet"
    assert fig["maxprob_fp_removed_calibrated"] == pytest.approx(1.0)  # 0.96 rejects everything
    assert fig["maxprob_extra_false_rejections_calibrated"] == pytest.approx(1.0)


# ----------------------------------------------------------------------------- records
def _card(run: Path, *, minutes: float, size, frames: int, epochs: int = 3, init=None) -> None:
    run.mkdir(parents=True, exist_ok=True)
    card = {"train_minutes": minutes, "epochs": epochs, "config": {"init_checkpoint": init},
            "data": {"size_hw": list(size), "train": {"frames": frames}}}  # fmt: skip
    (run / "model_card.json").write_text(json.dumps(card))


def test_training_records_and_untrained_reasons(tmp_path):
    _card(tmp_path / "seg", minutes=30.0, size=(240, 320), frames=1200)
    (tmp_path / "seg" / "encoder").mkdir()
    (tmp_path / "seg" / "encoder" / "metrics.json").write_text(
        json.dumps([{"epoch": 1, "time_s": 300.0}, {"epoch": 2, "time_s": 300.0}])
    )
    _card(tmp_path / "naive", minutes=12.5, size=(48, 64), frames=4, epochs=1, init="naive")
    (tmp_path / "dir").mkdir()
    (tmp_path / "dir" / "metrics.json").write_text(
        json.dumps({"fit_seconds": 1.5, "fit_inference_seconds": 58.5})
    )
    (tmp_path / "bare").mkdir()
    seg = ev.model_record(tmp_path / "seg" / "model.pt", "seg")
    assert seg.train_minutes == pytest.approx(40.0) and seg.epochs == 3
    assert seg.init_checkpoint is None
    assert ev.model_record(tmp_path / "naive", "naive").init_checkpoint == "naive"
    assert ev.model_record(tmp_path / "dir", "dirichlet").train_minutes == pytest.approx(1.0)
    bare = ev.model_record(tmp_path / "bare", "normals")
    assert bare.train_minutes is None and bare.source is None

    full = ev.EvalConfig(frames=24, size=(240, 320))
    assert ev.untrained_reasons({"seg": seg}, full) == []
    reasons = ev.untrained_reasons(
        {"seg": seg, "naive": ev.model_record(tmp_path / "naive", "naive"), "normals": bare},
        ev.EvalConfig(frames=2, size=SIZE),
    )
    text = " | ".join(reasons)
    assert "naive: trained on 64x48" in text and "naive: trained on 4 frames" in text
    assert "normals:" in text and "64x48" in text and "only 2 held-out frames" in text
    assert not any(r.startswith("seg") for r in reasons)


# ----------------------------------------------------------------------------- random models, bench
@pytest.fixture(scope="module")
def random_models(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("random_models")
    torch.manual_seed(0)
    for kind, name in (("seg", "enet"), ("normals", "joint"), ("naive", "naive_cnn")):
        save_model_checkpoint(get_model(name), root / kind / "model.pt", model_name=name)
    filt = DirichletFilter(alpha=np.full(NUM_CLASSES, 1.5))
    filt.threshold = 0.0
    filt.save(root / "dirichlet" / "dirichlet.json")
    return root


def test_random_models_give_figures_in_range_and_panels(cfg, heldout, random_models, tmp_path):
    dataset, indices, _ = heldout
    res = ev.evaluate(
        cfg,
        seg=ev.load_predictor(random_models / "seg"),
        normals=ev.load_predictor(random_models / "normals" / "model.pt"),
        naive=ev.load_predictor(random_models / "naive"),
        dirichlet=ev.load_filters(random_models / "dirichlet")[0],
        dataset=dataset,
        indices=indices,
    )
    fig = res.figures
    for key in ("miou", "building_iou", "normals_building_within_11_25", "dirichlet_fp_removed",
                "maxprob_fp_removed_same_rejections", "naive_miou"):  # fmt: skip
        assert math.isnan(fig[key]) or 0.0 <= fig[key] <= 1.0, key
    assert 0.0 <= fig["normals_building_median_deg"] <= 180.0
    assert -1.0 <= fig["dirichlet_extra_false_rejections"] <= 1.0
    assert len(res.panels) == 2 and res.panels[0].normals_pred.shape == (3, *SIZE)
    a = figures.labels_normals_figure(res.panels, tmp_path / "a.png")
    b = figures.filter_figure(res.panels, tmp_path / "b.png")
    for p in (a, b):
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(GeosegError, match="no frame"):
        figures.filter_figure(res.panels[:0], tmp_path / "c.png")


def test_bench_end_to_end_and_refusals(cfg, random_models, tmp_path, capsys):
    bench = _load_bench()
    args = [f"--{k}={random_models / k}" for k in ("seg", "normals", "naive", "dirichlet")]
    args += ["--frames", "2", "--size", "64x48", "--cache-dir", str(cfg.cache_dir), "--no-progress"]
    args += ["--cities", "1000,13"]  # two renders; tuning and validation cities: refused below

    results = bench.RESULTS_DIR / "accuracy_seg.json"
    before = results.stat().st_mtime_ns if results.exists() else None
    assert bench.main(args) == 3  # random models, smoke size: refused for bench/results
    err = capsys.readouterr().err
    assert "refusing" in err and "city 1000 recipes were chosen on" in err
    assert (results.stat().st_mtime_ns if results.exists() else None) == before

    out = tmp_path / "out"
    assert bench.main([*args, "--allow-untrained", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert (
        "| mIoU (8 classes) |" in printed and ">= 0.80" in printed and "Not a published" in printed
    )
    data = json.loads((out / "accuracy_seg.json").read_text())
    for key in ("miou", "building_iou", "normals_building_median_deg",
                "normals_building_within_11_25", "normals_building_mean_deg",
                "normals_building_within_22_5", "normals_building_within_30",
                "dirichlet_fp_removed", "dirichlet_extra_false_rejections",
                "maxprob_fp_removed_same_rejections", "train_minutes_seg", "train_minutes_normals",
                "train_minutes_naive", "train_minutes_dirichlet", "machine", "command", "untrained"):  # fmt: skip
        assert key in data, key
    assert data["train_minutes_seg"] is None  # save_model_checkpoint alone: no training record
    assert list(data["per_render"]) == ["1000", "13"] and data["renders"] == 2
    assert (
        data["frames"] == 4 and data["frames_per_render"] == 2 and data["eval_seeds"] == "1000,13"
    )
    assert data["split"].startswith("not report data: cities 1000, 13")
    runs = [data["per_render"][c]["miou"] for c in ("1000", "13")]
    if None not in runs:
        assert data["miou"] == pytest.approx(np.mean(runs))
        assert data["miou_std"] == pytest.approx(np.std(runs, ddof=1))
    assert "### Each render" in printed and "| 13 |" in printed
    assert (out / "accuracy_seg_fig4_20.png").is_file() and (
        out / "accuracy_seg_fig4_8.png"
    ).is_file()

    assert bench.main(["--seg", str(tmp_path / "nope"), "--naive", "none", "--dirichlet", "none",
                       "--normals", "none", "--out", str(out)]) == 2  # fmt: skip
    assert "missing models" in capsys.readouterr().err
    bench.WEIGHTS = tmp_path / "weights"
    assert bench.main(["--seg", str(tmp_path / "weights" / "seg"), "--normals", "none",
                       "--naive", "none", "--dirichlet", "none"]) == 2  # fmt: skip
    assert "shipped weights" in capsys.readouterr().err


def test_bench_summary_means_floats_sums_counts_and_judges_the_filter_on_means():
    bench = _load_bench()
    render = {
        "frames": 48, "eval_width": 320, "eval_seeds": "1001", "conditions": "dusk:8,sun_low:8",
        "miou": 0.8, "miou_heldout_condition": math.nan, "dirichlet_fp_removed": 0.7,
        "dirichlet_extra_false_rejections": 0.1, "maxprob_fp_removed_same_rejections": 0.6,
        "maxprob_extra_false_rejections_same": 0.1, "filter_winner": "dirichlet",
        "dirichlet_threshold_log_density": 10.0,
    }  # fmt: skip
    other = {**render, "eval_seeds": "1002", "conditions": "dusk:8,night:8", "miou": 0.9,
             "maxprob_fp_removed_same_rejections": 0.75, "filter_winner": "max_probability"}  # fmt: skip
    out = bench.mean_and_spread({"1001": render, "1002": other})
    assert out["miou"] == pytest.approx(0.85) and out["miou_std"] == pytest.approx(0.0707, abs=1e-4)
    assert out["frames"] == 96 and out["eval_width"] == 320 and out["eval_seeds"] == "1001,1002"
    assert out["conditions"] == "dusk:16,night:8,sun_low:8"
    assert math.isnan(out["miou_heldout_condition"])
    assert out["dirichlet_threshold_log_density"] == 10.0
    assert "dirichlet_threshold_log_density_std" not in out
    assert out["filter_winner"] == "dirichlet"  # 0.70 against 0.675 on the means
    assert out["filter_winner_renders"] == "dirichlet:1,max_probability:1"
    table = bench.markdown_table(out)
    assert "| mIoU (8 classes) | 0.850 ± 0.071 | >= 0.80 | yes |" in table
    assert "| Dirichlet: building FP removed | 70.0 ± 0.0 % |" in table
    assert bench.mean_and_spread({"1001": render})["miou_std"] == 0.0


def test_load_predictor_reads_training_checkpoints_and_names_bad_files(tmp_path):
    from training.checkpoint import build_checkpoint, save_checkpoint

    torch.manual_seed(0)
    net = get_model("naive_cnn")
    save_checkpoint(build_checkpoint(net, model_name="naive_cnn", epoch=1), tmp_path / "last.pt")
    image = np.zeros((1, *SIZE, 3), np.uint8)
    res = ev.load_predictor(tmp_path)(image)  # run directory with only last.pt
    assert res.probabilities.shape == (1, NUM_CLASSES, *SIZE)
    assert np.allclose(res.probabilities.sum(1), 1.0, atol=1e-4)
    with pytest.raises(GeosegError, match="no such"):
        ev.load_predictor(tmp_path / "missing")
    with pytest.raises(GeosegError, match="no such filter"):
        ev.load_filters(tmp_path)


def test_bench_training_budget_only_judges_from_scratch_runs():
    table = _load_bench().markdown_table(
        {"train_minutes_naive": 78.1, "init_checkpoint_naive": "naive", "train_minutes_seg": 50.0}
    )
    rows = {line.split(" | ")[0]: line for line in table.splitlines()}
    assert rows["| training wall time, naive (min)"].endswith("| (fine-tuned from naive) |  |")
    assert rows["| training wall time, seg (min)"].endswith("| <= 45 | **no** |")
