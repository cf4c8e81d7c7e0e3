"""ENet: shapes at several sizes, parameter count, gradients, input validation."""

import pytest
import torch

from geoseg.errors import GeosegError
from geoseg.models.enet import ENet, count_parameters, enet


@pytest.fixture(scope="module")
def model() -> ENet:
    torch.manual_seed(0)
    return enet(num_classes=8)


@pytest.mark.parametrize("size", [(64, 48), (37, 50), (16, 24), (5, 3)])
def test_shapes(model: ENet, size: tuple[int, int]) -> None:
    h, w = size
    model.eval()
    with torch.no_grad():
        out = model(torch.randn(2, 3, h, w))
    assert set(out) == {"logits", "features"}
    assert out["logits"].shape == (2, 8, h, w)
    assert out["features"].shape == (2, 128, -(-h // 8), -(-w // 8))
    assert torch.isfinite(out["logits"]).all()


def test_parameter_count_matches_paper() -> None:
    n = count_parameters(enet(num_classes=8))
    assert 340_000 <= n <= 390_000, n
    assert n == 359_199  # the figure quoted in the docs


def test_num_classes_changes_only_the_output() -> None:
    out = enet(num_classes=5).eval()(torch.randn(1, 3, 16, 16))
    assert out["logits"].shape == (1, 5, 16, 16)


def test_backprop_reaches_every_parameter() -> None:
    torch.manual_seed(1)
    m = enet(num_classes=8).train()
    out = m(torch.randn(2, 3, 32, 40))
    (out["logits"].square().mean() + out["features"].mean()).backward()
    for name, p in m.named_parameters():
        assert p.grad is not None, name
        assert p.grad.abs().sum() > 0, name


def test_padding_crops_back_consistently(model: ENet) -> None:
    """The top-left of a padded input sees the same computation as the cropped input."""
    model.eval()
    x = torch.randn(1, 3, 37, 50)
    with torch.no_grad():
        a = model(x)["logits"]
        b = model(torch.nn.functional.pad(x, (0, 6, 0, 3), mode="replicate"))["logits"]
    torch.testing.assert_close(a, b[..., :37, :50])


@pytest.mark.parametrize(
    "bad, match",
    [
        (torch.randn(1, 4, 16, 16), "3 channels"),
        (torch.randn(16, 16), "4-D"),
        (torch.randint(0, 255, (1, 3, 16, 16)), "floating-point"),
        (torch.full((1, 3, 16, 16), float("nan")), "NaN"),
        ("not a tensor", "torch.Tensor"),
    ],
)
def test_bad_inputs_raise_value_error(model: ENet, bad, match: str) -> None:
    with pytest.raises(GeosegError, match=match):
        model(bad)
    with pytest.raises(ValueError):
        model(bad)
