"""Frame datasets from a run's data section: the sample transforms (augmentations, camera
effects, crop, greyscale, normalisation) and :func:`build_frame_dataset`, which every image
trainer, the colour statistics of a run (:mod:`training.colour_stats`) and the tests build their
frames with. It sits below :mod:`training.common` and :mod:`training.colour_stats`, which both
need the frames (the end of a run records their colour statistics in the model card).

Images reach the networks normalised with :data:`NORMALIZATION` (ImageNet statistics, stored in
``model.pt`` and the ONNX metadata so that :class:`geoseg.infer.Segmenter` applies the same).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch.utils.data import Dataset

from geoseg.errors import GeosegError
from geoseg.infer import DEFAULT_NORMALIZATION
from training.config import DataConfig

NORMALIZATION: dict[str, list[float]] = {k: list(v) for k, v in DEFAULT_NORMALIZATION.items()}


class NormalizeImage:
    """Sample transform: ``image = (image - mean) / std`` on a `(3, H, W)` image in [0, 1]."""

    def __init__(self, normalization: Mapping[str, Sequence[float]] = NORMALIZATION) -> None:
        self.mean = torch.tensor(normalization["mean"], dtype=torch.float32)[:, None, None]
        self.std = torch.tensor(normalization["std"], dtype=torch.float32)[:, None, None]

    def __call__(self, sample: Mapping[str, Any]) -> dict[str, Any]:
        out = dict(sample)
        out["image"] = (out["image"] - self.mean) / self.std
        return out


LUMA_WEIGHTS: tuple[float, float, float] = (0.299, 0.587, 0.114)
"""ITU-R BT.601 luma weights of R, G, B: the grey a monochrome camera's frame is taken to be
(:func:`geoseg.infer.as_rgb` replicates such a frame to three channels)."""


class RandomGrayscale:
    """Sample transform: with probability ``p``, the `(3, H, W)` image in [0, 1] becomes its
    BT.601 luma replicated to three channels (a monochrome camera's frame as the networks see
    it). Draws from torch's global generator, as the other augmentations do."""

    def __init__(self, p: float) -> None:
        self.p = float(p)
        self.weights = torch.tensor(LUMA_WEIGHTS, dtype=torch.float32)[:, None, None]

    def __call__(self, sample: Mapping[str, Any]) -> dict[str, Any]:
        out = dict(sample)
        if self.p > 0 and float(torch.rand(())) < self.p:
            image = out["image"]
            luma = (image * self.weights.to(image.dtype)).sum(dim=0, keepdim=True)
            out["image"] = luma.expand_as(image).clone()
        return out


class Chain:
    """Apply sample transforms in order (picklable, for DataLoader workers)."""

    def __init__(self, *steps: Any) -> None:
        self.steps = [s for s in steps if s is not None]

    def __call__(self, sample: Mapping[str, Any]) -> dict[str, Any]:
        out = dict(sample)
        for step in self.steps:
            out = dict(step(out))
        return out


def random_crop(size: Sequence[int]) -> Any:
    """A sample transform cutting a random ``(h, w)`` window out of image, labels and normals
    (padded with ignore labels / zero normals when the frame is smaller)."""
    from torchvision import tv_tensors
    from torchvision.transforms import v2

    from geoseg.classes import IGNORE_INDEX
    from geoseg.data.transforms import Normals, SampleTransform

    if len(size) != 2 or any(int(s) < 1 for s in size):
        raise GeosegError(f"crop: expected positive (h, w), got {list(size)}")
    fill = {tv_tensors.Image: 0.0, tv_tensors.Mask: IGNORE_INDEX, Normals: 0.0}
    return SampleTransform(v2.RandomCrop([int(s) for s in size], pad_if_needed=True, fill=fill))


def build_frame_dataset(
    data: DataConfig,
    split: str,
    *,
    augment: bool | None = None,
    normalize: bool = True,
    crop: Sequence[int] | None = None,
) -> Dataset:
    """The frame dataset of ``split`` described by ``data``.

    Args:
        data: the run's data section.
        split: ``"train"``, ``"val"`` or ``"test"`` (synthetic: the held-out evaluation city;
            Cityscapes: ``data.val_split``).
        augment: apply the training augmentations (default: only for ``train``).
        normalize: normalise images with :data:`NORMALIZATION` (False: leave them in [0, 1]).
        crop: ``(h, w)``: a random crop of that size after the augmentations (training on
            crops of full-scale frames is cheaper and keeps the scale of evaluation).

    Returns:
        A dataset of ``{"image": (3, H, W), "labels": (H, W), ...}`` samples at ``data.size``
        (synthetic samples also hold ``normals`` and ``normal_valid``).

    Raises:
        GeosegError: unknown split, Cityscapes without ``root`` or in the wrong layout, bad
            ``data.synth`` keys.
    """
    from geoseg.data.camera_effects import CameraEffects
    from geoseg.data.transforms import build_transforms

    if split not in ("train", "val", "test"):
        raise GeosegError(f"split: expected train, val or test, got {split!r}")
    augment = split == "train" if augment is None else augment
    transform = Chain(
        build_transforms(data.augment, size=tuple(data.size), train=augment),
        CameraEffects(data.augment.camera) if augment and data.augment.camera.enabled else None,
        random_crop(crop) if crop is not None else None,
        RandomGrayscale(data.grayscale) if augment and data.grayscale > 0 else None,
        NormalizeImage() if normalize else None,
    )
    if data.source == "synth":
        from geoseg.data.synthetic import SyntheticDataset, synthetic_config

        config = synthetic_config(data.synth, split=split)
        clean_transform = None
        if config.clean_share > 0:
            # clean samples: the geometric augmentations only (no colour jitter or camera effects)
            plain = dataclasses.replace(data.augment, brightness=0, contrast=0, saturation=0, hue=0)
            clean_transform = Chain(
                build_transforms(plain, size=tuple(data.size), train=augment),
                random_crop(crop) if crop is not None else None,
                NormalizeImage() if normalize else None,
            )
        return SyntheticDataset(
            config,
            size=tuple(data.size),
            cache_dir=data.cache_dir,
            transform=transform,
            clean_transform=clean_transform,
        )
    if data.source == "cityscapes":
        from geoseg.data.cityscapes import CityscapesDataset

        if data.root is None:
            raise GeosegError(
                "data.root: a Cityscapes-format folder is needed for source=cityscapes"
            )
        name = data.train_split if split == "train" else data.val_split
        return CityscapesDataset(data.root, name, transform=transform, label_map=data.label_map)
    if data.source == "camvid":
        from geoseg.data.camvid import CamVidDataset

        if data.root is None:
            raise GeosegError("data.root: a CamVid-layout folder is needed for source=camvid")
        name = data.train_split if split == "train" else data.val_split
        return CamVidDataset(data.root, name, transform=transform, label_map=data.label_map)
    raise GeosegError(f"data.source: expected synth, cityscapes or camvid, got {data.source!r}")


def dataset_classes(dataset: Dataset) -> tuple[int, ...] | None:
    """The geoseg classes ``dataset`` labels (its ``labelled_classes``), None = all of them.

    The segmentation metrics take their mean IoU over these (:class:`training.metrics.SegmentationMeter`).
    """
    classes = getattr(dataset, "labelled_classes", None)
    return None if classes is None else tuple(int(c) for c in classes)
