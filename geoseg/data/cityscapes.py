"""A reader for Cityscapes-format folders, mapped to geoseg's 8 classes.

Layout (the official one; only ``leftImg8bit`` and ``gtFine`` are read)::

    <root>/leftImg8bit/<split>/<city>/<name>_leftImg8bit.png     8-bit RGB images
    <root>/gtFine/<split>/<city>/<name>_gtFine_labelIds.png      8-bit label ids (0..33)

Each Cityscapes ``labelId`` maps to a geoseg class (:mod:`geoseg.classes`) or to 255, ignored by
losses and metrics (void, ego vehicle, dynamic, ground, rail track, person, rider, license
plate); the table with the reason for each entry: ``docs/real_images.md`` ("Cityscapes labels
and geoseg's classes"). Any other value in a ``labelIds`` file is an error. With
``label_format="geoseg"`` the label files already hold geoseg ids (0..7, 255). ``label_map``
replaces the table (:mod:`geoseg.data.label_map`), e.g. for a dataset in this layout with other
classes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from geoseg.classes import (
    BUILDING,
    IGNORE_INDEX,
    NUM_CLASSES,
    OBJECT,
    ROAD,
    SIDEWALK,
    SKY,
    TERRAIN,
    VEGETATION,
    VEHICLE,
)
from geoseg.data.label_map import apply_label_map, label_lut, labelled_classes
from geoseg.data.labelled_folder import LabelledImageFolder
from geoseg.errors import GeosegError

logger = logging.getLogger(__name__)

IMAGE_DIR = "leftImg8bit"
LABEL_DIR = "gtFine"
IMAGE_SUFFIX = "_leftImg8bit.png"
LABEL_SUFFIX = "_gtFine_labelIds.png"
NUM_CITYSCAPES_IDS = 34  # labelIds 0..33

CITYSCAPES_TO_GEOSEG: dict[int, int] = {
    **{i: IGNORE_INDEX for i in (0, 1, 2, 3, 5, 6, 10, 24, 25)},
    4: OBJECT,
    7: ROAD,
    8: SIDEWALK,
    9: ROAD,
    11: BUILDING,
    12: BUILDING,
    13: OBJECT,
    14: OBJECT,
    15: BUILDING,
    16: BUILDING,
    17: OBJECT,
    18: OBJECT,
    19: OBJECT,
    20: OBJECT,
    21: VEGETATION,
    22: TERRAIN,
    23: SKY,
    **{i: VEHICLE for i in range(26, 34)},
}
"""Cityscapes labelId → geoseg class id (or IGNORE_INDEX); the table in the module docstring."""


def cityscapes_lut() -> np.ndarray:
    """`(256,)` int64 lookup table labelId → geoseg id; 255 → ignore; other ids → -1 (invalid)."""
    lut = np.full(256, -1, dtype=np.int64)
    for cs_id, ours in CITYSCAPES_TO_GEOSEG.items():
        lut[cs_id] = ours
    lut[255] = IGNORE_INDEX  # license plate (-1) as stored in 8-bit files
    return lut


def map_cityscapes_labels(label_ids: np.ndarray, *, path: str | Path = "<labels>") -> np.ndarray:
    """Map a Cityscapes ``labelIds`` map to geoseg classes.

    Args:
        label_ids: `(H, W)` integer labelIds.
        path: named in error messages.

    Returns:
        `(H, W)` int64 geoseg ids in ``[0, 8)`` or IGNORE_INDEX.

    Raises:
        GeosegError: a value that is not a Cityscapes labelId.
    """
    arr = np.asarray(label_ids)
    if arr.ndim != 2 or not np.issubdtype(arr.dtype, np.integer):
        raise GeosegError(
            f"labels {path}: expected a single-channel integer map, got {arr.dtype} {arr.shape}"
        )
    bad = (arr < 0) | (arr > 255)
    lut = cityscapes_lut()
    mapped = lut[np.clip(arr, 0, 255)]
    bad |= mapped < 0
    if bad.any():
        values = np.unique(arr[bad])[:10].tolist()
        raise GeosegError(
            f"labels {path}: values {values} are not Cityscapes labelIds (0..{NUM_CITYSCAPES_IDS - 1})"
        )
    return mapped


class CityscapesDataset(LabelledImageFolder):
    """Frames of a Cityscapes-format folder as ``{"image", "labels"}`` samples.

    Args:
        root: the folder holding ``leftImg8bit/`` and ``gtFine/``.
        split: ``"train"``, ``"val"``, ``"test"`` or any sub-folder name.
        cities: restrict to these city folders (default: all).
        label_format: ``"cityscapes"`` (labelIds, mapped by :data:`CITYSCAPES_TO_GEOSEG`) or
            ``"geoseg"`` (files already hold ids 0..7 / 255).
        transform: applied to each sample dict (e.g. :func:`geoseg.data.transforms.build_transforms`).
        label_map: label id → geoseg class (name, id or ``"ignore"``) replacing
            :data:`CITYSCAPES_TO_GEOSEG` (``label_format="cityscapes"`` only).

    Each sample is ``{"image": (3, H, W) float32 in [0, 1] RGB, "labels": (H, W) int64}``.

    Attributes:
        labelled_classes: the geoseg classes the labels can hold (the classes the mean IoU covers).

    Raises:
        GeosegError: ``root`` or a split folder missing (the message names the path expected), no
            image in the split, an image without its label file; at load time: an unreadable file,
            image and labels of different sizes, labels outside the class range.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        *,
        cities: Sequence[str] | None = None,
        label_format: Literal["cityscapes", "geoseg"] = "cityscapes",
        transform: Callable[[dict[str, Any]], Mapping[str, Any]] | None = None,
        label_map: Mapping[int | str, int | str] | None = None,
    ) -> None:
        if label_format not in ("cityscapes", "geoseg"):
            raise GeosegError(f"label_format: expected cityscapes or geoseg, got {label_format!r}")
        if label_map is not None and label_format != "cityscapes":
            raise GeosegError("label_map: only with label_format='cityscapes' (raw dataset ids)")
        self.lut = None if label_map is None else label_lut(label_map)
        if label_map is not None:
            self.labelled_classes = labelled_classes(label_map)
        elif label_format == "cityscapes":
            self.labelled_classes = labelled_classes(CITYSCAPES_TO_GEOSEG)
        else:
            self.labelled_classes = tuple(range(NUM_CLASSES))
        self.root = Path(root)
        self.split = split
        self.label_format = label_format
        self.transform = transform
        self.samples = self._scan(cities)
        logger.info("%s/%s: %d frames", self.root, split, len(self.samples))

    def _scan(self, cities: Sequence[str] | None) -> list[tuple[Path, Path]]:
        if not self.root.is_dir():
            raise GeosegError(f"Cityscapes root {self.root} does not exist or is not a folder")
        image_root = self.root / IMAGE_DIR / self.split
        label_root = self.root / LABEL_DIR / self.split
        for folder in (image_root, label_root):
            if not folder.is_dir():
                raise GeosegError(
                    f"Cityscapes layout: expected folder {folder} "
                    f"(<root>/{IMAGE_DIR}/<split>/<city>/*{IMAGE_SUFFIX} and "
                    f"<root>/{LABEL_DIR}/<split>/<city>/*{LABEL_SUFFIX})"
                )
        city_dirs = sorted(p for p in image_root.iterdir() if p.is_dir())
        if cities is not None:
            wanted = set(cities)
            unknown = wanted - {p.name for p in city_dirs}
            if unknown:
                raise GeosegError(f"cities: {sorted(unknown)} not found in {image_root}")
            city_dirs = [p for p in city_dirs if p.name in wanted]
        samples = []
        for city in city_dirs:
            for image in sorted(city.glob(f"*{IMAGE_SUFFIX}")):
                stem = image.name[: -len(IMAGE_SUFFIX)]
                label = label_root / city.name / f"{stem}{LABEL_SUFFIX}"
                if not label.is_file():
                    raise GeosegError(f"image {image} has no label file: expected {label}")
                samples.append((image, label))
        if not samples:
            stray = sorted(p.name for p in image_root.glob(f"*{IMAGE_SUFFIX}"))[:3]
            hint = (
                f" (images found directly in {image_root}: {stray}; they belong in <city>/ folders)"
                if stray
                else ""
            )
            raise GeosegError(
                f"Cityscapes split {image_root} is empty: no <city>/*{IMAGE_SUFFIX} files{hint}"
            )
        return samples

    def load_labels(self, index: int) -> np.ndarray:
        """`(H, W)` int64 geoseg ids of frame ``index`` (mapped and checked)."""
        path = self.samples[index][1]
        raw = self.read_label_file(index, ("labelIds image", "a *_color.png file?"))
        if self.lut is not None:
            return apply_label_map(raw, self.lut, path=path)
        if self.label_format == "cityscapes":
            return map_cityscapes_labels(raw, path=path)
        labels = raw.astype(np.int64)
        bad = (labels >= NUM_CLASSES) & (labels != IGNORE_INDEX)
        if bad.any():
            raise GeosegError(
                f"labels {path}: values {np.unique(labels[bad])[:10].tolist()} outside the class "
                f"range [0, {NUM_CLASSES}) (or {IGNORE_INDEX})"
            )
        return labels
