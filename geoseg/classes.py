"""The 8 semantic classes shared by the synthetic world, the networks and the SLAM bridge.

The order matches the naive CNN's 8 outputs (thesis fig. 4.5); docs/architecture.md lists them.
"""

from __future__ import annotations

import numpy as np

CLASS_NAMES: tuple[str, ...] = (
    "road",
    "sidewalk",
    "building",
    "vegetation",
    "vehicle",
    "object",  # poles, signs, bus shelters, advertising panels
    "sky",
    "terrain",
)
NUM_CLASSES = len(CLASS_NAMES)
ROAD, SIDEWALK, BUILDING, VEGETATION, VEHICLE, OBJECT, SKY, TERRAIN = range(NUM_CLASSES)

# Label id used for "not annotated" pixels (e.g. Cityscapes void); ignored by losses and metrics.
IGNORE_INDEX = 255

# Display colours, (8, 3) uint8 RGB, close to the Cityscapes palette of the matching classes.
PALETTE = np.array(
    [
        (128, 64, 128),  # road
        (244, 35, 232),  # sidewalk
        (70, 70, 70),  # building
        (107, 142, 35),  # vegetation
        (0, 0, 142),  # vehicle
        (220, 220, 0),  # object
        (70, 130, 180),  # sky
        (152, 251, 152),  # terrain
    ],
    dtype=np.uint8,
)


def colorize(labels: np.ndarray) -> np.ndarray:
    """Colour a label map.

    Args:
        labels: `(H, W)` integer class ids; ids outside `[0, 8)` (e.g. IGNORE_INDEX) are black.

    Returns:
        `(H, W, 3)` uint8 RGB image.
    """
    labels = np.asarray(labels)
    out = np.zeros(labels.shape + (3,), dtype=np.uint8)
    valid = (labels >= 0) & (labels < NUM_CLASSES)
    out[valid] = PALETTE[labels[valid]]
    return out
