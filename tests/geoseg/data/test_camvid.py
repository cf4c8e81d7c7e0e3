"""CamVid-layout reader on frames made here: class map, label_map option, layout errors."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from geoseg.classes import BUILDING, IGNORE_INDEX, OBJECT, ROAD, SIDEWALK, SKY, TERRAIN, VEHICLE
from geoseg.data.camvid import CamVidDataset
from geoseg.errors import ConfigError, GeosegError
from training.config import DataConfig
from training.frame_data import build_frame_dataset, dataset_classes


def _write_frames(root: Path, split: str = "train", n: int = 2, size=(12, 16)) -> np.ndarray:
    (root / split).mkdir(parents=True)
    (root / f"{split}annot").mkdir()
    ids = np.arange(size[0] * size[1]).reshape(size) % 12  # every CamVid id 0..11
    for i in range(n):
        rgb = np.full(size + (3,), 40 * i, np.uint8)
        rgb[..., 0] = 200  # red channel: checks RGB order
        cv2.imwrite(str(root / split / f"seq_{i:03d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / f"{split}annot" / f"seq_{i:03d}.png"), ids.astype(np.uint8))
    return ids


def test_reads_frames_and_maps_camvid_ids(tmp_path: Path) -> None:
    ids = _write_frames(tmp_path)
    ds = CamVidDataset(tmp_path, "train")
    assert len(ds) == 2
    sample = ds[1]
    assert sample["image"].shape == (3, 12, 16)
    assert float(sample["image"][0].mean()) == pytest.approx(200 / 255)
    labels = sample["labels"].numpy()
    expected = {0: SKY, 1: BUILDING, 2: OBJECT, 3: ROAD, 4: SIDEWALK, 6: OBJECT, 8: VEHICLE}
    for camvid_id, ours in expected.items():
        assert (labels[ids == camvid_id] == ours).all()
    for camvid_id in (7, 9, 10, 11):
        assert (labels[ids == camvid_id] == IGNORE_INDEX).all()
    assert TERRAIN not in ds.labelled_classes and len(ds.labelled_classes) == 7


def test_label_map_option_replaces_the_table(tmp_path: Path) -> None:
    ids = _write_frames(tmp_path, n=1)
    mapping = {i: "ignore" for i in range(12)} | {3: "road", 5: "terrain"}
    ds = CamVidDataset(tmp_path, "train", label_map=mapping)
    labels = ds[0]["labels"].numpy()
    assert (labels[ids == 5] == TERRAIN).all() and (labels[ids == 0] == IGNORE_INDEX).all()
    assert ds.labelled_classes == (ROAD, TERRAIN)
    with pytest.raises(GeosegError, match=r"values \[11\] are not in the label map"):
        CamVidDataset(tmp_path, "train", label_map={i: "road" for i in range(11)})[0]
    with pytest.raises(GeosegError, match="unknown class 'tree'"):
        CamVidDataset(tmp_path, "train", label_map={0: "tree"})


def test_layout_errors_name_the_expected_path(tmp_path: Path) -> None:
    _write_frames(tmp_path, n=1)
    with pytest.raises(GeosegError, match="valannot"):
        (tmp_path / "val").mkdir()
        CamVidDataset(tmp_path, "val")
    (tmp_path / "trainannot" / "seq_000.png").unlink()
    with pytest.raises(GeosegError, match="has no label file"):
        CamVidDataset(tmp_path, "train")


def test_config_source_camvid_builds_the_reader(tmp_path: Path) -> None:
    _write_frames(tmp_path, "train")
    _write_frames(tmp_path, "val", n=1)
    data = DataConfig(source="camvid", root=tmp_path, size=(8, 8))
    val = build_frame_dataset(data, "val")
    assert val[0]["image"].shape == (3, 8, 8)
    assert dataset_classes(val) == (0, 1, 2, 3, 4, 5, 6)
    with pytest.raises(ConfigError, match="unknown class"):
        DataConfig(source="camvid", root=tmp_path, label_map={0: "pedestrian"})
    with pytest.raises(ConfigError, match="only for source=cityscapes or camvid"):
        DataConfig(source="synth", label_map={0: "road"})
