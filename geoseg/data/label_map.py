"""Label maps: a dataset's own label ids → geoseg's 8 classes (:mod:`geoseg.classes`).

A label map is a mapping ``{dataset id: geoseg class}`` where the class is a name from
:data:`~geoseg.classes.CLASS_NAMES` (``"road"``, ``"building"``...), its index, or ``"ignore"``
(the pixel counts in no loss and no metric). In a config (``data.label_map``)::

    data:
      source: camvid
      label_map: {0: sky, 1: building, 2: object, 3: road, 4: sidewalk, 5: vegetation,
                  6: object, 7: ignore, 8: vehicle, 9: ignore, 10: ignore, 11: ignore}

A label file value the map does not list is an error (a wrong map is found at once, not as a
quietly worse score). The classes a map reaches are the classes the dataset *labels*: its mean
IoU is taken over those only (:func:`labelled_classes`), so that a dataset without, say,
``terrain`` is not charged an IoU of 0 for a class it cannot contain.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from geoseg.classes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES
from geoseg.errors import GeosegError

IGNORE_NAME = "ignore"
MAX_LABEL_ID = 255  # 8-bit label files


def class_id(value: int | str, *, key: str = "label_map") -> int:
    """A geoseg class id (or IGNORE_INDEX) from a class name, ``"ignore"`` or an id.

    Raises:
        GeosegError: an unknown name or an id outside ``[0, 8)`` and not 255.
    """
    if isinstance(value, str):
        if value == IGNORE_NAME:
            return IGNORE_INDEX
        if value in CLASS_NAMES:
            return CLASS_NAMES.index(value)
        raise GeosegError(
            f"{key}: unknown class {value!r}; expected one of {list(CLASS_NAMES)} or 'ignore'"
        )
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise GeosegError(f"{key}: expected a class name or id, got {value!r}")
    if not (0 <= int(value) < NUM_CLASSES or int(value) == IGNORE_INDEX):
        raise GeosegError(f"{key}: class id {value} outside [0, {NUM_CLASSES}) and not ignore")
    return int(value)


def normalise_label_map(mapping: Mapping[int | str, int | str]) -> dict[int, int]:
    """``{dataset id: geoseg id or IGNORE_INDEX}`` from a map of names or ids.

    Raises:
        GeosegError: empty map, a dataset id outside ``[0, 255]``, an unknown class.
    """
    if not isinstance(mapping, Mapping) or not mapping:
        raise GeosegError(f"label_map: expected a non-empty mapping, got {mapping!r}")
    out: dict[int, int] = {}
    for raw_id, value in mapping.items():
        try:
            source_id = int(raw_id)
        except (TypeError, ValueError):
            raise GeosegError(f"label_map: key {raw_id!r} is not an integer label id") from None
        if not 0 <= source_id <= MAX_LABEL_ID:
            raise GeosegError(f"label_map: key {source_id} outside [0, {MAX_LABEL_ID}]")
        out[source_id] = class_id(value, key=f"label_map[{source_id}]")
    return out


def label_lut(mapping: Mapping[int | str, int | str]) -> np.ndarray:
    """`(256,)` int64 lookup table dataset id → geoseg id; ids the map omits hold -1."""
    lut = np.full(MAX_LABEL_ID + 1, -1, dtype=np.int64)
    for source_id, ours in normalise_label_map(mapping).items():
        lut[source_id] = ours
    return lut


def labelled_classes(mapping: Mapping[int | str, int | str]) -> tuple[int, ...]:
    """The geoseg classes a dataset with this map can contain, sorted (ignore excluded)."""
    ids = set(normalise_label_map(mapping).values()) - {IGNORE_INDEX}
    return tuple(sorted(ids))


def apply_label_map(
    label_ids: np.ndarray, lut: np.ndarray, *, path: str | Path = "<labels>"
) -> np.ndarray:
    """Map a label file's ids through ``lut`` (:func:`label_lut`).

    Args:
        label_ids: `(H, W)` integer dataset ids.
        lut: `(256,)` lookup table.
        path: named in error messages.

    Returns:
        `(H, W)` int64 geoseg ids or IGNORE_INDEX.

    Raises:
        GeosegError: not a single-channel integer map, or values the map does not list.
    """
    arr = np.asarray(label_ids)
    if arr.ndim != 2 or not np.issubdtype(arr.dtype, np.integer):
        raise GeosegError(
            f"labels {path}: expected a single-channel integer map, got {arr.dtype} {arr.shape}"
        )
    bad = (arr < 0) | (arr > MAX_LABEL_ID)
    mapped = lut[np.clip(arr, 0, MAX_LABEL_ID)]
    bad |= mapped < 0
    if bad.any():
        values = np.unique(arr[bad])[:10].tolist()
        listed = np.flatnonzero(lut >= 0).tolist()
        raise GeosegError(
            f"labels {path}: values {values} are not in the label map (it lists {listed}); "
            "add them to data.label_map (a class name or 'ignore')"
        )
    return mapped
