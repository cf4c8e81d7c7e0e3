"""A reader for CamVid-layout folders (the SegNet/ENet 11-class version), mapped to geoseg's 8
classes.

Layout (as distributed with SegNet; images PNG or JPEG, labels 8-bit PNG of class ids)::

    <root>/<split>/<name>.png|.jpg        RGB images, e.g. <root>/train/0001TP_006690.png
    <root>/<split>annot/<name>.png        class ids, same name stem, e.g. <root>/trainannot/...

Default map (:data:`CAMVID_TO_GEOSEG`; ``data.label_map`` replaces it, see
:mod:`geoseg.data.label_map`):

====  ===========  ==========  =================================================================
id    CamVid       geoseg      why
====  ===========  ==========  =================================================================
0     Sky          sky
1     Building     building
2     Pole         object      poles, like the synthetic world's
3     Road         road
4     Pavement     sidewalk
5     Tree         vegetation
6     SignSymbol   object      signs and traffic lights are street furniture
7     Fence        ignore      fences and walls mixed: no single geoseg class
8     Car          vehicle
9     Pedestrian   ignore      no person class
10    Bicyclist    ignore      rider + bicycle: no single class
11    Unlabelled   ignore      void
====  ===========  ==========  =================================================================

geoseg's ``terrain`` has no CamVid counterpart: the dataset labels 7 classes
(:attr:`CamVidDataset.labelled_classes`), and its mean IoU is taken over those 7.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from geoseg.classes import (
    BUILDING,
    IGNORE_INDEX,
    OBJECT,
    ROAD,
    SIDEWALK,
    SKY,
    VEGETATION,
    VEHICLE,
)
from geoseg.data.label_map import apply_label_map, label_lut, labelled_classes
from geoseg.data.labelled_folder import LabelledImageFolder
from geoseg.errors import GeosegError

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
LABEL_DIR_SUFFIX = "annot"

CAMVID_TO_GEOSEG: dict[int, int] = {
    0: SKY,
    1: BUILDING,
    2: OBJECT,
    3: ROAD,
    4: SIDEWALK,
    5: VEGETATION,
    6: OBJECT,
    7: IGNORE_INDEX,
    8: VEHICLE,
    9: IGNORE_INDEX,
    10: IGNORE_INDEX,
    11: IGNORE_INDEX,
}
"""CamVid class id → geoseg class id (or IGNORE_INDEX); the table in the module docstring."""


class CamVidDataset(LabelledImageFolder):
    """Frames of a CamVid-layout folder as ``{"image", "labels"}`` samples.

    Args:
        root: the folder holding ``<split>/`` and ``<split>annot/``.
        split: ``"train"``, ``"val"``, ``"test"`` or any sub-folder name.
        label_map: dataset id → geoseg class (name, id or ``"ignore"``); default
            :data:`CAMVID_TO_GEOSEG`.
        transform: applied to each sample dict (e.g. :func:`geoseg.data.transforms.build_transforms`).

    Each sample is ``{"image": (3, H, W) float32 in [0, 1] RGB, "labels": (H, W) int64}``.

    Attributes:
        labelled_classes: the geoseg classes the map reaches (the classes the mean IoU covers).

    Raises:
        GeosegError: ``root`` or a split folder missing (the message names the path expected), no
            image in the split, an image without its label file, a bad label map; at load time:
            an unreadable file, image and labels of different sizes, ids the map does not list.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        *,
        label_map: Mapping[int | str, int | str] | None = None,
        transform: Callable[[dict[str, Any]], Mapping[str, Any]] | None = None,
    ) -> None:
        self.root = Path(root)
        self.split = split
        mapping = CAMVID_TO_GEOSEG if label_map is None else label_map
        self.lut = label_lut(mapping)
        self.labelled_classes = labelled_classes(mapping)
        self.transform = transform
        self.samples = self._scan()
        logger.info("%s/%s: %d frames", self.root, split, len(self.samples))

    def _scan(self) -> list[tuple[Path, Path]]:
        if not self.root.is_dir():
            raise GeosegError(f"CamVid root {self.root} does not exist or is not a folder")
        image_dir = self.root / self.split
        label_dir = self.root / f"{self.split}{LABEL_DIR_SUFFIX}"
        for folder in (image_dir, label_dir):
            if not folder.is_dir():
                raise GeosegError(
                    f"CamVid layout: expected folder {folder} (<root>/<split>/<name>.png|jpg and "
                    f"<root>/<split>{LABEL_DIR_SUFFIX}/<name>.png)"
                )
        images = sorted(p for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not images:
            raise GeosegError(f"CamVid split {image_dir} is empty: no {'/'.join(IMAGE_SUFFIXES)}")
        samples = []
        for image in images:
            label = label_dir / f"{image.stem}.png"
            if not label.is_file():
                raise GeosegError(f"image {image} has no label file: expected {label}")
            samples.append((image, label))
        return samples

    def load_labels(self, index: int) -> np.ndarray:
        """`(H, W)` int64 geoseg ids of frame ``index`` (mapped and checked)."""
        path = self.samples[index][1]
        raw = self.read_label_file(index, ("class-id image", "a colour-coded label image?"))
        return apply_label_map(raw, self.lut, path=path)
