"""Tests for the relocalisation embedding head, the triplet loss and the raw baseline."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch
import torch.nn.functional as F

from geoseg.errors import GeosegError
from geoseg.models.reloc import RawFeatureEmbedder, raw_feature_embedder, reloc_head, triplet_loss
from geoseg.reloc.retrieval import RetrievalIndex, triplet_accuracy


@pytest.mark.parametrize("size", [(1, 4, 5), (3, 6, 8), (2, 1, 1)])
def test_head_shapes_and_normalisation(size) -> None:
    torch.manual_seed(0)
    b, h, w = size
    head = reloc_head(embedding_dim=32).eval()
    out = head(torch.randn(b, 128, h, w))
    assert set(out) == {"embedding"}
    assert out["embedding"].shape == (b, 32)
    torch.testing.assert_close(out["embedding"].norm(dim=1), torch.ones(b))
    raw = reloc_head(embedding_dim=16, normalize=False).eval()
    assert not torch.allclose(
        raw(torch.randn(b, 128, h, w))["embedding"].norm(dim=1), torch.ones(b)
    )


def test_triplet_loss_closed_form() -> None:
    g = torch.Generator().manual_seed(1)
    ref, match, other = (torch.randn(16, 8, generator=g, dtype=torch.float64) for _ in range(3))
    d_pos = (ref - match).norm(dim=1)
    d_neg = (ref - other).norm(dim=1)
    closed = -torch.log(torch.exp(-d_pos) / (torch.exp(-d_pos) + torch.exp(-d_neg)))
    loss = triplet_loss(ref, match, other, reduction="none")
    torch.testing.assert_close(loss, closed, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(loss, F.softplus(d_pos - d_neg), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(triplet_loss(ref, match, other), closed.mean())
    torch.testing.assert_close(triplet_loss(ref, match, other, reduction="sum"), closed.sum())
    # stable for huge distance gaps where the naive form overflows / underflows
    far = torch.full((1, 8), 1e3, dtype=torch.float64)
    zero = torch.zeros(1, 8, dtype=torch.float64)
    big = triplet_loss(zero, far, zero.clone() + 1e-3, reduction="none")
    assert torch.isfinite(big).all() and big.item() == pytest.approx(
        far.norm().item() - 1e-3 * 8**0.5, rel=1e-12
    )
    assert triplet_loss(zero, zero + 1e-3, far, reduction="none").item() < 1e-100


def test_triplet_loss_finite_gradient_for_identical_embeddings() -> None:
    ref = torch.randn(4, 8, requires_grad=True)
    loss = triplet_loss(ref, ref.detach().clone(), torch.randn(4, 8))
    loss.backward()
    assert torch.isfinite(ref.grad).all()


def test_triplet_loss_bad_inputs() -> None:
    x = torch.randn(4, 8)
    with pytest.raises(GeosegError, match="match"):
        triplet_loss(x, x[:3], x)
    with pytest.raises(GeosegError, match="ref"):
        triplet_loss(x[0], x[0], x[0])
    with pytest.raises(GeosegError, match="reduction"):
        triplet_loss(x, x, x, reduction="max")


def test_loss_decreases_on_fixed_batch() -> None:
    torch.manual_seed(0)
    head = reloc_head(embedding_dim=32)
    g = torch.Generator().manual_seed(2)
    feats = torch.randn(4, 128, 6, 8, generator=g)
    # matches: the same place with an appearance change; others: different places
    ref, match = feats, feats * 0.8 + 0.3 * torch.randn(4, 128, 6, 8, generator=g)
    other = feats.roll(1, dims=0)
    opt = torch.optim.Adam(head.parameters(), lr=1e-3)
    losses = []
    for _ in range(15):
        e = head(torch.cat([ref, match, other]))["embedding"]
        loss = triplet_loss(*e.split(4))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] * 0.9
    head.eval()
    with torch.no_grad():
        e = [head(x)["embedding"] for x in (ref, match, other)]
    assert triplet_accuracy(*e) == 1.0


def test_head_bad_inputs() -> None:
    head = reloc_head().eval()
    for bad, msg in [
        (torch.randn(1, 64, 4, 4), r"\(B, 128, h, w\)"),
        (torch.randn(128, 4), r"\(B, 128, h, w\)"),
        (torch.ones(1, 128, 4, 4, dtype=torch.int64), "floating"),
        (torch.full((1, 128, 4, 4), float("nan")), "NaN"),
        (np.zeros((1, 128, 4, 4), dtype=np.float32), "Tensor"),
    ]:
        with pytest.raises(GeosegError, match=msg):
            head(bad)
    with pytest.raises(GeosegError):
        reloc_head(embedding_dim=0)


def test_raw_feature_embedder() -> None:
    feats = torch.randn(2, 128, 8, 12)
    assert raw_feature_embedder()(feats)["embedding"].shape == (2, 128 * 96)
    torch.testing.assert_close(raw_feature_embedder()(feats)["embedding"], feats.flatten(1))
    pooled = RawFeatureEmbedder(pool=4)(feats)["embedding"]
    assert pooled.shape == (2, 128 * 2 * 3)
    torch.testing.assert_close(pooled, F.avg_pool2d(feats, 4).flatten(1))
    fixed = RawFeatureEmbedder(output_size=(2, 2))
    assert fixed(torch.randn(1, 128, 7, 9))["embedding"].shape == (1, 512)
    assert fixed(feats)["embedding"].shape == (2, 512)
    with pytest.raises(GeosegError, match="pool"):
        RawFeatureEmbedder(pool=0)
    with pytest.raises(GeosegError, match="pool"):
        RawFeatureEmbedder(pool=16)(feats)
    with pytest.raises(GeosegError, match="at most one"):
        RawFeatureEmbedder(pool=2, output_size=(1, 1))


def test_raw_baseline_retrieval_and_size_mismatch() -> None:
    g = torch.Generator().manual_seed(3)
    base = torch.randn(20, 128, 4, 6, generator=g)
    emb = RawFeatureEmbedder(pool=2)
    index = RetrievalIndex(emb(base)["embedding"])
    query = base[[7, 11]] + 0.05 * torch.randn(2, 128, 4, 6, generator=g)
    idx, _ = index.query(emb(query)["embedding"], k=3)
    assert idx[:, 0].tolist() == [7, 11]
    # features of another image size give another embedding size: refused before sklearn
    with pytest.raises(GeosegError, match="embeddings"):
        index.query(emb(torch.randn(1, 128, 6, 6))["embedding"], k=1)


def test_onnx_dynamo_export_parity(tmp_path) -> None:
    torch.manual_seed(4)
    head = reloc_head(embedding_dim=64)
    # non-trivial batch-norm statistics
    head.train()
    with torch.no_grad():
        for _ in range(3):
            head(torch.randn(4, 128, 6, 8) * 2 + 0.5)
    head.eval()
    path = tmp_path / "reloc.onnx"
    batch, h, w = (torch.export.Dim(n, min=1, max=512) for n in ("batch", "h", "w"))
    torch.onnx.export(
        head,
        (torch.randn(2, 128, 6, 8),),
        str(path),
        dynamo=True,
        input_names=["features"],
        output_names=["embedding"],
        dynamic_shapes={"features": {0: batch, 2: h, 3: w}},
        verbose=False,
    )
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    x = torch.randn(3, 128, 5, 11)  # a second input with another batch and size
    (onnx_emb,) = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})
    with torch.no_grad():
        ref = head(x)["embedding"]
    assert onnx_emb.shape == (3, 64)
    cos = F.cosine_similarity(torch.from_numpy(onnx_emb), ref, dim=1)
    assert cos.min().item() >= 0.9999
