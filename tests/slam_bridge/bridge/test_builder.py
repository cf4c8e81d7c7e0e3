"""The bridge built from settings: the networks it accepts, the association it wires."""

from __future__ import annotations

import dataclasses
import json
import operator
from types import SimpleNamespace

import numpy as np
import pytest

from geoseg.classes import NUM_CLASSES
from geoseg.dirichlet import load_filter
from geoseg.errors import GeosegError
from geoseg.pretrained import pretrained_dir, pretrained_file
from slam_bridge.bridge.builder import (
    BridgeConfig,
    build_bridge,
    check_network,
    colour_transfer_of,
    load_dirichlet_filter,
    load_network,
    resolve_weights,
)
from slam_bridge.bridge.facades import Facades
from slam_bridge.bridge.worker import segmenter_outputs
from slam_bridge.errors import SlamError


class FakeSegmenter:
    """Uniform probabilities over ``classes`` at ``map_size``, normals facing the camera."""

    def __init__(self, classes=NUM_CLASSES, map_size=(320, 240), normals=True):
        self.classes, self.map_size, self.normals = classes, map_size, normals
        self.seen = []

    def __call__(self, image):
        self.seen.append(image.shape)
        w, h = self.map_size
        probs = np.full((1, self.classes, h, w), 1.0 / self.classes, np.float32)
        normals = np.zeros((1, 3, h, w), np.float32)
        normals[:, 2] = -1.0
        return SimpleNamespace(probabilities=probs, normals=normals if self.normals else None)


@pytest.fixture
def facades():
    return Facades(
        p0=np.array([[0.0, 0.0]]), p1=np.array([[10.0, 0.0]]), z_min=np.array([0.0]),
        z_max=np.array([8.0]), normal=np.array([[0.0, -1.0, 0.0]]), d=np.array([0.0]),
        true_facade_id=np.array([-1]),
    )  # fmt: skip


def test_config_refuses_an_unknown_association():
    with pytest.raises(SlamError, match="association"):
        BridgeConfig(association="guess")


@pytest.mark.parametrize(
    ("fake", "needs_normals", "message"),
    [
        (FakeSegmenter(classes=5), False, "5 classes.*building"),
        (FakeSegmenter(map_size=(100, 100)), False, "another aspect ratio"),
        (FakeSegmenter(normals=False), True, "no normals"),
    ],
)
def test_a_network_the_bridge_cannot_use_is_refused(fake, needs_normals, message):
    with pytest.raises(SlamError, match=message):
        check_network(segmenter_outputs(fake, (320, 240)), (640, 480), needs_normals)


def test_a_usable_network_passes_at_its_training_size():
    fake = FakeSegmenter()
    check_network(segmenter_outputs(fake, (320, 240)), (640, 480), needs_normals=True)
    assert fake.seen == [(240, 320, 3)]  # resized to the network's size first


def test_the_network_may_be_named_by_its_shipped_weights():
    grey = np.full((240, 320, 3), 128, np.uint8)
    named = load_network("bayes", "normals_real")(grey)
    by_folder = load_network("bayes", pretrained_dir("normals_real"))(grey)
    assert named.normals is not None and np.array_equal(named.labels, by_folder.labels)
    with pytest.raises(GeosegError, match="no_such_weights"):
        load_network("bayes", "no_such_weights")


def test_real_names_the_network_for_photographs(monkeypatch, tmp_path):
    from geoseg import pretrained

    monkeypatch.setattr(pretrained, "USER_WEIGHTS_DIR", tmp_path)  # street not installed
    assert resolve_weights("bayes", "real") == "normals_real"
    assert resolve_weights("dirichlet", "real") == "naive_real"
    assert resolve_weights("bayes", "normals") == "normals"
    assert resolve_weights("bayes", None) is None
    grey = np.full((240, 320), 128, np.uint8)  # a monochrome camera's frame
    real = load_network("bayes", "real")(grey)
    assert real.normals is not None
    assert np.array_equal(real.labels, load_network("bayes", "normals_real")(grey).labels)
    assert BridgeConfig(network="real").network == "real"


def test_the_dirichlet_filter_follows_the_naive_network(tmp_path, caplog):
    """Each shipped naive CNN gets the filter calibrated on it; a user's network the shipped
    one, with a warning; a filter may be given by name, folder or file."""
    shipped = load_filter(pretrained_file("dirichlet", "dirichlet.json"))
    real = load_filter(pretrained_file("dirichlet_real", "dirichlet.json"))
    assert not np.allclose(shipped.alpha, real.alpha)
    assert np.array_equal(load_dirichlet_filter().alpha, shipped.alpha)
    assert np.array_equal(load_dirichlet_filter(None, "naive_real").alpha, real.alpha)
    assert load_dirichlet_filter(None, "naive_real").threshold == real.threshold
    by_file = load_dirichlet_filter(None, pretrained_file("naive_real", "model.onnx"))
    assert np.array_equal(by_file.alpha, real.alpha)
    for given in ("dirichlet_real", pretrained_dir("dirichlet_real"), real):
        assert np.array_equal(load_dirichlet_filter(given, "naive").alpha, real.alpha)
    assert "calibrated on the shipped naive CNN" not in caplog.text
    with caplog.at_level("WARNING"):
        user = load_dirichlet_filter(None, tmp_path / "my_naive.onnx")
    assert np.array_equal(user.alpha, shipped.alpha)
    assert "calibrated on the shipped naive CNN" in caplog.text
    with pytest.raises(GeosegError, match="no such filter"):
        load_dirichlet_filter(tmp_path / "none.json")


def test_the_dirichlet_association_takes_the_filter_of_its_network(facades):
    cfg = BridgeConfig(association="dirichlet", asynchronous=False)
    worker = build_bridge(cfg, facades, image_size=(320, 240), weights="naive_real")
    try:
        real = load_filter(pretrained_file("dirichlet_real", "dirichlet.json"))
        assert np.array_equal(worker.smooth_at.__self__.alpha, real.alpha)
    finally:
        worker.close()


def test_build_bridge_checks_before_the_run(facades):
    with pytest.raises(SlamError, match="building"):
        build_bridge(BridgeConfig(), facades, image_size=(640, 480), segmenter=FakeSegmenter(3))
    with pytest.raises(SlamError, match="mesh"):
        build_bridge(BridgeConfig(association="raycast"), facades, image_size=(640, 480))


def test_build_bridge_wires_the_association_and_the_constraints(facades):
    worker = build_bridge(
        BridgeConfig(window_weight=3.0, asynchronous=False), facades, image_size=(640, 480),
        segmenter=FakeSegmenter(),
    )  # fmt: skip
    assert worker.constraints.window_weight == 3.0 and worker.smooth_at is not None
    probs, normals = worker.network(np.zeros((480, 640, 3), np.uint8))
    assert probs.shape == (240, 320, NUM_CLASSES) and normals.shape == (240, 320, 3)
    # a building-labelled point 1 m in front of the facade, its normal towards the street
    snapshot = SimpleNamespace(
        points=np.array([[5.0, -1.0, 2.0]]), labels=np.array([2]),
        normals=np.array([[0.0, -1.0, 0.0]]), mean_probs=None, centres=None,
    )  # fmt: skip
    a = worker.associate(snapshot)
    assert a.method == "bayes" and a.facade.tolist() == [0]
    worker.close()


def test_process_worker_gives_what_the_inline_network_gives(facades):
    """The asynchronous worker's child process builds the shipped network from its recipe and
    answers as the same network run inline."""
    image = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    call = operator.methodcaller("__call__", image)  # fn(network) = network(image), picklable
    inline = build_bridge(BridgeConfig(asynchronous=False), facades, image_size=(640, 480))
    child = build_bridge(BridgeConfig(worker="process"), facades, image_size=(640, 480))
    try:
        assert child.in_process and child.network is None and not inline.in_process
        (p_child, n_child), (p_inline, n_inline) = (
            child.call_network(call),
            inline.call_network(call),
        )
        assert p_child.shape == (240, 320, NUM_CLASSES) and n_child.shape == (240, 320, 3)
        np.testing.assert_allclose(p_child, p_inline, atol=1e-5)
        np.testing.assert_allclose(n_child, n_inline, atol=1e-5)
    finally:
        child.close()
        inline.close()


def test_process_worker_raises_a_bad_network_in_the_parent(facades, tmp_path):
    """Weights the child cannot load, or a network the bridge cannot use, raise their own clear
    error from build_bridge (not a broken process pool)."""
    missing = tmp_path / "missing.onnx"
    with pytest.raises(GeosegError, match="missing.onnx"):
        build_bridge(BridgeConfig(), facades, image_size=(640, 480), weights=missing)
    with pytest.raises(SlamError, match="no normals"):
        build_bridge(
            BridgeConfig(), facades, image_size=(640, 480),
            weights=pretrained_file("naive", "model.onnx"),
        )  # fmt: skip


def test_config_refuses_an_unknown_worker():
    with pytest.raises(SlamError, match="worker"):
        BridgeConfig(worker="cluster")


def test_online_associations_must_cover_the_fusion_window():
    from slam_bridge.slam.config import SlamConfig
    from slam_bridge.slam.windows import WindowConfig
    from slam_bridge.system.image_slam import ImageSlamConfig

    window = WindowConfig(l=20, n=10, history_keyframes=10)
    ImageSlamConfig(slam=SlamConfig(window=window), bridge=BridgeConfig(recent_keyframes=30))
    with pytest.raises(SlamError, match="recent_keyframes: 29 keyframes do not cover"):
        ImageSlamConfig(slam=SlamConfig(window=window), bridge=BridgeConfig(recent_keyframes=29))
    with pytest.raises(SlamError, match="recent_keyframes"):
        BridgeConfig(recent_keyframes=0)


class RecordingSegmenter(FakeSegmenter):
    """A :class:`FakeSegmenter` that keeps the images it is given."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.images = []

    def __call__(self, image):
        self.images.append(image)
        return super().__call__(image)


def _warm_image(seed: int, shape=(480, 640)) -> np.ndarray:
    """A textured image with a warm, dark cast (red up, blue down)."""
    rng = np.random.default_rng(seed)
    grey = rng.uniform(0.1, 0.9, shape)[..., None] * np.array([1.0, 0.8, 0.5])
    return np.round(np.clip(grey + rng.normal(0, 0.05, (*shape, 3)), 0, 1) * 255).astype(np.uint8)


def test_colour_transfer_gives_the_network_the_references_colours(facades, tmp_path):
    """The network sees each keyframe with the statistics of the reference image."""
    import cv2

    from geoseg.colour_transfer import colour_statistics

    rng = np.random.default_rng(5)
    reference = np.round(rng.uniform(0.3, 0.7, (60, 80, 3)) * [[[0.6, 0.8, 1.0]]] * 255)
    cv2.imwrite(str(tmp_path / "ref.png"), reference.astype(np.uint8)[..., ::-1])  # BGR file
    target = colour_statistics(reference.astype(np.uint8))
    fake = RecordingSegmenter()
    cfg = BridgeConfig(colour_transfer=str(tmp_path / "ref.png"), asynchronous=False)
    worker = build_bridge(cfg, facades, image_size=(640, 480), segmenter=fake)
    try:
        worker.network(_warm_image(0))
    finally:
        worker.close()
    seen = colour_statistics(fake.images[-1])
    assert fake.images[-1].shape == (240, 320, 3)  # resized, then mapped
    np.testing.assert_allclose(seen.mean, target.mean, atol=0.005)
    np.testing.assert_allclose(seen.std, target.std, rtol=0.1, atol=0.002)
    # without the setting, the network sees the keyframe's own colours, far from the reference's
    plain = RecordingSegmenter()
    build_bridge(
        BridgeConfig(asynchronous=False), facades, image_size=(640, 480), segmenter=plain
    ).network(_warm_image(0))
    off = np.abs(np.subtract(colour_statistics(plain.images[-1]).mean, target.mean))
    assert off.max() > 0.03


def test_colour_means_only_keeps_the_keyframes_contrast(facades):
    from geoseg.colour_transfer import colour_statistics, statistics_from_card

    cfg = BridgeConfig(colour_transfer="card", colour_means_only=True, asynchronous=False)
    transfer = colour_transfer_of(cfg)
    card = json.loads(pretrained_file("normals", "model_card.json").read_text())
    assert transfer.target == statistics_from_card(card) and not transfer.match_std
    image = _warm_image(1, (60, 80))
    own, mapped = colour_statistics(image), colour_statistics(transfer(image))
    np.testing.assert_allclose(mapped.mean, transfer.target.mean, atol=0.02)
    np.testing.assert_allclose(mapped.std[0], own.std[0], rtol=0.1)  # contrast kept


def test_colour_card_reads_the_card_of_the_networks_weights(tmp_path):
    from geoseg.colour_transfer import CARD_KEY, ColourStatistics

    folder = tmp_path / "net"
    folder.mkdir()
    stats = ColourStatistics(mean=(-1.0, 0.01, 0.0), std=(0.4, 0.05, 0.01))
    (folder / "model_card.json").write_text(json.dumps({CARD_KEY: stats.as_dict()}))
    cfg = BridgeConfig(colour_transfer="card")
    assert colour_transfer_of(cfg, weights=folder).target == stats
    assert colour_transfer_of(cfg, segmenter=SimpleNamespace(source=folder / "x.onnx")).target == (
        stats
    )
    assert colour_transfer_of(BridgeConfig(association="raycast", colour_transfer="card")) is None
    assert colour_transfer_of(BridgeConfig()) is None


@pytest.mark.parametrize(
    ("reference", "message"),
    [
        ("missing.png", "no such colour reference"),
        ("empty_dir", "without images"),
        ("notes.json", "expected"),
        ("card", "names no weights file"),
    ],
)
def test_a_bad_colour_reference_is_refused_before_the_run(facades, tmp_path, reference, message):
    (tmp_path / "empty_dir").mkdir()
    (tmp_path / "notes.json").write_text('{"hello": 1}')
    ref = reference if reference == "card" else str(tmp_path / reference)
    fake = RecordingSegmenter()
    with pytest.raises(SlamError, match=message) as err:
        build_bridge(
            BridgeConfig(colour_transfer=ref, asynchronous=False), facades, image_size=(640, 480),
            segmenter=fake,
        )  # fmt: skip
    assert "bridge.colour_transfer" in str(err.value) and not fake.images  # nothing ran


def test_the_child_process_network_maps_its_inputs_as_the_inline_one(facades):
    image = _warm_image(2)
    call = operator.methodcaller("__call__", image)
    cfg = BridgeConfig(colour_transfer="card")
    inline = build_bridge(
        dataclasses.replace(cfg, asynchronous=False), facades, image_size=(640, 480)
    )
    child = build_bridge(cfg, facades, image_size=(640, 480))
    plain = build_bridge(BridgeConfig(asynchronous=False), facades, image_size=(640, 480))
    try:
        (p_child, _), (p_inline, _), (p_plain, _) = (
            child.call_network(call), inline.call_network(call), plain.call_network(call),
        )  # fmt: skip
        np.testing.assert_allclose(p_child, p_inline, atol=1e-5)
        assert np.abs(p_plain - p_inline).max() > 0.05  # the transfer changed what it saw
    finally:
        for worker in (child, inline, plain):
            worker.close()


def test_config_refuses_an_empty_colour_reference():
    with pytest.raises(SlamError, match="colour_transfer"):
        BridgeConfig(colour_transfer="")
