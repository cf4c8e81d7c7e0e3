"""The relocalisation and relative-pose trainers and the reloc benchmark on tiny configs:
end to end (checkpoints, metrics, ONNX, model card), loss decrease on a fixed batch, hard
negatives, the ``geoseg train reloc|relpose`` errors and ``bench/accuracy_reloc.py --quick``."""

import importlib.util
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import onnxruntime as ort
import pytest
import torch

from geoseg.config import load_config
from geoseg.data.pairs import positive_mask
from geoseg.errors import GeosegError
from geoseg.infer import save_model_checkpoint
from geoseg.models.registry import get_model
from geoseg.models.relpose import relative_pose_labels, so3_exp
from geoseg_cli.cli import main as cli_main
from training import reloc as reloc_trainer
from training import relpose as relpose_trainer

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def shared(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("reloc")
    torch.manual_seed(0)
    save_model_checkpoint(get_model("enet"), root / "trunk.pt", model_name="enet")
    return {"root": root, "trunk": root / "trunk.pt", "cache": root / "cache"}


def _overrides(shared: dict, out: Path, **kw) -> dict:
    routes = {
        "world": {"blocks_x": 2, "blocks_y": 2},
        "size": [48, 64],
        "cache_dir": str(shared["cache"]),
        "train_seeds": [1],
        "val_seeds": [13],
        "conditions_per_route": 2,
        "length_m": 36.0,
        "val_length_m": 30.0,
        "spacing_m": 6.0,
    }
    base = {
        "trunk_checkpoint": str(shared["trunk"]),
        "routes": routes,
        "epochs": 1,
        "batch_size": 4,
        "device": "cpu",
        "progress": False,
        "plots": False,
        "out_dir": str(out),
    }
    base.update(kw)
    return base


def _onnx_run(path: Path, inputs: list[np.ndarray]) -> list[np.ndarray]:
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    return sess.run(None, dict(zip(names, inputs)))


# ----------------------------------------------------------------------------- end to end
def test_reloc_main_end_to_end(shared, tmp_path, run_files):
    cfg = load_config(
        reloc_trainer.RelocConfig,
        None,
        overrides=_overrides(
            shared,
            tmp_path / "run",
            triplets_per_epoch=8,
            val_triplets=8,
            min_negative_distance_m=12.0,
            hard_start_epoch=0,
        ),
    )
    run = reloc_trainer.main(cfg, command="pytest reloc")
    for name in run_files:
        assert (run / name).is_file(), name
    rows = json.loads((run / "metrics.json").read_text())
    assert len(rows) == 1 and 0.0 <= rows[0]["val_triplet_accuracy"] <= 1.0
    card = json.loads((run / "model_card.json").read_text())
    assert card["trainer"] == "reloc" and card["files"]["onnx"] == "model.onnx"
    assert card["command"] == "pytest reloc"
    # model.pt is the head alone, loadable from the registry; ONNX matches torch
    ckpt = torch.load(run / "model.pt", weights_only=True)
    head = get_model("reloc", **ckpt["model_config"])
    head.load_state_dict(ckpt["state_dict"])
    x = torch.randn(2, 128, 6, 8)
    with torch.no_grad():
        ref = head.eval()(x)["embedding"].numpy()
    (got,) = _onnx_run(run / "model.onnx", [x.numpy()])
    np.testing.assert_allclose(got, ref, atol=1e-4)


@pytest.mark.parametrize("distance", [False, True])
def test_relpose_main_end_to_end(shared, tmp_path, run_files, distance):
    model_config = {"predict_distance": True} if distance else {}
    cfg = load_config(
        relpose_trainer.RelPoseConfig,
        None,
        overrides=_overrides(
            shared, tmp_path / "run", pairs_per_epoch=8, val_pairs=8, model_config=model_config
        ),
    )
    run = relpose_trainer.main(cfg)
    for name in run_files:
        assert (run / name).is_file(), name
    row = json.loads((run / "metrics.json").read_text())[0]
    assert {"val_loss", "val_rot_median_deg", "val_dir_median_deg"} <= set(row)
    assert ("val_dist_median_rel" in row) is distance
    ckpt = torch.load(run / "model.pt", weights_only=True)
    head = get_model("relpose", **ckpt["model_config"])
    head.load_state_dict(ckpt["state_dict"])
    a, b = torch.randn(2, 128, 6, 8), torch.randn(2, 128, 6, 8)
    with torch.no_grad():
        ref = head.eval()(a, b)
    outs = _onnx_run(run / "model.onnx", [a.numpy(), b.numpy()])
    np.testing.assert_allclose(outs[0], ref["rotation"].numpy(), atol=1e-4)
    np.testing.assert_allclose(outs[1], ref["direction"].numpy(), atol=1e-4)
    if distance:
        np.testing.assert_allclose(outs[2], ref["log_distance"].numpy(), atol=1e-4)


def test_relpose_fine_tune_with_near_pairs_end_to_end(shared, tmp_path):
    first = load_config(
        relpose_trainer.RelPoseConfig,
        None,
        overrides=_overrides(
            shared, tmp_path / "first", pairs_per_epoch=8, val_pairs=8, export=False,
            model_config={"predict_distance": True},
        ),
    )  # fmt: skip
    first_run = relpose_trainer.main(first)
    over = _overrides(
        shared, tmp_path / "near", pairs_per_epoch=8, val_pairs=8, near_pairs_per_epoch=6,
        val_near_pairs=4, export=False, init_checkpoint=str(first_run),
        model_config={"predict_distance": True},
    )  # fmt: skip
    over["routes"]["aligned_conditions"] = 1
    cfg = load_config(relpose_trainer.RelPoseConfig, None, overrides=over)
    data = relpose_trainer.prepare_head_features(cfg)
    assert [len(r.traversals) for r in data.val] == [3]  # 2 offset + 1 aligned traversal
    np.testing.assert_allclose(data.val[0].traversals[2].t_wc, data.val[0].traversals[0].t_wc)
    run = relpose_trainer.main(cfg)
    row = json.loads((run / "metrics.json").read_text())[0]
    assert math.isfinite(row["val_loss"]) and row["val_near_dist_median_m"] > 0
    card = json.loads((run / "model_card.json").read_text())
    assert len(card["data"]["val_aligned_routes"]) == 1
    over["routes"]["aligned_conditions"] = 0
    with pytest.raises(GeosegError, match="aligned_conditions"):
        load_config(relpose_trainer.RelPoseConfig, None, overrides=over)


def test_reloc_resume_continues_with_the_next_epochs_triplets(shared, tmp_path):
    kw = {"triplets_per_epoch": 8, "val_triplets": 8, "min_negative_distance_m": 12.0}
    over = _overrides(shared, tmp_path / "run", export=False, **kw)
    reloc_trainer.main(load_config(reloc_trainer.RelocConfig, None, overrides=over))
    over.update(epochs=2, resume=True)
    cfg = load_config(reloc_trainer.RelocConfig, None, overrides=over)
    assert reloc_trainer.resume_epoch(cfg) == 1
    run = reloc_trainer.main(cfg)
    rows = json.loads((run / "metrics.json").read_text())
    assert [r["epoch"] for r in rows] == [1, 2]
    assert not (run / "model.onnx").exists()


def test_missing_trunk_is_a_clear_error(shared, tmp_path):
    cfg = load_config(
        reloc_trainer.RelocConfig,
        None,
        overrides=_overrides(shared, tmp_path / "run", trunk_checkpoint=None),
    )
    with pytest.raises(GeosegError, match="trunk_checkpoint"):
        reloc_trainer.main(cfg)


# ----------------------------------------------------------------------------- fixed batches
def _adam_losses(model, loss_fn, x, batch, steps=15) -> list[float]:
    """The loss at each of ``steps`` Adam steps (lr 1e-3) on the fixed input ``x``."""
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    losses = []
    for _ in range(steps):
        loss = loss_fn(model(x), batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return losses


def test_triplet_loss_decreases_on_a_fixed_batch():
    torch.manual_seed(0)
    model = reloc_trainer.TripletEmbedder(get_model("reloc", embedding_dim=16))
    x = torch.randn(8, 3, 128, 4, 5)
    x[:, 1] = x[:, 0] + 0.3 * torch.randn(8, 128, 4, 5)  # matches near their refs
    loss_fn = reloc_trainer.TripletLoss()
    losses = _adam_losses(model, loss_fn, x, {})
    assert losses[-1] < 0.7 * losses[0]


def test_relpose_loss_decreases_on_a_fixed_batch():
    torch.manual_seed(0)
    model = relpose_trainer.PairRegressor(get_model("relpose", hidden_channels=16, fc_dim=32))
    x = torch.randn(8, 2, 128, 4, 5)
    R = so3_exp(0.2 * torch.randn(8, 3))
    t = torch.nn.functional.normalize(torch.randn(8, 3), dim=1)
    batch = {"R_ab": R, "t_dir_ab": t}
    loss_fn = relpose_trainer.RelPoseLoss()
    losses = _adam_losses(model, loss_fn, x, batch)
    assert losses[-1] < 0.7 * losses[0]


def test_relpose_loss_with_distances_uses_the_baselines():
    torch.manual_seed(0)
    head = get_model("relpose", hidden_channels=16, fc_dim=32, predict_distance=True)
    model = relpose_trainer.PairRegressor(head)
    x = torch.randn(8, 2, 128, 4, 5)
    R = so3_exp(0.2 * torch.randn(8, 3))
    t = torch.nn.functional.normalize(torch.randn(8, 3), dim=1)
    baseline = torch.linspace(0.5, 10.0, 8)
    batch = {"R_ab": R, "t_dir_ab": t, "baseline_m": baseline}
    loss_fn = relpose_trainer.RelPoseLoss(mu=2.0)
    with torch.no_grad():
        out = model(x)
    # the distance term is mu times the mean squared log ratio
    plain = relpose_trainer.RelPoseLoss()(
        {k: v for k, v in out.items() if k != "log_distance"}, batch
    )
    want = plain + 2.0 * ((out["log_distance"] - baseline.log()) ** 2).mean()
    torch.testing.assert_close(loss_fn(out, batch), want)
    losses = _adam_losses(model, loss_fn, x, batch)
    assert losses[-1] < 0.7 * losses[0]


def test_relpose_loss_floor_pairs_penalise_only_nearer_predictions():
    n = 4
    out = {
        "rotation": torch.zeros(n, 3),
        "direction": torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3),
        "log_distance": torch.log(torch.tensor([5.0, 50.0, 20.0, 80.0])),
    }
    batch = {
        "R_ab": torch.eye(3).expand(n, 3, 3),
        "t_dir_ab": out["direction"],
        "baseline_m": torch.tensor([5.0, 40.0, 40.0, 40.0]),
        "distance_floor": torch.tensor([False, True, True, True]),
        "pose_weight": torch.tensor([1.0, 0.0, 0.0, 0.0]),
    }
    # exact pose and distance on the pose pair; of the floor pairs only the 20 m reading counts
    want = 3.0 * math.log(20.0 / 40.0) ** 2 / n
    got = relpose_trainer.RelPoseLoss(mu=3.0)(out, batch)
    assert float(got) == pytest.approx(want, rel=1e-5)


def test_relpose_loss_floors_the_distance_and_masks_the_direction_at_one_place():
    n = 2
    out = {
        "rotation": torch.zeros(n, 3),
        "direction": torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
        "log_distance": torch.log(torch.tensor([0.1, 0.3])),
    }
    batch = {
        "R_ab": torch.eye(3).expand(n, 3, 3),
        "t_dir_ab": torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
        "baseline_m": torch.tensor([0.0, 0.03]),  # one place, and 3 cm apart
    }
    loss_fn = relpose_trainer.RelPoseLoss(distance_floor_m=0.1, direction_min_m=0.05)
    # both are read against the 0.1 m floor; neither has a direction term
    want = (0.0 + math.log(3.0) ** 2) / n
    assert float(loss_fn(out, batch)) == pytest.approx(want, rel=1e-5)
    turned = dict(out, direction=torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]))
    assert float(loss_fn(turned, batch)) == pytest.approx(want, rel=1e-5)
    # beyond direction_min_m the direction counts again (opposite direction: 1 - cos = 2)
    far = dict(batch, baseline_m=torch.tensor([0.0, 0.3]))
    assert float(loss_fn(turned, far)) == pytest.approx((2.0 + 0.0) / n, rel=1e-5)


def test_relpose_meter_medians_and_shares():
    meter = relpose_trainer.RelPoseMeter()
    R_gt = torch.eye(3).expand(4, 3, 3)
    angles = torch.tensor([0.0, 1.0, 3.0, 20.0])
    rot = torch.zeros(4, 3)
    rot[:, 2] = torch.deg2rad(angles)
    t_gt = torch.tensor([[1.0, 0.0, 0.0]]).expand(4, 3)
    meter.update({"rotation": rot, "direction": t_gt}, {"R_ab": R_gt, "t_dir_ab": t_gt})
    out = meter.compute()
    assert 0.95 <= out["rot_median_deg"] <= 3.05  # lower median, 0.05-degree bins
    assert out["rot_within_2deg"] == pytest.approx(0.5)
    assert out["dir_median_deg"] < 0.1 and out["dir_within_10deg"] == 1.0
    assert "dist_median_rel" not in out  # no distance output, no distance figures
    # relative baseline errors 0, 10 %, 30 %, 100 %
    log_d = torch.log(torch.tensor([2.0, 5.5, 6.5, 2.0]))
    meter.reset()
    meter.update(
        {"rotation": rot, "direction": t_gt, "log_distance": log_d},
        {"R_ab": R_gt, "t_dir_ab": t_gt, "baseline_m": torch.tensor([2.0, 5.0, 5.0, 1.0])},
    )
    out = meter.compute()
    assert 0.099 <= out["dist_median_rel"] <= 0.301  # lower median, 0.001 bins
    assert out["dist_mean_rel"] == pytest.approx(0.35, abs=1e-6)
    assert out["dist_within_0.2"] == pytest.approx(0.5)


def test_hard_negatives_are_true_negatives_and_resampling_is_seeded(shared):
    from geoseg.data.traversals import RouteSpec, TrunkFeatureExtractor, route_features

    torch.manual_seed(0)
    spec = RouteSpec(
        seed=1, world={"blocks_x": 2, "blocks_y": 2}, length_m=36.0, spacing_m=6.0, size=(48, 64)
    )
    rf = route_features(spec, TrunkFeatureExtractor(get_model("enet")), progress=False)
    head = get_model("reloc")
    kw = {"max_distance_m": 5.0, "max_angle_deg": 30.0, "min_negative_distance_m": 12.0}
    ts = reloc_trainer.TripletSet(
        [rf], 20, seed=3, hard_head=head, hard_k=2, hard_start_epoch=0, **kw
    )
    first = ts.index.copy()
    for _r, q, d, a, p, n in ts.index:
        tq, td = rf.traversals[q], rf.traversals[d]
        assert positive_mask(td.poses, tq.poses)[a, p]
        assert np.linalg.norm(tq.t_wc[a] - td.t_wc[n]) > 12.0
    ts.resample(1)
    again = reloc_trainer.TripletSet(
        [rf], 20, seed=3, hard_head=head, hard_k=2, hard_start_epoch=0, **kw
    )
    np.testing.assert_array_equal(again.index, first)  # same seed and head: same triplets
    uniform = reloc_trainer.TripletSet([rf], 20, seed=3, **kw)
    assert uniform.index.shape == first.shape
    item = ts[0]
    assert item["image"].shape == (3, 128, 6, 8) and item["image"].dtype == torch.float32
    pairs = relpose_trainer.PairSet([rf], 10, seed=0, min_baseline_m=0.5, max_baseline_m=10.0)
    _r, i, j, a, b = pairs.index[0]
    R, t = relative_pose_labels(
        rf.traversals[i].R_wc[a], rf.traversals[i].t_wc[a], rf.traversals[j].R_wc[b],
        rf.traversals[j].t_wc[b],
    )  # fmt: skip
    np.testing.assert_allclose(pairs[0]["R_ab"].numpy(), R, atol=1e-5)
    np.testing.assert_allclose(pairs[0]["t_dir_ab"].numpy(), t, atol=1e-5)
    base_ab = rf.traversals[j].t_wc[b] - rf.traversals[i].t_wc[a]
    assert pairs[0]["baseline_m"].item() == pytest.approx(np.linalg.norm(base_ab), rel=1e-6)
    # far, distance-only pairs come after the pose pairs, which they leave unchanged
    far = relpose_trainer.PairSet(
        [rf], 10, seed=0, n_far=4, far_max_baseline_m=30.0, min_baseline_m=0.5, max_baseline_m=10.0
    )
    assert len(far) == 14
    np.testing.assert_array_equal(far.index[:10], pairs.index)
    assert far.pose_weight.tolist() == [1.0] * 10 + [0.0] * 4
    assert (far.baseline_m[10:] > 10.0).all() and (far.baseline_m[10:] <= 30.0).all()
    assert far[12]["pose_weight"].item() == 0.0
    assert not far.distance_floor.any()
    with pytest.raises(GeosegError, match="far_max_baseline_m"):
        relpose_trainer.PairSet([rf], 10, n_far=4)
    # unrelated pairs (views >= 20 m apart, any orientation) come last, their baseline a floor
    unrelated = relpose_trainer.PairSet(
        [rf], 10, seed=0, n_far=4, far_max_baseline_m=30.0, n_unrelated=3, unrelated_min_m=20.0,
        unrelated_floor_m=15.0, min_baseline_m=0.5, max_baseline_m=10.0,
    )  # fmt: skip
    assert len(unrelated) == 17
    np.testing.assert_array_equal(unrelated.index[:14], far.index)
    assert unrelated.distance_floor.tolist() == [False] * 14 + [True] * 3
    assert unrelated.pose_weight[14:].eq(0).all() and unrelated.baseline_m[14:].eq(15.0).all()
    for _r, i, j, a, b in unrelated.index[14:]:
        assert np.linalg.norm(rf.traversals[i].t_wc[a] - rf.traversals[j].t_wc[b]) >= 20.0
    assert unrelated[16]["distance_floor"].item() is True


def _turning_route(turn_deg: float) -> SimpleNamespace:
    """A route of 24 cameras 2 m apart: 12 looking along +x, then 12 turned by ``turn_deg``
    along their new heading (two traversals, 0.5 m apart), with zero features."""
    from scipy.spatial.transform import Rotation

    R_x = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # OpenCV, looking +x
    yaw = Rotation.from_euler("z", np.r_[[0.0] * 12, [turn_deg] * 12][:, None], degrees=True)
    yaw = yaw.as_matrix()
    R = yaw @ R_x
    heading = yaw[:, :, 0]
    t = np.cumsum(np.r_[np.zeros((1, 3)), 2.0 * heading[:-1]], axis=0)
    travs = [
        SimpleNamespace(poses=(R, t + [0.0, dy, 0.0]), R_wc=R, t_wc=t + [0.0, dy, 0.0])
        for dy in (0.0, 0.5)
    ]
    return SimpleNamespace(traversals=travs, features=[torch.zeros(24, 128, 2, 3)] * 2)


def test_turned_pairs_are_near_turned_views_with_a_distance_floor():
    routes = [_turning_route(0.0), _turning_route(90.0)]  # a straight route has no turned pair
    kw = {"min_baseline_m": 0.5, "max_baseline_m": 10.0, "max_angle_deg": 30.0}
    pairs = relpose_trainer.PairSet(
        routes, 8, seed=0, n_turned=6, turned_max_m=15.0, turned_min_angle_deg=45.0,
        turned_floor_m=30.0, **kw,
    )  # fmt: skip
    assert len(pairs) == 14 and pairs.index.shape == (14, 5)
    assert pairs.distance_floor.tolist() == [False] * 8 + [True] * 6
    assert pairs.pose_weight[8:].eq(0).all() and pairs.baseline_m[8:].eq(30.0).all()
    for r, i, j, a, b in pairs.index[8:]:
        assert r == 1  # the turning route
        ta, tb = routes[r].traversals[i], routes[r].traversals[j]
        assert np.linalg.norm(ta.t_wc[a] - tb.t_wc[b]) <= 15.0
        axis_cos = ta.R_wc[a][:, 2] @ tb.R_wc[b][:, 2]
        assert axis_cos <= math.cos(math.radians(45.0)) + 1e-9
    with pytest.raises(GeosegError, match="no pair of views"):
        relpose_trainer.PairSet(routes[:1], 8, n_turned=6, **kw)


def _aligned_route() -> SimpleNamespace:
    """A route of two traversals of 10 cameras 8 m apart looking along +x, the second 3 m
    further, and one aligned traversal at the first one's positions turned by 2 degrees, with
    zero features."""
    from scipy.spatial.transform import Rotation

    R_x = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    t = np.c_[8.0 * np.arange(10), np.zeros(10), np.full(10, 1.5)]
    turn = Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    poses = [(np.stack([R_x] * 10), t), (np.stack([R_x] * 10), t + [3.0, 0.0, 0.0])]
    poses.append((np.stack([turn @ R_x] * 10), t))
    travs = [SimpleNamespace(poses=(R, p), R_wc=R, t_wc=p) for R, p in poses]
    return SimpleNamespace(
        traversals=travs,
        features=[torch.zeros(10, 128, 2, 3)] * 3,
        spec=SimpleNamespace(conditions=["summer_day", "winter"]),
        aligned=SimpleNamespace(conditions=["summer_day", "night"]),
    )


def test_near_pairs_are_views_of_one_place_in_two_traversals():
    kw = {"min_baseline_m": 0.5, "max_baseline_m": 10.0, "max_angle_deg": 30.0}
    plain = relpose_trainer.PairSet([_aligned_route()], 12, seed=0, **kw)
    pairs = relpose_trainer.PairSet(
        [_aligned_route()], 12, seed=0, n_near=9, near_max_baseline_m=0.5, **kw
    )
    assert len(pairs) == 21
    np.testing.assert_array_equal(pairs.index[:12], plain.index)  # near pairs come last
    assert pairs.pose_weight.eq(1).all() and not pairs.distance_floor.any()
    assert (plain.baseline_m >= 0.5).all()
    assert (plain.index[:, 1:3] < 2).all()  # pose pairs: the route's own traversals only
    for _r, i, j, a, b in pairs.index[12:]:
        assert {int(i), int(j)} == {0, 2} and a == b  # only the traversals that share poses
    assert pairs.baseline_m[12:].eq(0).all() and pairs.t_dir_ab[12:].eq(0).all()
    assert pairs[20]["R_ab"].trace().item() == pytest.approx(1 + 2 * math.cos(math.radians(2)))
    # the meter reads near pairs as a distance in metres, without a direction error
    meter = relpose_trainer.RelPoseMeter(near_max_baseline_m=0.5)
    batch = {k: getattr(pairs, k)[10:14] for k in ("R_ab", "t_dir_ab", "baseline_m")}
    log_d = torch.log(torch.tensor([2.0, 4.0, 0.2, 0.3]))  # two pose pairs, two near pairs
    out = {"rotation": torch.zeros(4, 3), "direction": batch["t_dir_ab"] + 0.0}
    out["direction"][2:] = torch.tensor([1.0, 0.0, 0.0])
    meter.update({**out, "log_distance": log_d}, batch)
    got = meter.compute()
    assert got["near_dist_mean_m"] == pytest.approx(0.25, abs=1e-6)
    assert got["near_dist_within_0.5"] == 1.0
    assert got["dir_median_deg"] < 0.1  # the near pairs' arbitrary directions do not count


def test_aligned_traversals_share_the_first_traversals_poses():
    from training.heads import RoutesConfig

    routes = RoutesConfig(
        world={"blocks_x": 2, "blocks_y": 2}, train_seeds=[1, 2], val_seeds=[13],
        length_m=40.0, aligned_conditions=2, aligned_yaw_jitter_deg=2.0,
    )  # fmt: skip
    for spec in routes.specs("train"):
        aligned = routes.aligned_spec(spec)
        assert aligned.conditions[0] == spec.conditions[0]
        assert not set(aligned.conditions[1:]) & set(spec.conditions)
        assert aligned.offset_m == 0.0 and aligned.yaw_jitter_deg == 2.0
        assert aligned.traversal_key(0) == spec.traversal_key(0)  # one cached traversal
    assert RoutesConfig(length_m=40.0).aligned_spec(spec) is None
    with pytest.raises(GeosegError, match="aligned_conditions"):
        RoutesConfig(length_m=40.0, conditions_per_route=4, aligned_conditions=2)


def test_far_pairs_need_a_distance_head(shared, tmp_path):
    from geoseg.errors import ConfigError

    for key in ("far_pairs_per_epoch", "unrelated_pairs_per_epoch", "turned_pairs_per_epoch"):
        with pytest.raises(ConfigError, match=f"{key}.*predict_distance"):
            load_config(
                relpose_trainer.RelPoseConfig,
                None,
                overrides=_overrides(shared, tmp_path / "run", **{key: 8}),
            )
    distance_head = {"model_config": {"predict_distance": True}}
    for match, bad in (
        ("unrelated_floor_m", {"unrelated_pairs_per_epoch": 8, "unrelated_floor_m": 80.0}),
        ("far_max_baseline_m", {"far_pairs_per_epoch": 8, "far_max_baseline_m": 5.0}),
        ("turned_min_angle_deg", {"turned_pairs_per_epoch": 8, "turned_min_angle_deg": 20.0}),
        ("turned_max_m", {"turned_pairs_per_epoch": 8, "turned_max_m": 0.0}),
    ):
        with pytest.raises(ConfigError, match=match):
            load_config(
                relpose_trainer.RelPoseConfig,
                None,
                overrides=_overrides(shared, tmp_path / "run", **bad, **distance_head),
            )


# ----------------------------------------------------------------------------- the command
@pytest.mark.parametrize("trainer", ["reloc", "relpose"])
def test_cli_bad_config_key_exits_2_naming_it(trainer, capsys):
    code = cli_main(["train", trainer, "--set", "no_such_key=1"])
    assert code == 2
    assert "no_such_key" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the benchmark
def _bench():
    spec = importlib.util.spec_from_file_location(
        "accuracy_reloc", ROOT / "bench" / "accuracy_reloc.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_refuses_untrained_weights(tmp_path, capsys):
    bench = _bench()
    random = ["--trunk", "random", "--reloc", "random", "--relpose", "random"]
    code = bench.main(["--quick", "--out", str(tmp_path), *random])
    assert code == 2  # refused before any work
    assert "--allow-untrained" in capsys.readouterr().err
    assert not (tmp_path / "accuracy_reloc.json").exists()


@pytest.mark.parametrize("distance", [False, True])
def test_bench_quick_runs_end_to_end(shared, tmp_path, distance):
    bench = _bench()
    out = tmp_path / "results"
    relpose = "random"
    if distance:  # an untrained head with the distance output
        torch.manual_seed(0)
        head = get_model("relpose", predict_distance=True)
        relpose = str(tmp_path / "relpose.pt")
        save_model_checkpoint(
            head, relpose, model_name="relpose", model_config={"predict_distance": True}
        )
    code = bench.main(
        [
            "--quick",
            "--allow-untrained",
            "--out",
            str(out),
            "--cache-dir",
            str(shared["cache"]),
            "--trunk",
            str(shared["trunk"]),
            "--reloc",
            "random",
            "--relpose",
            relpose,
            "--pairs",
            "4",
            "--triplets",
            "8",
            # with distances, the head is gated with a near head (here: itself)
            *(["--relpose-near", relpose, "--near-gate-m", "0.5"] if distance else []),
        ]
    )
    assert code == 0
    res = json.loads((out / "accuracy_reloc.json").read_text())
    for key in (
        "recall_at_1",
        "recall_at_3",
        "recall_at_1_gps_window",
        "recall_at_1_raw_layer21",
        "triplet_accuracy",
        "relpose_rot_median_deg",
        "relpose_dir_median_deg",
        "essential_rot_median_deg",
        "essential_dir_median_deg",
        "abs_position_median_m",
        "abs_position_degenerate_share",
        "machine",
        "command",
    ):
        assert key in res, key
    assert 0.0 <= res["recall_at_1"] <= res["recall_at_3"] <= 1.0
    for tail in ("", "_smoothed", "_no_odometry", "_irregular"):
        assert 0.0 <= res[f"recall_at_1_sequence{tail}"] <= res[f"recall_at_3_sequence{tail}"] <= 1
    assert 0.0 <= res["recall_at_1_gps_window_sequence"] <= 1.0
    assert res["untrained"] == (["reloc"] if distance else ["reloc", "relpose"])
    assert "warning" in res
    assert (out / "accuracy_reloc_tsne.png").stat().st_size > 0
    assert (out / "accuracy_reloc_panel.png").stat().st_size > 0
    # the geometry itself is exact: true directions give the true position, for every k
    assert res["abs_position_top_k"] == 2
    for suffix in ("", "_top3", "_top4", "_top5"):
        assert 0.0 <= res[f"abs_position_degenerate_share{suffix}"] <= 1.0
        exact = res[f"abs_position_median_m_true_directions{suffix}"]
        assert exact in (None, pytest.approx(0.0, abs=1e-6)), suffix
    if distance:  # ranged rays head the figures, from one base image up; rays alone beside
        assert "ranged" in res["abs_position_method"]
        assert res["abs_position_degenerate_share_top1"] <= res["abs_position_degenerate_share"]
        assert "abs_position_median_m_rays_only" in res
        assert 0.0 <= res["recall_at_1_gps_window_reranked"] <= 1.0
        assert 0.0 <= res["recall_at_1_reranked"] <= res["recall_at_3_reranked"] <= 1.0
        assert 0.0 <= res["recall_at_1_gps_window_reranked_gps"] <= 1.0
        assert res["rerank_appearance_weight"] == 0.5
        for key in ("recall_at_1_gps_window_reranked", "recall_at_1_reranked"):
            assert 0.0 <= res[f"{key}_distance_only"] <= 1.0
        assert res["relpose_dist_median_rel"] is not None
        assert res["relpose_near_gate"] == {
            "near_head": str(Path(relpose).resolve()),
            "near_gate_m": 0.5,
        }
    else:
        assert res["relpose_near_gate"] is None
        assert "abs_position_median_m_top1" not in res and "rays" in res["abs_position_method"]
