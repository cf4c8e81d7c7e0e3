"""Naive patch classifier: tables, shapes, dense == patch classifier, gradients, bad inputs."""

import numpy as np
import pytest
import torch

from geoseg.errors import GeosegError
from geoseg.models.enet import count_parameters
from geoseg.models.naive_cnn import (
    PATCH_SIZE,
    NaiveDense,
    extract_patches,
    naive_cnn,
    random_table,
)


def test_random_table_is_seeded_and_sparse() -> None:
    t = random_table(16, 64, 8, seed=0)
    assert t.shape == (64, 8)
    assert all(len(set(row)) == 8 for row in t)
    np.testing.assert_array_equal(t, random_table(16, 64, 8, seed=0))
    assert not np.array_equal(t, random_table(16, 64, 8, seed=1))


def test_patch_classifier_shapes_and_sparsity() -> None:
    torch.manual_seed(0)
    m = naive_cnn()
    out = m(torch.randn(5, 3, PATCH_SIZE, PATCH_SIZE))
    assert out["log_probs"].shape == (5, 8)
    torch.testing.assert_close(out["log_probs"].exp().sum(1), torch.ones(5))
    w = m.conv2.dense_weight()
    assert (w.abs().sum((2, 3)) > 0).sum(1).eq(8).all()  # each output sees 8 of 16 inputs
    assert count_parameters(m) == 2_368 + 25_152 + 401_664 + 131_584 + 4_104


@pytest.mark.parametrize("size", [(37, 50), (8, 8)])
def test_dense_equals_patch_classifier(size: tuple[int, int]) -> None:
    torch.manual_seed(1)
    m = naive_cnn().eval()
    h, w = size
    image = torch.randn(1, 3, h, w)
    with torch.no_grad():
        dense = m.dense(image)
        banded = m.dense(image, band_rows=5)
    assert dense.shape == (1, 8, h, w)
    torch.testing.assert_close(banded, dense)
    gen = torch.Generator().manual_seed(2)
    yx = torch.stack(
        [torch.randint(0, h, (12,), generator=gen), torch.randint(0, w, (12,), generator=gen)], 1
    )
    yx = torch.cat([yx, torch.tensor([[0, 0], [h - 1, w - 1]])])
    with torch.no_grad():
        patches = m(extract_patches(image[0], yx))["log_probs"]
    torch.testing.assert_close(dense[0, :, yx[:, 0], yx[:, 1]].T, patches, atol=1e-4, rtol=1e-4)
    out = NaiveDense(m)(image)
    torch.testing.assert_close(out["log_probs"], dense)


def test_backprop_reaches_every_parameter() -> None:
    torch.manual_seed(3)
    m = naive_cnn()
    m(torch.randn(4, 3, PATCH_SIZE, PATCH_SIZE))["log_probs"][:, 2].sum().backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_bad_inputs() -> None:
    m = naive_cnn()
    with pytest.raises(GeosegError, match="46"):
        m(torch.randn(1, 3, 32, 32))
    with pytest.raises(ValueError, match="floating-point"):
        m.dense(torch.zeros(1, 3, 8, 8, dtype=torch.uint8))
    with pytest.raises(ValueError, match="4-D"):
        m.dense(torch.zeros(3, 8, 8))
