"""Picture keys for the label and normal maps: class colours and the normal-colour sphere.

Both return plain RGB uint8 images, so that any contact sheet (``geoseg demo``'s, a user's) can
show them as one more tile beside the maps they explain.
"""

from __future__ import annotations

import numpy as np

from geoseg.classes import CLASS_NAMES, PALETTE
from geoseg.infer import normals_to_rgb

__all__ = ["class_legend", "normal_key", "sphere_normals"]


def class_legend(width: int = 320, height: int = 240) -> np.ndarray:
    """The 8 class colours (:data:`geoseg.classes.PALETTE`) with their ids and names.

    Returns:
        ``(height, width, 3)`` uint8 RGB, white background, one swatch per line.
    """
    import cv2

    img = np.full((height, width, 3), 255, np.uint8)
    line = height // len(CLASS_NAMES)
    scale = max(0.3, line / 40.0)
    for i, name in enumerate(CLASS_NAMES):
        y0 = i * line + 2
        cv2.rectangle(img, (4, y0), (4 + 2 * line, y0 + line - 4), PALETTE[i].tolist(), -1)
        cv2.putText(
            img, f"{i} {name}", (10 + 2 * line, y0 + int(line * 0.7)),
            cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA,
        )  # fmt: skip
    return img


def sphere_normals(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a sphere seen by the camera (the half facing it).

    Returns:
        ``(normals (3, size, size) float32, inside (size, size) bool)``: camera-frame unit
        normals (x right, y down, z forward: facing the camera means ``n_z < 0``), zero outside.
    """
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c, c)
    r2 = x * x + y * y
    inside = r2 < 1.0
    z = -np.sqrt(np.clip(1.0 - r2, 0.0, None))
    n = np.stack([x, y, z]).astype(np.float32)
    n[:, ~inside] = 0.0
    return n, inside


def normal_key(size: int = 240) -> np.ndarray:
    """The normal-colour key: a sphere coloured like a normal map, labelled with directions.

    Colour = ``(n + 1) / 2 * 255`` per camera axis (:func:`geoseg.infer.normals_to_rgb`): a
    surface facing the camera is olive, one facing up (the road) purple, one facing left teal.

    Returns:
        ``(size, size, 3)`` uint8 RGB.
    """
    import cv2

    n, inside = sphere_normals(size)
    img = np.ascontiguousarray(normals_to_rgb(n))
    img[~inside] = 255
    s = max(0.3, size / 600.0)
    for text, org in (
        ("up", (size // 2 - 10, 14)),
        ("left", (2, size // 2)),
        ("right", (size - 40, size // 2)),
        ("facing", (size // 2 - 26, size // 2 - 4)),
        ("camera", (size // 2 - 26, size // 2 + 12)),
    ):
        cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, s, (0, 0, 0), 1, cv2.LINE_AA)
    return img
