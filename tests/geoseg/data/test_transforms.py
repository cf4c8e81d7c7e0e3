"""Transforms keep image, labels and normals aligned; a flip negates the normals' x."""

import pytest
import torch
from torchvision.transforms import v2

from geoseg.data.transforms import AugmentConfig, Normals, SampleTransform, build_transforms
from geoseg.errors import GeosegError

H, W, Z = 12, 16, 20.0


def _sample() -> dict[str, torch.Tensor]:
    """Every map encodes its pixel coordinates, so misalignment is visible."""
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij"
    )
    image = torch.stack([xs / W, ys / H, torch.full_like(xs, 0.5)])
    labels = (ys * W + xs).long()
    n = torch.stack([xs - 7.5, ys - 5.5, torch.full_like(xs, Z)])
    normals = n / n.norm(dim=0, keepdim=True)
    normals[:, 0, 0] = 0.0  # one invalid (sky) pixel
    return {"image": image, "labels": labels, "normals": normals}


def _decode_normals(normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(x, y) pixel coordinates encoded by the un-flipped normals."""
    return normals[0] / normals[2] * Z + 7.5, normals[1] / normals[2] * Z + 5.5


def test_horizontal_flip_mirrors_everything_and_negates_normals_x() -> None:
    s = _sample()
    out = SampleTransform(v2.RandomHorizontalFlip(p=1.0))(s)
    assert torch.equal(out["image"], s["image"].flip(-1))
    assert torch.equal(out["labels"], s["labels"].flip(-1))
    mirrored = s["normals"].flip(-1)
    assert torch.equal(out["normals"][0], -mirrored[0])
    assert torch.equal(out["normals"][1:], mirrored[1:])
    assert out["labels"].dtype == torch.int64
    assert all(type(v) is torch.Tensor for v in out.values())  # plain tensors for collate


def test_vertical_flip_negates_normals_y() -> None:
    s = _sample()
    out = SampleTransform(v2.RandomVerticalFlip(p=1.0))(s)
    assert torch.equal(out["normals"][1], -s["normals"].flip(-2)[1])
    assert torch.equal(out["labels"], s["labels"].flip(-2))


@pytest.mark.parametrize("seed", range(5))
def test_random_crop_keeps_maps_aligned(seed: int) -> None:
    torch.manual_seed(seed)
    out = SampleTransform(v2.RandomCrop((5, 7)))(_sample())
    labels = out["labels"]
    y, x = labels // W, labels % W
    y0, x0 = int(y[0, 0]), int(x[0, 0])
    assert torch.equal(y, y0 + torch.arange(5)[:, None].expand(5, 7))
    assert torch.equal(x, x0 + torch.arange(7)[None].expand(5, 7))
    assert torch.allclose(out["image"][0] * W, x.float(), atol=1e-5)
    assert torch.allclose(out["image"][1] * H, y.float(), atol=1e-5)
    valid = out["normals"].norm(dim=0) > 0.5
    nx, ny = _decode_normals(out["normals"])
    assert torch.allclose(nx[valid], x.float()[valid], atol=1e-4)
    assert torch.allclose(ny[valid], y.float()[valid], atol=1e-4)
    assert torch.equal(~valid, (y == 0) & (x == 0))


def _check_aligned(out: dict[str, torch.Tensor], flipped: bool = False) -> None:
    """Normals vs image: same source coordinates (both interpolated); labels: nearest source
    pixel (torchvision's legacy nearest is offset by up to ~half an output pixel)."""
    ix, iy = out["image"][0] * W, out["image"][1] * H
    known = out["labels"] != 255  # not padding
    valid = (out["normals"].norm(dim=0) > 0.5) & known
    # pixels interpolated from the invalid source pixel (0, 0) lean towards their valid neighbours
    valid &= ((ix - (W - 1) * flipped) ** 2 + iy**2) > 4
    nx, ny = _decode_normals(out["normals"])
    if flipped:  # a flip negates the normals' x: they encode the mirrored column
        nx = (W - 1) - nx
    assert (nx[valid] - ix[valid]).abs().max() < 0.05
    assert (ny[valid] - iy[valid]).abs().max() < 0.05
    lx, ly = (out["labels"] % W).float(), (out["labels"] // W).float()
    assert (lx[known] - ix[known]).abs().max() < 1.5
    assert (ly[known] - iy[known]).abs().max() < 1.5


def test_resize_labels_nearest_and_normals_unit() -> None:
    out = SampleTransform(v2.Resize((7, 9)))(_sample())
    assert out["labels"].dtype == torch.int64
    assert set(out["labels"].unique().tolist()) <= set(range(H * W))  # no blended ids
    norms = out["normals"].norm(dim=0)
    valid = norms > 0.5
    assert torch.allclose(norms[valid], torch.ones_like(norms[valid]), atol=1e-5)
    assert not valid[0, 0]  # the invalid pixel stays invalid
    _check_aligned(out)
    up = SampleTransform(v2.Resize((24, 32)))(_sample())
    _check_aligned(up)


def test_full_training_pipeline_keeps_alignment() -> None:
    tf = build_transforms(AugmentConfig(hflip=0.5, scale=(0.8, 1.5)), size=(H, W), train=True)
    seen = set()
    for seed in range(8):
        torch.manual_seed(seed)
        out = tf(_sample())
        assert out["image"].shape == (3, H, W) and out["labels"].shape == (H, W)
        assert out["normals"].shape == (3, H, W) and out["labels"].dtype == torch.int64
        known = out["labels"] != 255  # padding (moved to the left by a flip) excluded
        dx = out["image"][0, :, 1:] - out["image"][0, :, :-1]
        flipped = bool(dx[known[:, 1:] & known[:, :-1]].mean() < 0)
        seen.add(flipped)
        _check_aligned(out, flipped)
    assert seen == {True, False}


def test_scale_jitter_zooms_in_from_the_output_size() -> None:
    # scale >= 1 on a frame of the output size: a zoom and a crop, never padding
    tf = build_transforms(AugmentConfig(hflip=0.0, scale=(1.0, 1.3)), size=(H, W), train=True)
    for seed in range(4):
        torch.manual_seed(seed)
        out = tf(_sample())
        assert out["labels"].shape == (H, W) and not (out["labels"] == 255).any()


def test_colour_jitter_only_touches_the_image() -> None:
    s = _sample()
    torch.manual_seed(0)
    out = SampleTransform(v2.ColorJitter(brightness=0.5, contrast=0.5, saturation=0.5, hue=0.2))(s)
    assert not torch.equal(out["image"], s["image"])
    assert torch.equal(out["labels"], s["labels"]) and torch.equal(out["normals"], s["normals"])


def test_unsupported_warps_and_undeclared_maps_are_refused() -> None:
    with pytest.raises(GeosegError, match="rotate"):
        SampleTransform(v2.RandomRotation(10))(_sample())
    s = _sample()
    s["depth"] = torch.rand(H, W)
    with pytest.raises(GeosegError, match="depth"):
        SampleTransform(v2.RandomHorizontalFlip(p=1.0))(s)
    out = SampleTransform(v2.RandomHorizontalFlip(p=1.0), mask_keys=("labels", "depth"))(s)
    assert torch.equal(out["depth"], s["depth"].flip(-1))
    with pytest.raises(GeosegError, match="normals"):
        Normals(torch.zeros(2, 4, 4))


def test_eval_pipeline_is_deterministic() -> None:
    tf = build_transforms(AugmentConfig(brightness=0.5), size=(6, 8), train=False)
    a, b = tf(_sample()), tf(_sample())
    assert all(torch.equal(a[k], b[k]) for k in a)
