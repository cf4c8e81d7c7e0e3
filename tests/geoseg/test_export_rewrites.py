"""Export rewrites (geoseg.export_rewrites): each rewritten module against the original, in torch."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from geoseg.export_rewrites import (
    DepthwisePReLU,
    SubPixelTransposedConv,
    depth_to_space,
    rewrite_for_onnxruntime,
    switch_mask,
    window_priority,
)
from geoseg.models import get_model
from geoseg.models.enet import DownsamplingBottleneck


def _randomise(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Batch-norm statistics and PReLU slopes away from their initial values (folding is tested
    only when they matter), slopes of both signs and above 1 as training can leave them."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.copy_(torch.rand(m.num_features, generator=gen) - 0.5)
                m.running_var.copy_(0.5 + 1.5 * torch.rand(m.num_features, generator=gen))
                m.weight.copy_(0.5 + torch.rand(m.num_features, generator=gen))
                m.bias.copy_(0.4 * torch.rand(m.num_features, generator=gen) - 0.2)
            if isinstance(m, torch.nn.PReLU):
                m.weight.copy_(2.0 * torch.rand(m.weight.shape, generator=gen) - 0.5)
    return model.eval()


def test_switch_mask_marks_torchs_pooling_index_even_on_ties() -> None:
    # small integers: most windows hold ties
    x = torch.randint(0, 3, (2, 5, 8, 10), generator=torch.Generator().manual_seed(0)).float()
    pooled, mask = switch_mask(x)
    expected_pooled, indices = F.max_pool2d(x, 2, 2, return_indices=True)
    expected = F.max_unpool2d(torch.ones_like(pooled), indices, 2, 2, output_size=x.shape[-2:])
    assert torch.equal(pooled, expected_pooled)
    assert torch.equal(mask, expected)
    assert mask.reshape(2, 5, 4, 2, 5, 2).sum((3, 5)).eq(1).all()  # one switch per window


def test_depth_to_space_is_an_exact_pixel_shuffle() -> None:
    packed = torch.randn(2, 12, 3, 4, generator=torch.Generator().manual_seed(3)) * 1e3
    assert torch.equal(depth_to_space(packed), F.pixel_shuffle(packed, 2))  # copies: bit-exact


def test_window_priority_ranks_each_window_in_row_major_order() -> None:
    rank = window_priority(4, 6, torch.float32)
    y, x = torch.meshgrid(torch.arange(4), torch.arange(6), indexing="ij")
    assert torch.equal(rank, (4 - 2 * (y % 2) - x % 2).float())


@pytest.mark.parametrize("slopes", [1, 6])
@pytest.mark.parametrize("shape", [(3, 6, 5, 4), (3, 6)])
def test_depthwise_prelu_matches_prelu(slopes: int, shape: tuple[int, ...]) -> None:
    prelu = torch.nn.PReLU(slopes)
    with torch.no_grad():
        prelu.weight.copy_(torch.linspace(-0.5, 1.5, slopes))
    x = torch.randn(*shape, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(DepthwisePReLU(prelu)(x), prelu(x), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("with_bn", [False, True])
def test_sub_pixel_transposed_conv_matches_conv_transpose(with_bn: bool) -> None:
    torch.manual_seed(2)
    conv = torch.nn.ConvTranspose2d(5, 7, 3, stride=2, padding=1, output_padding=1, bias=True)
    bn = _randomise(torch.nn.Sequential(torch.nn.BatchNorm2d(7)))[0] if with_bn else None
    x = torch.randn(2, 5, 6, 9)
    with torch.no_grad():
        expected = bn(conv(x)) if bn is not None else conv(x)
        got = SubPixelTransposedConv(conv, bn)(x)
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
        relu = SubPixelTransposedConv(conv, bn, relu=True)(x)
        torch.testing.assert_close(relu, expected.clamp_min(0), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="3x3 stride-2"):
        SubPixelTransposedConv(torch.nn.ConvTranspose2d(5, 7, 2, stride=2))


@pytest.mark.parametrize("name", ["enet", "joint"])
def test_rewritten_models_match_the_originals(name: str) -> None:
    torch.manual_seed(3)
    model = _randomise(get_model(name), seed=3)
    rewritten = rewrite_for_onnxruntime(model)
    assert rewritten is not model
    assert any(isinstance(m, torch.nn.PReLU) for m in model.modules())  # original untouched
    x = torch.randn(2, 3, 37, 50, generator=torch.Generator().manual_seed(4))  # not multiples of 8
    with torch.no_grad():
        expected, got = model(x), rewritten(x)
    assert set(got) == set(expected)
    for key in expected:
        torch.testing.assert_close(got[key], expected[key], rtol=1e-4, atol=1e-4)


def test_rewrite_leaves_other_models_alone_and_rejects_half_an_enet() -> None:
    naive = get_model("naive_cnn")
    assert rewrite_for_onnxruntime(naive) is naive
    with pytest.raises(ValueError, match="downsampling without upsampling"):
        rewrite_for_onnxruntime(torch.nn.Sequential(DownsamplingBottleneck(16, 64)))


def test_unit_normals_export_form_matches_normalize_zero_vectors_included() -> None:
    from geoseg.export_rewrites import UnitNormalsForExport
    from geoseg.models.joint import UnitNormals

    raw = torch.randn(2, 3, 5, 7, generator=torch.Generator().manual_seed(6)) * 10
    raw[0, :, 1, 2] = 0.0  # a zero vector: eps keeps it finite (zero)
    raw[1, :, 3, 4] = 1e-8
    unit = UnitNormals()
    got = UnitNormalsForExport(unit)(raw)
    torch.testing.assert_close(got, unit(raw), rtol=1e-6, atol=1e-7)
    assert torch.equal(got[0, :, 1, 2], torch.zeros(3))


def test_pixel_shuffle_conv_transpose_matches_the_2x2_transposed_conv() -> None:
    from geoseg.export_rewrites import PixelShuffleConvTranspose

    torch.manual_seed(0)
    conv = nn.ConvTranspose2d(16, 5, 2, stride=2)
    x = torch.randn(2, 16, 7, 9)
    torch.testing.assert_close(PixelShuffleConvTranspose(conv)(x), conv(x), atol=1e-5, rtol=1e-5)
    assert not PixelShuffleConvTranspose.applies(nn.ConvTranspose2d(4, 4, 3, stride=2))
