"""Tests for the georeferenced image base: loading, validation, embeddings, cache, index."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from geoseg.errors import GeosegError
from geoseg.reloc.image_base import (
    HeadEmbedder,
    ThumbnailEmbedder,
    layer21_features,
    load_image_base,
    raw_layer21_embedder,
    write_poses_csv,
)

R_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def make_base(root: Path, m: int = 6, size=(48, 64), seed: int = 0, **kw) -> list[np.ndarray]:
    """``m`` random RGB images ``img_i.png`` 10 m apart along x, with poses.csv."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    images, names = [], []
    for i in range(m):
        img = rng.integers(0, 256, (*size, 3), dtype=np.uint8)
        img = cv2.GaussianBlur(img, (5, 5), 0)
        name = f"img_{i:02d}.png"
        assert cv2.imwrite(str(root / name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        images.append(img)
        names.append(name)
    t = np.c_[np.arange(m) * 10.0, np.zeros(m), np.full(m, 1.5)]
    write_poses_csv(root / "poses.csv", names, np.stack([R_NORTH] * m), t, **kw)
    return images


def test_round_trip_and_exact_duplicate_is_rank_one(tmp_path: Path) -> None:
    images = make_base(tmp_path / "base", timestamps=np.arange(6) * 0.5, latlon=np.ones((6, 2)))
    base = load_image_base(tmp_path / "base")
    assert len(base) == 6 and base.images[2] == "img_02.png"
    np.testing.assert_allclose(base.t_wc[3], [30.0, 0.0, 1.5])
    np.testing.assert_allclose(base.R_wc[0], R_NORTH)
    np.testing.assert_allclose(base.timestamps, np.arange(6) * 0.5)
    assert base.latlon is not None and base.K is None
    np.testing.assert_array_equal(base.load_image(4), images[4])
    emb = ThumbnailEmbedder(size=(8, 6))
    index = base.build_index(emb)
    assert len(index) == 6 and index.dim == 48
    idx, dist = index.query(emb([images[4]]), k=3)
    assert idx[0, 0] == 4 and dist[0, 0] < 1e-9
    # the GPS window (tx, ty) keeps only nearby base images
    idx, _ = index.query(emb([images[4]]), k=3, gps=[[0.0, 0.0]], radius_m=15.0)
    assert set(idx[0][idx[0] >= 0].tolist()) == {0, 1}


def test_embedding_cache(tmp_path: Path) -> None:
    make_base(tmp_path)
    base = load_image_base(tmp_path)
    calls = []

    class Counting(ThumbnailEmbedder):
        def __call__(self, images):
            calls.append(len(images))
            return super().__call__(images)

    emb = Counting(size=(4, 4))
    first = base.embeddings(emb, batch_size=4)
    assert calls == [4, 2] and base.cache_path(emb.name).is_file()
    second = load_image_base(tmp_path).embeddings(emb)
    assert calls == [4, 2]  # read from the cache
    np.testing.assert_array_equal(first, second)
    # a changed image invalidates the cache
    img = np.zeros((48, 64, 3), np.uint8)
    img[10:20, 10:30] = 255
    cv2.imwrite(str(tmp_path / "img_01.png"), img)
    third = load_image_base(tmp_path).embeddings(emb)
    assert calls == [4, 2, 6] and not np.allclose(third[1], first[1])
    # no name: no cache
    anon = lambda ims: np.ones((len(ims), 3))  # noqa: E731
    assert base.embeddings(anon).shape == (6, 3)
    # a file at the cache's name that is not a cache is someone else's: used never, kept
    other = Counting(size=(2, 2))
    base.cache_path(other.name).write_bytes(b"a user's file")
    assert load_image_base(tmp_path).embeddings(other).shape == (6, 4)
    assert base.cache_path(other.name).read_bytes() == b"a user's file"


def test_thumbnail_is_a_normalised_block_mean() -> None:
    emb = ThumbnailEmbedder(size=(2, 2))
    img = np.zeros((4, 6), np.uint8)
    img[:2, :3] = 200
    v = emb.embed_one(img)
    expected = np.array([150.0, -50, -50, -50])
    np.testing.assert_allclose(v, expected / np.linalg.norm(expected))
    assert np.abs(emb.embed_one(np.full((4, 4), 7, np.uint8))).max() == 0.0  # flat image
    with pytest.raises(GeosegError, match="smaller"):
        emb.embed_one(np.zeros((1, 1), np.uint8))


def _write_rows(path: Path, header: list[str], rows: list[list[str]]) -> None:
    path.write_text("\n".join(",".join(r) for r in [header, *rows]) + "\n")


def test_bad_bases_are_named(tmp_path: Path) -> None:
    with pytest.raises(GeosegError, match="not a directory"):
        load_image_base(tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(GeosegError, match="empty image base"):
        load_image_base(empty)
    # images but no poses.csv
    make_base(tmp_path / "noposes")
    (tmp_path / "noposes" / "poses.csv").unlink()
    with pytest.raises(GeosegError, match="poses.csv is missing.*img_00.png"):
        load_image_base(tmp_path / "noposes")
    # header only
    only_header = tmp_path / "header"
    make_base(only_header, m=1)
    header = (only_header / "poses.csv").read_text().splitlines()[0]
    (only_header / "poses.csv").write_text(header + "\n")
    (only_header / "img_00.png").unlink()
    with pytest.raises(GeosegError, match="empty image base"):
        load_image_base(only_header)
    # an image without a pose
    orphan = tmp_path / "orphan"
    make_base(orphan)
    cv2.imwrite(str(orphan / "extra.jpg"), np.zeros((8, 8, 3), np.uint8))
    (orphan / "sub").mkdir()
    cv2.imwrite(str(orphan / "sub" / "deep.png"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(GeosegError, match="without poses.*extra.jpg.*sub/deep.png"):
        load_image_base(orphan)
    # a pose without an image
    gone = tmp_path / "gone"
    make_base(gone)
    (gone / "img_03.png").unlink()
    with pytest.raises(GeosegError, match="not found.*img_03.png"):
        load_image_base(gone)


def test_bad_pose_rows_are_named(tmp_path: Path) -> None:
    make_base(tmp_path, m=2)
    lines = (tmp_path / "poses.csv").read_text().splitlines()
    header = lines[0].split(",")
    good = lines[1].split(",")
    bad = list(good)
    bad[header.index("ty")] = "north"
    _write_rows(tmp_path / "poses.csv", header, [bad, lines[2].split(",")])
    with pytest.raises(GeosegError, match="row 2.*'ty'.*not a number"):
        load_image_base(tmp_path)
    bad = list(good)
    bad[header.index("r00")] = "2.0"
    _write_rows(tmp_path / "poses.csv", header, [bad, lines[2].split(",")])
    with pytest.raises(GeosegError, match="img_00.png.*not a rotation"):
        load_image_base(tmp_path)
    _write_rows(tmp_path / "poses.csv", header, [good, good])
    with pytest.raises(GeosegError, match="already listed"):
        load_image_base(tmp_path)
    cols = [c for c in header if c != "tz"]
    _write_rows(tmp_path / "poses.csv", cols, [[v for c, v in zip(header, good) if c != "tz"]])
    with pytest.raises(GeosegError, match="missing column.*tz"):
        load_image_base(tmp_path)


def test_camera_json(tmp_path: Path) -> None:
    make_base(tmp_path, m=2)
    (tmp_path / "camera.json").write_text(json.dumps({"fx": 50, "fy": 51, "cx": 32, "cy": 24}))
    K = load_image_base(tmp_path).K
    np.testing.assert_allclose(K, [[50, 0, 32], [0, 51, 24], [0, 0, 1]])
    (tmp_path / "camera.json").write_text(json.dumps({"fx": 50}))
    with pytest.raises(GeosegError, match="camera.json"):
        load_image_base(tmp_path)


class _FakeSegmenter:
    """Stands in for geoseg.infer.Segmenter: layer-21 'features' of size (4, H/8, W/8)."""

    def __call__(self, batch):
        b, h, w, _ = batch.shape
        f = np.zeros((b, 4, h // 8, w // 8), np.float32)
        f[:, :3] = batch[:, ::8, ::8].transpose(0, 3, 1, 2)[:, :, : h // 8, : w // 8] / 255.0
        return type("Result", (), {"features": f})()


def test_layer21_adapters(tmp_path: Path) -> None:
    images = make_base(tmp_path, m=4)
    seg = _FakeSegmenter()
    f = layer21_features(seg)(images[0])
    assert f.shape == (4, 6, 8) and f.dtype == np.float32
    raw = raw_layer21_embedder(seg)
    assert raw([images[0], images[1]]).shape == (2, 4 * 6 * 8)
    index = load_image_base(tmp_path).build_index(raw)
    assert index.query(raw([images[2]]), k=1)[0][0, 0] == 2
    # images of another size: mismatched feature maps, unless pooled to a fixed size
    big = np.zeros((64, 64, 3), np.uint8)
    with pytest.raises(GeosegError, match="mismatched sizes"):
        raw([big])
    pooled = raw_layer21_embedder(seg, output_size=(2, 2))
    assert pooled([images[0], big]).shape == (2, 16)

    import torch

    from geoseg.models.reloc import reloc_head

    head = reloc_head(in_channels=4, embedding_dim=8, hidden_channels=4)
    learned = HeadEmbedder(seg, head)
    e = learned(images[:3])
    assert e.shape == (3, 8)
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, rtol=1e-5)
    assert not head.training and isinstance(head, torch.nn.Module)

    class NoFeatures:
        def __call__(self, batch):
            return {"logits": np.zeros((1, 8, 2, 2))}

    with pytest.raises(GeosegError, match="no layer-21"):
        raw_layer21_embedder(NoFeatures())([images[0]])
