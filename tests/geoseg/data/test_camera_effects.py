"""Camera effects change the image, never the labels or normals, and are reproducible."""

import dataclasses

import numpy as np
import pytest
import torch

from geoseg.data.camera_effects import (
    REALISTIC,
    CameraEffects,
    CameraEffectsConfig,
    apply_camera_effects,
)
from geoseg.errors import ConfigError

EFFECTS = ("exposure", "white_balance", "vignetting", "defocus", "motion_blur", "noise", "jpeg")


def _sample() -> dict:
    g = torch.Generator().manual_seed(0)
    image = torch.rand(3, 24, 32, generator=g) * 0.6 + 0.2
    image[:, :, 16:] *= 0.5  # an edge for the blurs
    labels = torch.randint(0, 8, (24, 32), generator=g)
    normals = torch.nn.functional.normalize(torch.randn(3, 24, 32, generator=g), dim=0)
    return {"image": image, "labels": labels, "normals": normals}


@pytest.mark.parametrize("effect", EFFECTS)
def test_each_effect_changes_the_image_and_nothing_else(effect: str) -> None:
    cfg = CameraEffectsConfig(**{f"p_{effect}": 1.0})
    sample = _sample()
    torch.manual_seed(1)
    out = CameraEffects(cfg)(sample)
    assert out["image"].shape == sample["image"].shape and out["image"].dtype == torch.float32
    assert (out["image"] - sample["image"]).abs().max() > 1e-3, effect
    assert 0.0 <= float(out["image"].min()) and float(out["image"].max()) <= 1.0
    assert torch.equal(out["labels"], sample["labels"])
    assert torch.equal(out["normals"], sample["normals"])


def test_off_by_default_and_reproducible_with_a_seed() -> None:
    image = _sample()["image"].permute(1, 2, 0).numpy()
    assert not CameraEffectsConfig().enabled
    assert np.array_equal(apply_camera_effects(image, CameraEffectsConfig()), image)
    torch.manual_seed(3)
    a = apply_camera_effects(image, REALISTIC)
    torch.manual_seed(3)
    b = apply_camera_effects(image, REALISTIC)
    assert np.array_equal(a, b)


def test_vignetting_darkens_the_corners_not_the_centre() -> None:
    image = np.full((25, 33, 3), 0.5, np.float32)
    cfg = CameraEffectsConfig(p_vignetting=1.0, vignetting=(0.4, 0.4))
    out = apply_camera_effects(image, cfg)
    assert out[12, 16, 0] == pytest.approx(0.5) and out[0, 0, 0] == pytest.approx(0.5 * 0.6)


def test_bad_options_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="p_noise"):
        CameraEffectsConfig(p_noise=1.5)
    with pytest.raises(ConfigError, match="jpeg_quality"):
        CameraEffectsConfig(jpeg_quality=(90, 20))
    assert dataclasses.replace(REALISTIC, p_jpeg=0.0).enabled


def test_training_frames_get_the_effects_when_configured(tmp_path) -> None:
    import cv2

    from geoseg.config import load_config
    from training.common import describe_data
    from training.config import TrainConfig
    from training.frame_data import build_frame_dataset

    for folder in ("train", "trainannot"):
        (tmp_path / folder).mkdir()
    rgb = np.random.default_rng(0).integers(40, 200, (16, 24, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "train" / "f.png"), rgb)
    cv2.imwrite(str(tmp_path / "trainannot" / "f.png"), np.full((16, 24), 3, np.uint8))
    camera = {"p_noise": 1.0, "noise_std": [0.05, 0.05]}
    data = {"source": "camvid", "root": str(tmp_path), "size": [16, 24]}
    cfg = load_config(TrainConfig, {"data": data | {"augment": {"hflip": 0.0, "camera": camera}}})
    assert describe_data(cfg.data)["augment"]["camera"]["p_noise"] == 1.0
    noisy = build_frame_dataset(cfg.data, "train", normalize=False)[0]
    clean = build_frame_dataset(cfg.data, "train", augment=False, normalize=False)[0]
    assert (noisy["image"] - clean["image"]).abs().mean() > 0.01
    assert torch.equal(noisy["labels"], clean["labels"])
