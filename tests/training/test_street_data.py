"""The real-photo recipe's data: grey augmentation and the CamVid split held out for selection."""

import cv2
import numpy as np
import pytest
import torch

from geoseg.errors import ConfigError, GeosegError
from training.camvid_holdout import make_holdout, sequence_of
from training.config import DataConfig
from training.frame_data import LUMA_WEIGHTS, RandomGrayscale, build_frame_dataset


def test_random_grayscale_is_luma_on_three_channels() -> None:
    torch.manual_seed(0)
    image = torch.rand(3, 5, 7)
    out = RandomGrayscale(1.0)({"image": image, "labels": torch.zeros(5, 7)})
    luma = sum(w * image[c] for c, w in enumerate(LUMA_WEIGHTS))
    for c in range(3):
        torch.testing.assert_close(out["image"][c], luma)
    assert RandomGrayscale(0.0)({"image": image})["image"] is image
    torch.manual_seed(1)
    grey = [
        bool((RandomGrayscale(0.3)({"image": image})["image"][0] == luma).all()) for _ in range(400)
    ]
    assert 0.2 < np.mean(grey) < 0.4


def test_grayscale_probability_checked() -> None:
    with pytest.raises(ConfigError, match="grayscale"):
        DataConfig(grayscale=1.5)


def _camvid(root, split: str, names: list[str]) -> None:
    (root / split).mkdir(parents=True)
    (root / f"{split}annot").mkdir()
    rng = np.random.default_rng(0)
    for name in names:
        cv2.imwrite(str(root / split / f"{name}.png"), rng.integers(0, 256, (16, 24, 3), np.uint8))
        cv2.imwrite(str(root / f"{split}annot" / f"{name}.png"), np.full((16, 24), 3, np.uint8))


def test_holdout_moves_whole_sequences_to_select(tmp_path) -> None:
    src = tmp_path / "camvid"
    _camvid(src, "train", ["0001TP_000010", "0001TP_000020", "0006R0_000030"])
    _camvid(src, "val", ["0016E5_000040"])
    out = make_holdout(src, tmp_path / "split", held_out=["0001TP"])
    assert sorted(p.stem for p in (out / "train").iterdir()) == ["0006R0_000030"]
    assert sorted(p.stem for p in (out / "select").iterdir()) == ["0001TP_000010", "0001TP_000020"]
    assert sorted(p.stem for p in (out / "valannot").iterdir()) == ["0016E5_000040"]
    make_holdout(src, tmp_path / "split", held_out=["0001TP"])  # existing links: skipped
    data = DataConfig(source="camvid", root=out, val_split="select", size=(16, 24), grayscale=1.0)
    train = build_frame_dataset(data, "train", normalize=False)
    sample = train[0]
    assert sample["image"].shape == (3, 16, 24)
    torch.testing.assert_close(sample["image"][0], sample["image"][2])  # grey on all channels
    assert len(build_frame_dataset(data, "val")) == 2  # the held-out sequence
    assert sequence_of("0016E5_000040") == "0016E5"
    with pytest.raises(GeosegError, match="no frame of sequence"):
        make_holdout(src, tmp_path / "other", held_out=["Seq05VD"])
    with pytest.raises(GeosegError, match="no training sequence"):
        make_holdout(src, tmp_path / "other", held_out=["0001TP", "0006R0"])


def test_normals_head_starts_from_another_joint_network(tmp_path) -> None:
    from geoseg.infer import save_model_checkpoint
    from geoseg.models import get_model
    from training.normals import load_normal_head

    torch.manual_seed(0)
    source = get_model("joint", num_classes=8)
    path = save_model_checkpoint(source, tmp_path / "j.pt", model_name="joint")
    target = get_model("joint", num_classes=8)
    load_normal_head(target, path)
    for key, value in source.normal_head.state_dict().items():
        torch.testing.assert_close(target.normal_head.state_dict()[key], value)
    enet = save_model_checkpoint(get_model("enet"), tmp_path / "e.pt", model_name="enet")
    with pytest.raises(GeosegError, match="normals_init"):
        load_normal_head(target, enet)
