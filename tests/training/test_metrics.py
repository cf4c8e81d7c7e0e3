"""Metrics against hand-computed examples."""

import math

import pytest
import torch

from geoseg.classes import BUILDING, IGNORE_INDEX
from geoseg.errors import GeosegError
from training.losses import class_weights_from_dataset
from training.metrics import (
    MeterCollection,
    NormalsMeter,
    SegmentationMeter,
    angular_error_deg,
    building_filter_scores,
    class_counts,
    confusion_matrix,
    enet_class_weights,
    iou_per_class,
    normal_scores,
    segmentation_scores,
)


def test_confusion_and_iou_on_a_3x3_case() -> None:
    target = torch.tensor([[0, 0, 1], [1, 1, 2], [2, 2, IGNORE_INDEX]])
    pred = torch.tensor([[0, 1, 1], [1, 2, 2], [2, 0, 0]])
    cm = confusion_matrix(pred, target, num_classes=3)
    expected = torch.tensor([[1, 1, 0], [0, 2, 1], [1, 0, 2]])
    assert torch.equal(cm, expected)
    # IoU = tp / (tp + fp + fn): class 0: 1 / 3; class 1: 2 / 4; class 2: 2 / 4
    iou = iou_per_class(cm)
    assert torch.allclose(iou, torch.tensor([1 / 3, 1 / 2, 1 / 2], dtype=torch.float64))
    scores = segmentation_scores(cm, ["a", "b", "c"])
    assert scores["miou"] == pytest.approx((1 / 3 + 1 / 2 + 1 / 2) / 3)
    assert scores["pixel_acc"] == pytest.approx(5 / 8)
    assert scores["iou_b"] == pytest.approx(0.5)


def test_absent_class_is_nan_and_left_out_of_miou() -> None:
    cm = confusion_matrix(torch.tensor([0, 1, 1]), torch.tensor([0, 1, 1]), num_classes=3)
    iou = iou_per_class(cm)
    assert math.isnan(float(iou[2]))
    assert segmentation_scores(cm, ["a", "b", "c"])["miou"] == pytest.approx(1.0)


def test_confusion_rejects_labels_outside_the_range() -> None:
    with pytest.raises(GeosegError, match="class ids"):
        confusion_matrix(torch.tensor([0, 1]), torch.tensor([0, 9]), num_classes=3)


def test_segmentation_meter_accumulates_batches() -> None:
    meter = SegmentationMeter(num_classes=3, class_names=["a", "b", "c"])
    target = torch.tensor([[[0, 1], [2, 2]]])
    logits = torch.nn.functional.one_hot(torch.tensor([[[0, 1], [2, 0]]]), 3).permute(0, 3, 1, 2)
    meter.update({"logits": logits.float()}, {"labels": target})
    meter.update({"logits": logits.float()}, {"labels": target})
    assert int(meter.state["cm"].sum()) == 8
    assert meter.compute()["pixel_acc"] == pytest.approx(0.75)
    meter.reset()
    assert int(meter.state["cm"].sum()) == 0


def test_enet_class_weights_formula() -> None:
    counts = torch.tensor([70, 20, 10, 0])
    w = enet_class_weights(counts)
    expected = [1 / math.log(1.02 + p) for p in (0.7, 0.2, 0.1, 0.0)]
    assert torch.allclose(w, torch.tensor(expected, dtype=torch.float32))
    assert w[3] == pytest.approx(1 / math.log(1.02))  # absent class: the maximum
    labels = torch.tensor([[0, 0, 1, IGNORE_INDEX]])
    assert class_counts(labels, 4).tolist() == [2, 1, 0, 0]
    with pytest.raises(GeosegError):
        enet_class_weights(torch.zeros(3))


class _RandomlyCroppedLabels(torch.utils.data.Dataset):
    """Labels whose visible part a random transform picks (torch's global generator)."""

    def __len__(self) -> int:
        return 6

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        labels = torch.zeros(4, 8, dtype=torch.int64)
        labels[:, :i] = 1
        shift = int(torch.randint(0, 8, ()))  # as a random zoom or crop draws
        return {"labels": labels.roll(shift, dims=1)[:, :4]}


def test_class_weights_from_a_randomly_transformed_dataset_do_not_depend_on_the_generator():
    dataset = _RandomlyCroppedLabels()
    torch.manual_seed(1)
    first, counts = class_weights_from_dataset(dataset, max_samples=4, seed=0)
    after = torch.rand(())  # the global stream goes on as if nothing had drawn from it
    torch.manual_seed(1)
    assert torch.equal(after, torch.rand(()))
    torch.manual_seed(2)  # another state before the call: the same weights
    second, _ = class_weights_from_dataset(dataset, max_samples=4, seed=0)
    assert torch.equal(first, second) and int(counts.sum()) == 4 * 16
    third, _ = class_weights_from_dataset(dataset, max_samples=4, seed=3)
    assert not torch.equal(first, third)  # another seed, other samples and transforms


def _rot_z(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor(
        [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]]
    )


def test_angular_errors_of_known_rotations() -> None:
    # 4 pixels of a (1, 3, 2, 2) map, all with target normal x; rotate by 5, 15, 25, 90 degrees
    angles = [5.0, 15.0, 25.0, 90.0]
    x = torch.tensor([1.0, 0.0, 0.0])
    pred = torch.stack([2.0 * (_rot_z(a) @ x) for a in angles], 1).reshape(1, 3, 2, 2)
    target = x.view(1, 3, 1, 1).expand(1, 3, 2, 2).clone()
    err = angular_error_deg(pred, target)
    assert torch.allclose(err, torch.tensor(angles), atol=1e-4)
    s = normal_scores(err)
    assert s["angle_mean"] == pytest.approx(sum(angles) / 4, abs=1e-4)
    assert s["angle_median"] == pytest.approx(20.0, abs=1e-4)
    assert s["within_11_25"] == pytest.approx(0.25)
    assert s["within_22_5"] == pytest.approx(0.5)
    assert s["within_30"] == pytest.approx(0.75)


def test_angular_error_skips_invalid_pixels_and_meter_matches() -> None:
    target = torch.zeros(1, 3, 1, 3)
    target[0, 2, 0, :2] = 1.0  # third pixel invalid (sky)
    pred = torch.zeros(1, 3, 1, 3)
    pred[0, :, 0, 0] = torch.tensor([0.0, 0.0, 1.0])
    pred[0, :, 0, 1] = torch.tensor([1.0, 0.0, 1.0])  # 45 degrees
    pred[0, :, 0, 2] = torch.tensor([1.0, 0.0, 0.0])
    err = angular_error_deg(pred, target)
    assert torch.allclose(err, torch.tensor([0.0, 45.0]), atol=1e-4)
    labels = torch.tensor([[[BUILDING, 0, BUILDING]]])
    meter = MeterCollection(NormalsMeter(), NormalsMeter(only_class=BUILDING, prefix="b_"))
    meter.update({"normals": pred}, {"normals": target, "labels": labels})
    out = meter.compute()
    assert out["angle_mean"] == pytest.approx(22.5, abs=1e-4)
    assert out["n_pixels"] == 2 and out["b_n_pixels"] == 1
    assert out["b_angle_median"] == pytest.approx(0.0, abs=0.05)


def test_building_filter_counts() -> None:
    # 6 pixels: argmax building on 0..3; truth building on 0, 1, 4; the filter accepts 0 and 2
    pred_b = torch.tensor([1, 1, 1, 1, 0, 0], dtype=torch.bool)
    true_b = torch.tensor([1, 1, 0, 0, 1, 0], dtype=torch.bool)
    accepted = torch.tensor([1, 0, 1, 0, 0, 0], dtype=torch.bool)
    s = building_filter_scores(pred_b, accepted, true_b)
    assert (s["fp_argmax"], s["fp_filter"], s["fr_argmax"], s["fr_filter"]) == (2, 1, 1, 2)
    assert s["fp_removed"] == pytest.approx(0.5)
    assert s["extra_false_rejections"] == pytest.approx(1 / 3)


def test_miou_over_the_classes_the_dataset_labels() -> None:
    # classes 0, 1 labelled; class 2 ("terrain") never in the truth but predicted once
    cm = torch.tensor([[3, 0, 1], [1, 3, 0], [0, 0, 0]])
    everything = segmentation_scores(cm, ["a", "b", "t"])
    assert everything["iou_t"] == 0.0  # present in the mean: it drags it down
    assert everything["miou"] == pytest.approx((3 / 5 + 3 / 4 + 0.0) / 3)
    labelled = segmentation_scores(cm, ["a", "b", "t"], classes=[0, 1])
    # the wrong "t" pixel still costs class a (its row): IoU_a = 3 / (3 + 1 + 1)
    assert labelled["miou"] == pytest.approx((3 / 5 + 3 / 4) / 2)
    assert "iou_t" not in labelled and labelled["pixel_acc"] == everything["pixel_acc"]
    with pytest.raises(GeosegError, match="classes"):
        segmentation_scores(cm, ["a", "b", "t"], classes=[0, 3])


def test_segmentation_meter_takes_the_labelled_classes() -> None:
    meter = SegmentationMeter(3, classes=[0, 1])
    logits = torch.zeros(1, 3, 1, 4)
    logits[0, torch.tensor([0, 1, 2, 2]), 0, torch.arange(4)] = 1.0  # predicts 0, 1, 2, 2
    meter.update({"logits": logits}, {"labels": torch.tensor([[[0, 1, 1, 0]]])})
    scores = meter.compute()
    assert scores["miou"] == pytest.approx((1 / 2 + 1 / 2) / 2)
    assert "iou_2" not in scores
