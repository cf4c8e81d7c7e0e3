"""Joint labels + normals network: shapes, unit normals, freezing, ENet initialisation."""

import pytest
import torch

from geoseg.errors import GeosegError
from geoseg.models.enet import count_parameters, enet
from geoseg.models.joint import JointNet, joint


@pytest.mark.parametrize("size", [(64, 48), (37, 50), (9, 13)])
def test_shapes_and_unit_normals(size: tuple[int, int]) -> None:
    torch.manual_seed(0)
    h, w = size
    m = joint(num_classes=8).eval()
    with torch.no_grad():
        out = m(torch.randn(2, 3, h, w))
    assert set(out) == {"logits", "normals", "features"}
    assert out["logits"].shape == (2, 8, h, w)
    assert out["normals"].shape == (2, 3, h, w)
    assert out["features"].shape == (2, 128, -(-h // 8), -(-w // 8))
    torch.testing.assert_close(out["normals"].norm(dim=1), torch.ones(2, h, w))


def test_normals_head_overhead() -> None:
    m = joint(num_classes=8)
    base = count_parameters(enet(num_classes=8))
    extra = count_parameters(m.normal_head)
    assert count_parameters(m) == base + extra == 434_466
    assert 0.05 < extra / base < 0.25  # thesis ~10 %; ours 21 % (see the module docstring)


def test_backprop_reaches_every_parameter() -> None:
    torch.manual_seed(1)
    m = joint().train()
    out = m(torch.randn(2, 3, 32, 24))
    (out["logits"].square().mean() + out["normals"][:, 0].mean()).backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_frozen_trunk_and_labels_stay_frozen() -> None:
    torch.manual_seed(2)
    m = joint(freeze_trunk=True).train()
    assert m.frozen and not m.trunk.training and not m.label_head.training
    assert m.normal_head.training
    frozen_before = {
        k: v.clone() for k, v in m.state_dict().items() if not k.startswith("normal_head.")
    }
    head_before = {k: v.clone() for k, v in m.normal_head.state_dict().items()}
    trainable = [p for p in m.parameters() if p.requires_grad]
    assert trainable and all(any(p is q for q in m.normal_head.parameters()) for p in trainable)
    opt = torch.optim.Adam(trainable, lr=1e-2)
    for _ in range(2):
        out = m(torch.randn(2, 3, 32, 32))
        loss = (out["normals"] - torch.tensor([0.0, 0.0, 1.0])[:, None, None]).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    for k, v in m.state_dict().items():
        if k in frozen_before:  # weights and BN running stats of trunk + label head
            torch.testing.assert_close(v, frozen_before[k], rtol=0, atol=0, msg=k)
    changed = [
        k for k, v in m.normal_head.state_dict().items() if not torch.equal(v, head_before[k])
    ]
    assert changed
    m.freeze_trunk_and_labels(False)
    assert all(p.requires_grad for p in m.parameters()) and m.trunk.training


def test_initialised_from_enet_gives_identical_logits() -> None:
    torch.manual_seed(3)
    net = enet(num_classes=8)
    net.train()
    net(torch.randn(2, 3, 32, 32))  # move BN running stats away from their defaults
    net.eval()
    m = JointNet(num_classes=8).load_enet_weights(net.state_dict()).eval()
    x = torch.randn(1, 3, 37, 50)
    with torch.no_grad():
        a, b = net(x), m(x)
    torch.testing.assert_close(a["logits"], b["logits"])
    torch.testing.assert_close(a["features"], b["features"])


def test_load_enet_weights_rejects_other_architectures() -> None:
    with pytest.raises(GeosegError, match="head"):
        joint(num_classes=8).load_enet_weights(enet(num_classes=5))
    with pytest.raises(GeosegError, match="unexpected"):
        joint().load_enet_weights({"foo.weight": torch.zeros(1)})


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="channels"):
        joint()(torch.randn(1, 1, 16, 16))
