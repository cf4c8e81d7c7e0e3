"""Tests for SO(3) helpers, the relative-pose head, its loss (eq. 5.2) and its labels."""

from __future__ import annotations

import math

import numpy as np
import onnxruntime as ort
import pytest
import torch

from geoseg.errors import GeosegError
from geoseg.models.relpose import (
    correlation_volume,
    from_thesis_coefficients,
    relative_pose_labels,
    relpose_head,
    relpose_loss,
    so3_exp,
    so3_hat,
    so3_log,
    so3_vee,
    to_thesis_coefficients,
)
from geoseg.reloc.retrieval import absolute_position

F64 = torch.float64


def _rz(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


# ----------------------------------------------------------------------------- SO(3)


def test_exp_log_round_trip_and_orthonormal() -> None:
    g = torch.Generator().manual_seed(0)
    axis = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=F64), dim=1)
    angles = torch.cat(
        [torch.tensor([0.0, 1e-9, 1e-5, 1e-3, 0.5, 2.0, 3.1, 3.14159], dtype=F64)] * 25
    )
    w = axis * angles[:, None]
    r = so3_exp(w)
    eye = torch.eye(3, dtype=F64)
    torch.testing.assert_close(r.transpose(-1, -2) @ r, eye.expand_as(r), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(200, dtype=F64))
    torch.testing.assert_close(so3_log(r), w, atol=1e-9, rtol=0)
    # exp of the hat matches the matrix exponential
    torch.testing.assert_close(r, torch.linalg.matrix_exp(so3_hat(w)), atol=1e-12, rtol=0)
    torch.testing.assert_close(so3_vee(so3_hat(w)), w)


def test_hat_and_thesis_basis() -> None:
    w = torch.tensor([0.1, -0.2, 0.3], dtype=F64)
    x = torch.tensor([1.0, 2.0, -0.5], dtype=F64)
    torch.testing.assert_close(so3_hat(w) @ x, torch.linalg.cross(w, x))
    # thesis eq. 1.44: sum a_i G_i = [[0, a1, -a2], [-a1, 0, a3], [a2, -a3, 0]]
    a1, a2, a3 = 0.7, -0.4, 0.25
    thesis = torch.tensor([[0, a1, -a2], [-a1, 0, a3], [a2, -a3, 0]], dtype=F64)
    alpha = torch.tensor([a1, a2, a3], dtype=F64)
    torch.testing.assert_close(so3_hat(from_thesis_coefficients(alpha)), thesis)
    torch.testing.assert_close(to_thesis_coefficients(from_thesis_coefficients(alpha)), alpha)
    assert torch.dot(alpha, alpha) == torch.dot(
        from_thesis_coefficients(alpha), from_thesis_coefficients(alpha)
    )


def test_exp_log_gradcheck() -> None:
    g = torch.Generator().manual_seed(1)
    w = (torch.randn(4, 3, generator=g, dtype=F64) * 0.8).requires_grad_()
    assert torch.autograd.gradcheck(so3_exp, (w,))
    small = (torch.randn(3, 3, generator=g, dtype=F64) * 1e-4).requires_grad_()
    assert torch.autograd.gradcheck(so3_exp, (small,))
    assert torch.autograd.gradcheck(lambda v: so3_log(so3_exp(v)), (w,))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_no_nan_gradient_at_identity(dtype) -> None:
    w = torch.zeros(3, 3, dtype=dtype, requires_grad=True)
    loss = (so3_log(so3_exp(w)) ** 2).sum() + so3_log(so3_exp(w)).sum()
    loss.backward()
    assert torch.isfinite(w.grad).all()
    torch.testing.assert_close(w.grad, torch.ones_like(w))  # d/dw (|w|^2 + sum w) at 0
    # the loss itself, exactly at the truth R_gt = R_est = I
    pred = {
        "rotation": torch.zeros(2, 3, dtype=dtype, requires_grad=True),
        "direction": torch.tensor([[0.0, 0, 1], [1, 0, 0]], dtype=dtype, requires_grad=True),
    }
    r_gt = torch.eye(3, dtype=dtype).expand(2, 3, 3)
    loss = relpose_loss(pred, r_gt, pred["direction"].detach())
    loss.backward()
    assert loss.item() == pytest.approx(0.0, abs=1e-7)
    assert torch.isfinite(pred["rotation"].grad).all()
    assert torch.isfinite(pred["direction"].grad).all()
    # log at exactly the identity matrix
    r = torch.eye(3, dtype=dtype).clone().requires_grad_()
    so3_log(r).sum().backward()
    assert torch.isfinite(r.grad).all()


# ----------------------------------------------------------------------------- loss


def test_relpose_loss_zero_at_truth_and_hand_values() -> None:
    g = torch.Generator().manual_seed(2)
    w_gt = torch.randn(5, 3, generator=g, dtype=F64)
    w_gt = w_gt / w_gt.norm(dim=1, keepdim=True) * torch.rand(5, 1, generator=g, dtype=F64) * 3
    r_gt = so3_exp(w_gt)
    t_gt = torch.nn.functional.normalize(torch.randn(5, 3, generator=g, dtype=F64), dim=1)
    pred = {"rotation": so3_log(r_gt), "direction": t_gt}
    assert relpose_loss(pred, r_gt, t_gt).item() == pytest.approx(0.0, abs=1e-14)
    # hand values: R_gt = I, 0.3 rad about z -> alpha^T alpha = 0.09; orthogonal direction -> lam
    r_i = torch.eye(3, dtype=F64)[None]
    pred = {
        "rotation": torch.tensor([[0.0, 0.0, 0.3]], dtype=F64),
        "direction": torch.tensor([[1.0, 0.0, 0.0]], dtype=F64),
    }
    t = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    assert relpose_loss(pred, r_i, t, lam=2.0).item() == pytest.approx(2.0 + 0.09)
    # opposite direction -> 2 lam; rotation error on the R_gt^T R_est side
    pred["direction"] = -t
    r_gt = so3_exp(torch.tensor([[0.0, 0.0, 0.1]], dtype=F64))
    assert relpose_loss(pred, r_gt, t, lam=1.0).item() == pytest.approx(2.0 + 0.04)
    with pytest.raises(GeosegError, match="R_gt"):
        relpose_loss(pred, torch.eye(3, dtype=F64), t)
    with pytest.raises(GeosegError, match="pred"):
        relpose_loss({"rotation": pred["rotation"]}, r_gt, t)


# ----------------------------------------------------------------------------- labels


def test_relative_pose_labels_hand_worked() -> None:
    # camera a: at (1, 2, 0), rotated 90 deg about world z (its x axis points along world +y)
    # camera b: at (1, 5, 0), rotated 180 deg about world z.
    # b - a = (0, 3, 0) in the world = (3, 0, 0) in a's frame: b lies along a's x axis.
    r_ab, t_dir = relative_pose_labels(_rz(90), [1.0, 2.0, 0.0], _rz(180), [1.0, 5.0, 0.0])
    np.testing.assert_allclose(r_ab, _rz(90), atol=1e-15)
    np.testing.assert_allclose(t_dir, [1.0, 0.0, 0.0], atol=1e-15)
    assert isinstance(r_ab, np.ndarray)
    # batched torch inputs give torch outputs, same numbers
    r_ab_t, t_dir_t = relative_pose_labels(
        torch.tensor(np.stack([_rz(90), np.eye(3)])),
        torch.tensor([[1.0, 2.0, 0.0], [0.0, 0.0, 0.0]], dtype=F64),
        torch.tensor(np.stack([_rz(180), _rz(30)])),
        torch.tensor([[1.0, 5.0, 0.0], [0.0, 0.0, -2.0]], dtype=F64),
    )
    torch.testing.assert_close(r_ab_t[0], torch.tensor(_rz(90)))
    torch.testing.assert_close(t_dir_t, torch.tensor([[1.0, 0, 0], [0, 0, -1.0]], dtype=F64))
    with pytest.raises(GeosegError, match="coincident"):
        relative_pose_labels(np.eye(3), np.zeros(3), _rz(10), np.zeros(3))
    with pytest.raises(GeosegError, match="t_wc_b"):
        relative_pose_labels(np.eye(3), np.zeros(3), np.eye(3), np.zeros(2))


def test_labels_feed_absolute_position() -> None:
    rng = np.random.default_rng(5)
    query_t = np.array([10.0, -4.0, 1.5])
    base_t = rng.uniform(-30, 30, size=(4, 3))
    base_r = np.stack([_rz(a) for a in (0, 45, 170, -60)])
    _, dirs = relative_pose_labels(
        base_r, base_t, np.repeat(_rz(20)[None], 4, 0), np.repeat(query_t[None], 4, 0)
    )
    res = absolute_position(base_r, base_t, dirs)
    np.testing.assert_allclose(res.point, query_t, atol=1e-9)


# ----------------------------------------------------------------------------- head


def test_correlation_volume_matches_loop_and_finds_the_shift() -> None:
    g = torch.Generator().manual_seed(1)
    a = torch.randn(2, 5, 6, 7, generator=g, dtype=F64)
    b = torch.randn(2, 5, 6, 7, generator=g, dtype=F64)
    r = 2
    vol = correlation_volume(a, b, r)
    assert vol.shape == (2, 25, 6, 7)
    an, bn = (torch.nn.functional.normalize(x, dim=1) for x in (a, b))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            k = (dy + r) * (2 * r + 1) + (dx + r)
            for y in range(6):
                for x in range(7):
                    inside = 0 <= y + dy < 6 and 0 <= x + dx < 7
                    want = (an[:, :, y, x] * bn[:, :, y + dy, x + dx]).sum(1) if inside else 0.0
                    torch.testing.assert_close(vol[:, k, y, x], want * torch.ones(2, dtype=F64))
    # b = a moved by (+1 row, -2 columns): a[y, x] reappears at b[y + 1, x - 2], cosine 1
    moved = torch.roll(a, shifts=(1, -2), dims=(2, 3))
    best = correlation_volume(a, moved, r)[:, :, 1:4, 2:5].argmax(dim=1)
    assert (best == (1 + r) * (2 * r + 1) + (-2 + r)).all()


@pytest.mark.parametrize("radius", [0, 2])
@pytest.mark.parametrize("size", [(1, 4, 5), (2, 6, 8), (2, 1, 1)])
def test_head_shapes(size, radius) -> None:
    b, h, w = size
    head = relpose_head(correlation_radius=radius).eval()
    out = head(torch.randn(b, 128, h, w), torch.randn(b, 128, h, w))
    assert set(out) == {"rotation", "direction"}
    assert out["rotation"].shape == (b, 3) and out["direction"].shape == (b, 3)
    torch.testing.assert_close(out["direction"].norm(dim=1), torch.ones(b))


def test_distance_output_shape_and_initial_value() -> None:
    head = relpose_head(predict_distance=True).eval()
    out = head(torch.randn(3, 128, 4, 5), torch.randn(3, 128, 4, 5))
    assert set(out) == {"rotation", "direction", "log_distance"}
    assert out["log_distance"].shape == (3,)
    # the output starts near a 4 m baseline (small weights, bias log 4)
    assert torch.allclose(out["log_distance"].exp(), torch.full((3,), 4.0), rtol=0.3)
    with pytest.raises(GeosegError, match="predict_distance"):
        relpose_head(predict_distance=1)


def test_distance_term_of_the_loss() -> None:
    """Zero for the exact baseline, ``mu log(ratio)^2`` otherwise, gradient 2 mu log(ratio) / B."""
    r_gt = so3_exp(torch.tensor([[0.1, -0.2, 0.05], [0.0, 0.3, 0.0]], dtype=F64))
    t_gt = torch.nn.functional.normalize(torch.tensor([[0.2, 0.1, 1.0], [1.0, 0, 0]], dtype=F64))
    dist = torch.tensor([2.0, 7.5], dtype=F64)
    log_d = torch.log(dist * torch.tensor([1.0, 1.5], dtype=F64)).requires_grad_(True)
    pred = {"rotation": so3_log(r_gt), "direction": t_gt, "log_distance": log_d}
    base = relpose_loss(pred, r_gt, t_gt, reduction="none")
    loss = relpose_loss(pred, r_gt, t_gt, distance_gt=dist, mu=0.5, reduction="none")
    want = 0.5 * torch.log(torch.tensor([1.0, 1.5], dtype=F64)) ** 2
    torch.testing.assert_close(loss - base, want)
    relpose_loss(pred, r_gt, t_gt, distance_gt=dist, mu=0.5).backward()
    grad = 2 * 0.5 * torch.log(torch.tensor([1.0, 1.5], dtype=F64)) / 2
    torch.testing.assert_close(log_d.grad, grad)
    with pytest.raises(GeosegError, match="log_distance"):
        relpose_loss(
            {"rotation": pred["rotation"], "direction": t_gt}, r_gt, t_gt, distance_gt=dist
        )
    with pytest.raises(GeosegError, match="distance_gt"):
        relpose_loss(pred, r_gt, t_gt, distance_gt=torch.tensor([1.0, 0.0], dtype=F64))
    with pytest.raises(GeosegError, match="mu"):
        relpose_loss(pred, r_gt, t_gt, distance_gt=dist, mu=0.0)


def test_head_bad_inputs() -> None:
    with pytest.raises(GeosegError, match="correlation_radius"):
        relpose_head(correlation_radius=-1)
    head = relpose_head().eval()
    x = torch.randn(1, 128, 4, 4)
    with pytest.raises(GeosegError, match="feat_b"):
        head(x, torch.randn(1, 128, 4, 5))
    with pytest.raises(GeosegError, match="feat_a"):
        head(torch.randn(1, 3, 4, 4), x)
    with pytest.raises(GeosegError, match="NaN"):
        head(x, torch.full_like(x, float("nan")))
    with pytest.raises(GeosegError, match="floating"):
        head(x.long(), x)


def test_loss_decreases_on_fixed_batch() -> None:
    torch.manual_seed(0)
    head = relpose_head()
    g = torch.Generator().manual_seed(3)
    fa = torch.randn(4, 128, 6, 8, generator=g)
    fb = torch.randn(4, 128, 6, 8, generator=g)
    r_gt = so3_exp(torch.randn(4, 3, generator=g) * 0.3)
    t_gt = torch.nn.functional.normalize(torch.randn(4, 3, generator=g), dim=1)
    opt = torch.optim.Adam(head.parameters(), lr=3e-3)
    losses = []
    for _ in range(8):
        loss = relpose_loss(head(fa, fb), r_gt, t_gt)
        opt.zero_grad()
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in head.parameters() if p.grad is not None)
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


@pytest.mark.filterwarnings("ignore:# The axis name")
@pytest.mark.parametrize(("radius", "distance"), [(0, False), (3, True)])
def test_onnx_dynamo_export_parity(tmp_path, radius, distance) -> None:
    torch.manual_seed(6)
    head = relpose_head(correlation_radius=radius, predict_distance=distance)
    head.train()
    with torch.no_grad():
        for _ in range(3):
            head(torch.randn(4, 128, 6, 8) + 0.3, torch.randn(4, 128, 6, 8) - 0.2)
    head.eval()
    path = tmp_path / "relpose.onnx"
    batch, h, w = (torch.export.Dim(n, min=1, max=512) for n in ("batch", "h", "w"))
    dims = {0: batch, 2: h, 3: w}
    torch.onnx.export(
        head,
        (torch.randn(2, 128, 6, 8), torch.randn(2, 128, 6, 8)),
        str(path),
        dynamo=True,
        input_names=["feat_a", "feat_b"],
        output_names=["rotation", "direction", "log_distance"][: 2 + distance],
        dynamic_shapes={"feat_a": dims, "feat_b": dims},
        verbose=False,
    )
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    fa, fb = torch.randn(3, 128, 5, 11), torch.randn(3, 128, 5, 11)
    outs = sess.run(None, {names[0]: fa.numpy(), names[1]: fb.numpy()})
    rot, dirn = outs[:2]
    with torch.no_grad():
        ref = head(fa, fb)
    assert len(outs) == 2 + distance
    if distance:
        np.testing.assert_allclose(outs[2], ref["log_distance"].numpy(), atol=1e-4, rtol=1e-3)
    np.testing.assert_allclose(rot, ref["rotation"].numpy(), atol=1e-4, rtol=1e-3)
    cos = torch.nn.functional.cosine_similarity(torch.from_numpy(dirn), ref["direction"], dim=1)
    assert cos.min().item() >= 0.9999
