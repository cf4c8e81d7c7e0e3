"""Monochrome cameras: grey images through the Segmenter (torch and onnxruntime), the image
reader and the layer-21 embedder give what their three-channel replicates give."""

import cv2
import numpy as np
import pytest
import torch

from geoseg.errors import GeosegError
from geoseg.export import export_onnx
from geoseg.infer import Segmenter, as_rgb, save_model_checkpoint
from geoseg.models import get_model
from geoseg.reloc.image_base import Layer21Embedder, read_rgb


@pytest.fixture(scope="module")
def segmenters(tmp_path_factory):
    root = tmp_path_factory.mktemp("grey")
    torch.manual_seed(3)
    model = get_model("joint", num_classes=8).eval()
    ckpt = save_model_checkpoint(model, root / "joint.pt", model_name="joint")
    onnx_path = export_onnx(model, root / "joint.onnx")
    return (
        Segmenter.from_checkpoint(ckpt),
        Segmenter.from_onnx(onnx_path, providers=["CPUExecutionProvider"]),
    )


def _grey(n: int = 2, h: int = 33, w: int = 45) -> np.ndarray:
    return np.random.default_rng(1).integers(0, 256, (n, h, w), dtype=np.uint8)


def test_as_rgb_shapes() -> None:
    g = _grey()
    rgb = np.repeat(g[..., None], 3, axis=-1)
    for given in (g, g[..., None]):
        np.testing.assert_array_equal(as_rgb(given), rgb)
    for given in (g[0], g[0][..., None]):
        np.testing.assert_array_equal(as_rgb(given), rgb[:1])
    np.testing.assert_array_equal(as_rgb(rgb), rgb)
    np.testing.assert_array_equal(as_rgb(rgb[0]), rgb[:1])
    for bad in (np.zeros((2, 8, 8, 2), np.uint8), np.zeros((8,), np.uint8)):
        with pytest.raises(GeosegError, match="grey"):
            as_rgb(bad)


@pytest.mark.parametrize("backend", [0, 1], ids=["torch", "onnxruntime"])
def test_grey_image_segments_as_its_replicate(segmenters, backend) -> None:
    seg = segmenters[backend]
    g = _grey()
    want = seg(np.repeat(g[..., None], 3, axis=-1))
    for given in (g, g[..., None]):
        got = seg(given)
        np.testing.assert_array_equal(got.labels, want.labels)
        np.testing.assert_allclose(got.probabilities, want.probabilities, atol=1e-6)
        np.testing.assert_allclose(got.normals, want.normals, atol=1e-6)
    one = seg(g[0])
    assert one.labels.shape == (1, 33, 45)
    np.testing.assert_array_equal(one.labels[0], want.labels[0])


def test_grey_file_reads_as_replicated_rgb(tmp_path) -> None:
    g = _grey(1)[0]
    cv2.imwrite(str(tmp_path / "g.png"), g)
    rgb = read_rgb(tmp_path / "g.png")
    assert rgb.shape == (33, 45, 3)
    np.testing.assert_array_equal(rgb, np.repeat(g[..., None], 3, axis=-1))


def test_layer21_embedding_of_a_grey_image(segmenters) -> None:
    embed = Layer21Embedder(segmenters[0], output_size=(2, 2), name=None)
    g = _grey(1)[0]
    np.testing.assert_allclose(
        embed([g]), embed([np.repeat(g[..., None], 3, axis=-1)]), rtol=1e-5, atol=1e-6
    )
