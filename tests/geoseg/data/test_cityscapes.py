"""The Cityscapes-format reader: layout checks, label mapping, errors naming the path."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from geoseg.classes import (
    BUILDING,
    IGNORE_INDEX,
    OBJECT,
    ROAD,
    SIDEWALK,
    SKY,
    TERRAIN,
    VEGETATION,
    VEHICLE,
)
from geoseg.data.cityscapes import CITYSCAPES_TO_GEOSEG, CityscapesDataset, map_cityscapes_labels
from geoseg.data.transforms import build_transforms
from geoseg.errors import GeosegError

# (Cityscapes labelId, expected geoseg id) planted as vertical stripes
PLANTED = [
    (7, ROAD), (8, SIDEWALK), (9, ROAD), (11, BUILDING), (12, BUILDING), (13, OBJECT),
    (17, OBJECT), (20, OBJECT), (21, VEGETATION), (22, TERRAIN), (23, SKY), (24, IGNORE_INDEX),
    (26, VEHICLE), (33, VEHICLE), (0, IGNORE_INDEX), (1, IGNORE_INDEX),
]  # fmt: skip


def _write_frame(root: Path, split: str, city: str, name: str, label_ids: np.ndarray) -> Path:
    h, w = label_ids.shape
    img_dir = root / "leftImg8bit" / split / city
    lab_dir = root / "gtFine" / split / city
    img_dir.mkdir(parents=True, exist_ok=True)
    lab_dir.mkdir(parents=True, exist_ok=True)
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = 200  # red in RGB
    rgb[..., 2] = np.arange(w, dtype=np.uint8)[None] * 10
    cv2.imwrite(str(img_dir / f"{name}_leftImg8bit.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    label_path = lab_dir / f"{name}_gtFine_labelIds.png"
    cv2.imwrite(str(label_path), label_ids.astype(np.uint8))
    return label_path


def _planted(h: int = 4) -> np.ndarray:
    return np.tile(np.array([cs for cs, _ in PLANTED], np.uint8)[None], (h, 1))


def test_reads_and_maps_a_planted_frame(tmp_path: Path) -> None:
    _write_frame(tmp_path, "train", "aachen", "aachen_000000_000019", _planted())
    _write_frame(tmp_path, "train", "bochum", "bochum_000000_000001", _planted())
    ds = CityscapesDataset(tmp_path, "train")
    assert len(ds) == 2
    sample = ds[0]
    assert sample["image"].shape == (3, 4, len(PLANTED)) and sample["image"].dtype == torch.float32
    assert sample["labels"].dtype == torch.int64
    assert torch.allclose(sample["image"][0], torch.full((4, len(PLANTED)), 200 / 255))  # RGB order
    assert sample["image"][2, 0, 3] == pytest.approx(30 / 255)
    expected = torch.tensor([ours for _, ours in PLANTED])
    assert torch.equal(sample["labels"][0], expected) and torch.equal(sample["labels"][3], expected)
    assert len(CityscapesDataset(tmp_path, "train", cities=["bochum"])) == 1


def test_every_cityscapes_id_is_mapped() -> None:
    assert set(CITYSCAPES_TO_GEOSEG) == set(range(34))
    assert set(CITYSCAPES_TO_GEOSEG.values()) <= set(range(8)) | {IGNORE_INDEX}
    assert map_cityscapes_labels(np.array([[255]]))[0, 0] == IGNORE_INDEX
    with pytest.raises(GeosegError, match=r"x\.png.*\[34, 200\]"):
        map_cityscapes_labels(np.array([[34, 200, 7]]), path="x.png")


def test_transform_is_applied(tmp_path: Path) -> None:
    _write_frame(tmp_path, "val", "c", "c_0", _planted(h=6))
    ds = CityscapesDataset(tmp_path, "val", transform=build_transforms(size=(3, 8), train=False))
    sample = ds[0]
    assert sample["image"].shape == (3, 3, 8) and sample["labels"].shape == (3, 8)
    assert set(sample["labels"].unique().tolist()) <= {ours for _, ours in PLANTED}


def test_layout_errors_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(GeosegError, match="does not exist"):
        CityscapesDataset(tmp_path / "missing")
    (tmp_path / "leftImg8bit" / "train").mkdir(parents=True)
    with pytest.raises(GeosegError, match=r"expected folder .*gtFine[/\\]train"):
        CityscapesDataset(tmp_path)
    (tmp_path / "gtFine" / "train").mkdir(parents=True)
    with pytest.raises(GeosegError, match=r"leftImg8bit[/\\]train is empty"):
        CityscapesDataset(tmp_path)
    # images dropped straight into the split folder (no city level): a wrong layout
    cv2.imwrite(
        str(tmp_path / "leftImg8bit" / "train" / "a_leftImg8bit.png"), np.zeros((2, 2, 3), np.uint8)
    )
    with pytest.raises(GeosegError, match="city"):
        CityscapesDataset(tmp_path)


def test_missing_label_file_and_out_of_range_labels(tmp_path: Path) -> None:
    label = _write_frame(tmp_path, "train", "c", "c_0", _planted())
    label.unlink()
    with pytest.raises(
        GeosegError, match=r"c_0_leftImg8bit\.png has no label file.*c_0_gtFine_labelIds\.png"
    ):
        CityscapesDataset(tmp_path)
    bad = np.full((4, 5), 7, np.uint8)
    bad[0, 0] = 40
    label = _write_frame(tmp_path, "train", "c", "c_0", bad)
    ds = CityscapesDataset(tmp_path)
    with pytest.raises(GeosegError, match=r"c_0_gtFine_labelIds\.png.*\[40\]"):
        ds[0]
    # already-mapped labels: ids beyond the 8 classes are refused
    cv2.imwrite(str(label), np.full((4, 5), 9, np.uint8))
    with pytest.raises(GeosegError, match=r"c_0_gtFine_labelIds\.png.*outside the class range"):
        CityscapesDataset(tmp_path, label_format="geoseg")[0]
    # a colour label image instead of labelIds
    cv2.imwrite(str(label), np.zeros((4, 5, 3), np.uint8))
    with pytest.raises(GeosegError, match="single-channel"):
        ds[0]
