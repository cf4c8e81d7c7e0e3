"""What the readers of labelled image folders share: a sample is an image and its class ids.

A reader (:mod:`geoseg.data.camvid`, :mod:`geoseg.data.cityscapes`) finds its ``samples``
(``(image path, label path)`` pairs) and decodes its own label files (``load_labels``); this
base reads the images and assembles the training sample, so both hand the trainers the same
thing.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from geoseg.errors import GeosegError


class LabelledImageFolder(Dataset):
    """Base of the labelled-folder readers.

    Subclasses set ``samples`` (a list of ``(image path, label path)``), ``transform`` (a
    callable on the sample dict, or None) and implement ``load_labels(index) -> (H, W)`` int64
    class ids.
    """

    samples: list
    transform: Any = None

    def __len__(self) -> int:
        return len(self.samples)

    def load_labels(self, index: int) -> np.ndarray:
        raise NotImplementedError

    def read_label_file(self, index: int, hint: tuple[str, str]) -> np.ndarray:
        """``(H, W)`` the raw single-channel label image of frame ``index``; ``hint``: (what
        the file should be, what a multi-channel one probably is), for the error."""
        path = self.samples[index][1]
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise GeosegError(f"labels {path}: cannot read (not an image file?)")
        if raw.ndim != 2:
            raise GeosegError(
                f"labels {path}: expected a single-channel {hint[0]}, got shape {raw.shape} "
                f"({hint[1]})"
            )
        return raw

    def load_image(self, index: int) -> np.ndarray:
        """`(H, W, 3)` uint8 RGB image of frame ``index``."""
        path = self.samples[index][0]
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise GeosegError(f"image {path}: cannot read (not an image file?)")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def __getitem__(self, index: int) -> dict[str, Any]:
        """``{"image": (3, H, W) float32 in [0, 1], "labels": (H, W) int64}``, transformed."""
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        index %= len(self)
        image = self.load_image(index)
        labels = self.load_labels(index)
        if image.shape[:2] != labels.shape:
            raise GeosegError(
                f"labels {self.samples[index][1]}: size {labels.shape} differs from image "
                f"{self.samples[index][0]} size {image.shape[:2]}"
            )
        sample: dict[str, Any] = {
            "image": torch.from_numpy(image).permute(2, 0, 1).float().div_(255.0),
            "labels": torch.from_numpy(labels),
        }
        if self.transform is not None:
            sample = dict(self.transform(sample))
        return sample
