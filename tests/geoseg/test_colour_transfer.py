"""Reinhard colour transfer: exact statistics on a synthetic pair, and its use by Segmenter."""

import json

import numpy as np
import pytest

from geoseg.colour_transfer import (
    CARD_KEY,
    ColourStatistics,
    ColourTransfer,
    colour_statistics,
    lab_to_rgb,
    rgb_to_lab,
    statistics_from_card,
    transfer_colour,
    transfer_lab,
)
from geoseg.errors import GeosegError
from geoseg.infer import Segmenter, colour_transfer_for


def _pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    source = rng.uniform(0.2, 0.8, (12, 16, 3))  # grey-ish, high contrast
    target = rng.uniform(0.1, 0.5, (9, 7, 3)) * np.array([1.0, 0.8, 0.55])  # dark, warm
    return source, target


def test_lab_round_trip_is_lossless_above_the_floor() -> None:
    source, _ = _pair()
    assert np.allclose(lab_to_rgb(rgb_to_lab(source)), source, atol=1e-12)


def test_transfer_gives_exactly_the_target_statistics() -> None:
    source, target = _pair()
    s_stats, t_stats = colour_statistics(source), colour_statistics(target)
    assert not np.allclose(s_stats.mean, t_stats.mean, atol=1e-2)
    mapped_lab = transfer_lab(rgb_to_lab(source), s_stats, t_stats)
    assert np.allclose(mapped_lab.reshape(-1, 3).mean(0), t_stats.mean, atol=1e-12)
    assert np.allclose(mapped_lab.reshape(-1, 3).std(0), t_stats.std, atol=1e-12)
    # and through RGB (the mapped image stays in gamut here, so nothing is clipped)
    rgb = lab_to_rgb(mapped_lab)
    assert rgb.min() > 0 and rgb.max() < 1
    back = colour_statistics(rgb)
    assert np.allclose(back.mean, t_stats.mean, atol=1e-9)
    assert np.allclose(back.std, t_stats.std, atol=1e-9)


def test_uint8_images_move_to_the_target_and_keep_shape() -> None:
    source, target = _pair()
    image = np.round(source * 255).astype(np.uint8)
    out = transfer_colour(image, colour_statistics(target))
    assert out.dtype == np.uint8 and out.shape == image.shape
    got = colour_statistics(out)
    assert np.allclose(got.mean, colour_statistics(target).mean, atol=0.02)


def test_a_sequence_source_maps_every_frame_the_same_way() -> None:
    source, target = _pair()
    frame_a = np.round(source * 255).astype(np.uint8)
    frame_b = frame_a.copy()
    frame_b[:4] = 30  # a dark patch changes this frame's own statistics
    fixed = ColourTransfer(colour_statistics(target)).fit_sequence([frame_a, frame_b])
    per_image = ColourTransfer(colour_statistics(target))
    # same pixel value, same output under a fixed source; not so frame by frame
    assert np.array_equal(fixed(frame_a)[4:], fixed(frame_b)[4:])
    assert not np.array_equal(per_image(frame_a)[4:], per_image(frame_b)[4:])


def test_statistics_round_trip_and_refusals() -> None:
    stats = ColourStatistics(mean=(-1.0, 0.1, 0.0), std=(0.2, 0.05, 0.01))
    assert ColourStatistics.from_dict(stats.as_dict()) == stats
    with pytest.raises(GeosegError, match="3 finite means"):
        ColourStatistics.from_dict({"mean": [0, 0], "std": [1, 1, 1]})
    with pytest.raises(GeosegError, match="records no 'colour_statistics'"):
        statistics_from_card({"model_name": "enet"})
    assert statistics_from_card({CARD_KEY: stats.as_dict()}) == stats


def test_segmenter_feeds_the_network_the_transferred_image(tmp_path) -> None:
    source, target = _pair()
    seen = []

    def backend(batch):
        seen.append(batch)
        return {"logits": np.zeros((batch.shape[0], 8) + batch.shape[2:], np.float32)}

    image = np.round(source * 255).astype(np.uint8)
    (tmp_path / "model_card.json").write_text(
        json.dumps({CARD_KEY: colour_statistics(target).as_dict()})
    )
    transfer = colour_transfer_for(tmp_path / "model.onnx")
    norm = {"mean": [0.0, 0.0, 0.0], "std": [1.0, 1.0, 1.0]}
    Segmenter(backend, normalization=norm)(image)
    Segmenter(backend, normalization=norm, colour_transfer=transfer)(image)
    plain, mapped = seen
    assert np.allclose(plain[0].transpose(1, 2, 0), image / 255.0, atol=1e-6)
    assert np.allclose(mapped[0].transpose(1, 2, 0), transfer(image) / 255.0, atol=1e-6)
    with pytest.raises(GeosegError, match="no images"):
        colour_transfer_for(tmp_path / "model.onnx", mode="sequence")
    with pytest.raises(GeosegError, match="no model card"):
        colour_transfer_for(tmp_path / "elsewhere" / "model.onnx")


def test_typical_statistics_are_medians_of_the_images_own() -> None:
    from geoseg.colour_transfer import typical_statistics

    rng = np.random.default_rng(1)
    day = [rng.uniform(0.3, 0.9, (8, 8, 3)) for _ in range(3)]
    night = [rng.uniform(0.0, 0.05, (8, 8, 3))]  # one very dark frame does not move the median
    typical = typical_statistics(day + night)
    own = np.array([colour_statistics(i).mean for i in day + night])
    assert np.allclose(typical.mean, np.median(own, axis=0))
    assert typical.mean[0] > colour_statistics(day + night).mean[0]


def test_mean_only_transfer_keeps_the_image_contrast() -> None:
    source, target = _pair()
    s_stats, t_stats = colour_statistics(source), colour_statistics(target)
    mapped = transfer_lab(rgb_to_lab(source), s_stats, t_stats, match_std=False).reshape(-1, 3)
    assert np.allclose(mapped.mean(0), t_stats.mean, atol=1e-12)
    assert np.allclose(mapped.std(0), s_stats.std, atol=1e-12)


def test_reference_statistics_of_an_image_a_folder_and_json(tmp_path) -> None:
    import cv2

    from geoseg.colour_transfer import reference_statistics, typical_statistics

    rng = np.random.default_rng(2)
    images = [np.round(rng.uniform(0.1, 0.9, (20, 30, 3)) * 255).astype(np.uint8) for _ in range(3)]
    (tmp_path / "drive" / "rgb").mkdir(parents=True)
    for i, image in enumerate(images):
        cv2.imwrite(str(tmp_path / "drive" / "rgb" / f"{i}.png"), image[..., ::-1])  # BGR file
    one = reference_statistics(tmp_path / "drive" / "rgb" / "1.png")
    assert np.allclose(one.mean, colour_statistics(images[1]).mean)
    assert np.allclose(
        reference_statistics(tmp_path / "drive").mean, typical_statistics(images).mean
    )
    stats = colour_statistics(images[0])
    (tmp_path / "stats.json").write_text(json.dumps(stats.as_dict()))
    (tmp_path / "model_card.json").write_text(json.dumps({CARD_KEY: stats.as_dict()}))
    assert reference_statistics(tmp_path / "stats.json") == stats
    assert reference_statistics(tmp_path / "model_card.json") == stats


def test_reference_statistics_refusals(tmp_path) -> None:
    from geoseg.colour_transfer import reference_statistics

    (tmp_path / "empty").mkdir()
    (tmp_path / "broken.png").write_bytes(b"not a png")
    (tmp_path / "list.json").write_text("[1, 2]")
    for path, message in (
        ("missing", "no such colour reference"),
        ("empty", "without images"),
        ("broken.png", "not a readable image"),
        ("list.json", "expected a JSON object"),
    ):
        with pytest.raises(GeosegError, match=message):
            reference_statistics(tmp_path / path)
