"""Colour transfer between images (Reinhard, Ashikhmin, Gooch, Shirley, "Color transfer between
images", IEEE CG&A 2001), used to bring real photographs to the colour statistics of the
synthetic training images (thesis §4.3.2 transfers its inputs' intensities the same way).

The transfer works in Ruderman's decorrelated ``lαβ`` space: RGB → LMS cone responses (a
linear map) → ``log10`` → an orthogonal-like rotation into one achromatic axis ``l`` and two
opponent axes ``α`` (yellow-blue) and ``β`` (red-green). There, each channel of the source is
shifted and scaled so that its mean and standard deviation become the target's::

    lab_out = (lab - mean_source) * std_target / std_source + mean_target

Because the three axes are nearly decorrelated for natural images, matching them one by one
matches the overall colour cast and contrast without visible cross-channel artefacts.

Statistics (:class:`ColourStatistics`) are a mean and a standard deviation per ``lαβ`` channel:
of one image or pooled over a sequence (:func:`colour_statistics`; a source estimate for all
frames of a drive, steadier than frame by frame), or those of a typical image of a set
(:func:`typical_statistics`, per-channel medians of the images' own statistics). A model card
records the typical statistics of the training set (key ``colour_statistics``) so that inference
can map onto them; :func:`reference_statistics` reads a target from a file instead (an image, a
folder of images, a model card or a statistics JSON).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoseg.errors import GeosegError, check_shape

# RGB -> LMS (Reinhard et al. 2001, eq. 4: the XYZ-mediated conversion, rows L, M, S).
RGB_TO_LMS = np.array(
    [[0.3811, 0.5783, 0.0402], [0.1967, 0.7244, 0.0782], [0.0241, 0.1288, 0.8444]],
    dtype=np.float64,
)
# log10 LMS -> lαβ (eq. 6): a diagonal scaling after sums and differences of the cone signals.
LOG_LMS_TO_LAB = np.diag([1 / np.sqrt(3), 1 / np.sqrt(6), 1 / np.sqrt(2)]) @ np.array(
    [[1.0, 1.0, 1.0], [1.0, 1.0, -2.0], [1.0, -1.0, 0.0]]
)
# Exact inverses (the paper prints rounded ones; exact ones make the round trip lossless).
LMS_TO_RGB = np.linalg.inv(RGB_TO_LMS)
LAB_TO_LOG_LMS = np.linalg.inv(LOG_LMS_TO_LAB)
# Cone responses are floored here before the logarithm: black pixels would otherwise give -inf
# and dominate the statistics (1/255 = the darkest non-zero 8-bit level).
LMS_FLOOR = 1.0 / 255.0
# A channel flatter than this (a uniform image) is not rescaled: its std would divide by ~0.
MIN_STD = 1e-6


@dataclass(frozen=True)
class ColourStatistics:
    """Per-channel mean and standard deviation of images in ``lαβ`` space.

    Attributes:
        mean: `(3,)` means of l, α, β.
        std: `(3,)` standard deviations of l, α, β (non-negative).
    """

    mean: tuple[float, float, float]
    std: tuple[float, float, float]

    def as_dict(self) -> dict[str, list[float]]:
        """Plain-data form for model cards (``{"space": "lab_reinhard", "mean", "std"}``)."""
        return {"space": "lab_reinhard", "mean": list(self.mean), "std": list(self.std)}

    @classmethod
    def from_dict(
        cls, data: Mapping[str, Any], *, name: str = "colour_statistics"
    ) -> ColourStatistics:
        """Read :meth:`as_dict` output.

        Raises:
            GeosegError: missing keys, not 3 finite means and 3 non-negative stds, another space.
        """
        try:
            space = data.get("space", "lab_reinhard")
            mean = tuple(float(v) for v in data["mean"])
            std = tuple(float(v) for v in data["std"])
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise GeosegError(
                f"{name}: expected {{'mean': [3 floats], 'std': [3 floats]}} ({err!r})"
            ) from None
        if space != "lab_reinhard":
            raise GeosegError(f"{name}: statistics in space {space!r}, expected 'lab_reinhard'")
        values = np.array(mean + std)
        if len(mean) != 3 or len(std) != 3 or not np.isfinite(values).all() or min(std) < 0:
            raise GeosegError(f"{name}: expected 3 finite means and 3 stds >= 0, got {mean}, {std}")
        return cls(mean=mean, std=std)  # type: ignore[arg-type]


def _as_unit_rgb(image: np.ndarray, name: str) -> np.ndarray:
    """`(..., 3)` uint8 (0..255) or float (0..1) RGB → float64 in [0, 1]."""
    image = np.asarray(image)
    if image.ndim < 1 or image.shape[-1] != 3:
        raise GeosegError(f"{name}: expected RGB images (..., 3), got shape {image.shape}")
    if image.dtype == np.uint8:
        return image.astype(np.float64) / 255.0
    if not np.issubdtype(image.dtype, np.floating):
        raise GeosegError(f"{name}: expected uint8 or float RGB, got dtype {image.dtype}")
    if not np.isfinite(image).all():
        raise GeosegError(f"{name}: holds NaN or infinite values")
    return image.astype(np.float64)


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """RGB to Reinhard's ``lαβ``.

    Args:
        rgb: `(..., 3)` uint8 RGB, or float RGB in [0, 1].

    Returns:
        `(..., 3)` float64 ``lαβ``.
    """
    lms = _as_unit_rgb(rgb, "rgb") @ RGB_TO_LMS.T
    return np.log10(np.maximum(lms, LMS_FLOOR)) @ LOG_LMS_TO_LAB.T


def lab_to_rgb(lab: np.ndarray) -> np.ndarray:
    """Reinhard's ``lαβ`` back to float RGB (not clipped: values may leave [0, 1]).

    Args:
        lab: `(..., 3)` ``lαβ``.

    Returns:
        `(..., 3)` float64 RGB.
    """
    lab = np.asarray(lab, dtype=np.float64)
    check_shape("lab", lab, (None,) * (lab.ndim - 1) + (3,))
    return np.power(10.0, lab @ LAB_TO_LOG_LMS.T) @ LMS_TO_RGB.T


def colour_statistics(images: np.ndarray | Iterable[np.ndarray]) -> ColourStatistics:
    """``lαβ`` mean and std pooled over all pixels of one image or of several images.

    Args:
        images: one `(H, W, 3)` RGB image, a `(B, H, W, 3)` batch, or an iterable of `(H, W, 3)`
            images of any sizes (uint8, or float in [0, 1]).

    Returns:
        The pooled :class:`ColourStatistics` (each pixel weighs the same).

    Raises:
        GeosegError: no pixel, or not RGB.
    """
    if isinstance(images, np.ndarray):
        images = [images]
    count = 0
    total = np.zeros(3)
    total_sq = np.zeros(3)
    for image in images:
        lab = rgb_to_lab(np.asarray(image)).reshape(-1, 3)
        count += lab.shape[0]
        total += lab.sum(0)
        total_sq += np.square(lab).sum(0)
    if count == 0:
        raise GeosegError("images: no pixel to compute colour statistics from")
    mean = total / count
    # why the clamp: E[x^2] - E[x]^2 can come out a hair below 0 in floating point
    std = np.sqrt(np.maximum(total_sq / count - np.square(mean), 0.0))
    return ColourStatistics(mean=tuple(mean.tolist()), std=tuple(std.tolist()))


def typical_statistics(images: Iterable[np.ndarray]) -> ColourStatistics:
    """The statistics of a typical image of a set: per-channel medians of each image's own
    mean and std.

    A per-image transfer maps one image's statistics onto these, so the target should describe
    one image, not the pooled set (pooling adds the spread *between* images to the std), and a
    median is not pulled by a minority of very dark frames (the synthetic set's night).

    Args:
        images: `(H, W, 3)` RGB images (uint8, or float in [0, 1]).

    Raises:
        GeosegError: no image.
    """
    stats = [colour_statistics(image) for image in images]
    rows = [np.array(s.mean + s.std) for s in stats]
    if not rows:
        raise GeosegError("images: no image to compute typical colour statistics from")
    median = np.median(np.stack(rows), axis=0)
    return ColourStatistics(mean=tuple(median[:3].tolist()), std=tuple(median[3:].tolist()))


def transfer_lab(
    lab: np.ndarray,
    source: ColourStatistics,
    target: ColourStatistics,
    *,
    match_std: bool = True,
) -> np.ndarray:
    """Map ``lαβ`` values with statistics ``source`` onto ``target`` (Reinhard's eq. 10-11).

    Args:
        lab: `(..., 3)` ``lαβ`` values.
        source: statistics the values are taken to have.
        target: statistics to map them to.
        match_std: scale each channel to the target's std (Reinhard's transfer); False only
            shifts the means (removes a colour cast and an exposure offset, keeps the image's
            own contrast and saturation).

    Returns:
        `(..., 3)` float64: mean ``target.mean`` and (with ``match_std``) std ``target.std``
        per channel when ``source`` are the values' own statistics. A flat source channel is
        only shifted.
    """
    src_std = np.asarray(source.std)
    scale = np.where(src_std > MIN_STD, np.asarray(target.std) / np.maximum(src_std, MIN_STD), 1.0)
    if not match_std:
        scale = np.ones(3)
    return (np.asarray(lab, np.float64) - source.mean) * scale + np.asarray(target.mean)


def transfer_colour(
    image: np.ndarray,
    target: ColourStatistics,
    source: ColourStatistics | None = None,
    *,
    match_std: bool = True,
) -> np.ndarray:
    """Give ``image`` the colour statistics ``target``.

    Args:
        image: `(H, W, 3)` or `(B, H, W, 3)` RGB, uint8 or float in [0, 1].
        target: statistics to reach (e.g. the training set's, from a model card).
        source: statistics to map from: None = the image's own (each image of a batch on its
            own); a sequence's pooled statistics map every frame the same way.
        match_std: see :func:`transfer_lab` (False: shift the means only).

    Returns:
        Same shape and dtype as ``image``: uint8 rounded and clipped to [0, 255], float clipped
        to [0, 1]. :func:`transfer_lab` holds the exact, unclipped mapping.
    """
    arr = np.asarray(image)
    if arr.ndim not in (3, 4):
        raise GeosegError(f"image: expected (H, W, 3) or (B, H, W, 3), got shape {arr.shape}")
    if arr.ndim == 4:
        return np.stack([transfer_colour(a, target, source, match_std=match_std) for a in arr])
    lab = rgb_to_lab(arr)
    stats = source if source is not None else colour_statistics(arr)
    rgb = np.clip(lab_to_rgb(transfer_lab(lab, stats, target, match_std=match_std)), 0.0, 1.0)
    if arr.dtype == np.uint8:
        return np.round(rgb * 255.0).astype(np.uint8)
    return rgb.astype(arr.dtype)


class ColourTransfer:
    """A reusable image → image map onto a target's colour statistics (for :class:`Segmenter`).

    Args:
        target: the training set's statistics (:func:`statistics_from_card` reads a model card's).
        source: fixed source statistics for a whole sequence (:meth:`fit_sequence`); None maps
            each image from its own statistics.
        match_std: Reinhard's full transfer (means and stds); False shifts the means only.
    """

    def __init__(
        self,
        target: ColourStatistics,
        source: ColourStatistics | None = None,
        *,
        match_std: bool = True,
    ) -> None:
        self.target = target
        self.source = source
        self.match_std = match_std

    def fit_sequence(self, images: Iterable[np.ndarray]) -> ColourTransfer:
        """Pool ``images``' statistics as the source of every later call; returns ``self``."""
        self.source = colour_statistics(images)
        return self

    def __call__(self, images: np.ndarray) -> np.ndarray:
        """`(H, W, 3)` or `(B, H, W, 3)` uint8 RGB → the same, mapped onto ``target``."""
        return transfer_colour(images, self.target, self.source, match_std=self.match_std)

    def __repr__(self) -> str:
        mode = "per image" if self.source is None else "fixed source"
        what = "means and stds" if self.match_std else "means only"
        return f"ColourTransfer({mode}, {what}, target={self.target})"


CARD_KEY = "colour_statistics"


def statistics_from_card(card: Mapping[str, Any], *, name: str = "model card") -> ColourStatistics:
    """The training set's colour statistics recorded in a model card (key ``colour_statistics``).

    Raises:
        GeosegError: the card records none (weights trained before this key existed: compute
            them with :func:`colour_statistics` over training images instead).
    """
    if CARD_KEY not in card:
        raise GeosegError(
            f"{name}: records no {CARD_KEY!r}; compute them from training images with "
            "geoseg.colour_transfer.colour_statistics"
        )
    return ColourStatistics.from_dict(card[CARD_KEY], name=f"{name}: {CARD_KEY}")


#: image files a reference folder is read from
REFERENCE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".webp")
#: most images of a reference folder read, evenly spaced (a model card's statistics come from
#: 64 training frames too)
REFERENCE_IMAGES = 64


def reference_statistics(path: str | Path) -> ColourStatistics:
    """The target statistics a reference file describes.

    Args:
        path: one image (its own statistics); a folder of images, directly or in ``rgb/`` (a
            render's layout), of which at most :data:`REFERENCE_IMAGES` evenly spaced ones
            give :func:`typical_statistics`; or a ``.json`` file: a model card
            (:func:`statistics_from_card`) or :meth:`ColourStatistics.as_dict` output.

    Raises:
        GeosegError: no such file or folder, a folder without images, an unreadable image, a
            JSON file of neither kind.
    """
    path = Path(path)
    if path.is_dir():
        folder = path / "rgb" if (path / "rgb").is_dir() else path
        files = sorted(
            p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in REFERENCE_SUFFIXES
        )
        if not files:
            raise GeosegError(
                f"{path}: a colour reference folder without images ({', '.join(REFERENCE_SUFFIXES)}"
                " directly or in rgb/)"
            )
        picks = np.unique(np.linspace(0, len(files) - 1, min(len(files), REFERENCE_IMAGES)).round())
        return typical_statistics(_read_rgb(files[int(i)]) for i in picks)
    if not path.is_file():
        raise GeosegError(
            f"{path}: no such colour reference (expected an image, a folder of images or a JSON "
            "file of colour statistics)"
        )
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise GeosegError(f"{path}: not a readable JSON file ({exc})") from None
        if not isinstance(data, dict):
            raise GeosegError(f"{path}: expected a JSON object, got {type(data).__name__}")
        if CARD_KEY in data:
            return statistics_from_card(data, name=str(path))
        return ColourStatistics.from_dict(data, name=str(path))
    return colour_statistics(_read_rgb(path))


def _read_rgb(path: Path) -> np.ndarray:
    """`(H, W, 3)` uint8 RGB of an image file (grey ones replicated)."""
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise GeosegError(f"{path}: not a readable image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
