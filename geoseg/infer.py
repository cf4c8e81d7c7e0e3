"""Inference API: :class:`Segmenter` over a torch checkpoint or an ONNX file, one call signature.

``segmenter(images)`` takes RGB uint8 images `(B, H, W, 3)` or `(H, W, 3)`, normalises them with
the mean/std stored with the model, runs the network and returns a :class:`SegmentationResult`
(class probabilities, labels, normals when the model predicts them, layer-21 features when it
exposes them).

Model checkpoints (:func:`save_model_checkpoint`) are dicts saved with ``torch.save``::

    {"format": "geoseg-model", "version": 1, "model_name": "joint", "model_config": {...},
     "state_dict": {...}, "normalization": {"mean": [r, g, b], "std": [r, g, b]}, ...}

Extra keys (optimizer, epoch, ... from a training checkpoint) are ignored. They are read with
``torch.load(..., weights_only=True)`` only, and carry a SHA-256 of their content (key
``"sha256"``, :mod:`geoseg.integrity`) that every load verifies.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from geoseg.checkpoint_format import BEST, LAST, validate_checkpoint
from geoseg.errors import GeosegError, check_shape
from geoseg.integrity import read_torch_file, save_torch_file, seal

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "geoseg-model"
# Smallest image side the networks accept: one layer-21 cell (the trunk downsamples by 8).
MIN_IMAGE_SIDE = 8
# ImageNet statistics, applied to images scaled to [0, 1]; trainers store their own.
DEFAULT_NORMALIZATION: dict[str, list[float]] = {
    "mean": [0.485, 0.456, 0.406],
    "std": [0.229, 0.224, 0.225],
}


def _check_normalization(name: str, norm: Mapping[str, Any]) -> dict[str, list[float]]:
    try:
        mean = [float(v) for v in norm["mean"]]
        std = [float(v) for v in norm["std"]]
    except (KeyError, TypeError, ValueError) as err:
        raise GeosegError(
            f"{name}: expected {{'mean': [3 floats], 'std': [3 floats]}} ({err})"
        ) from None
    if len(mean) != 3 or len(std) != 3 or min(std) <= 0:
        raise GeosegError(f"{name}: expected 3 means and 3 positive stds, got {mean}, {std}")
    return {"mean": mean, "std": std}


def save_model_checkpoint(
    model: nn.Module,
    path: str | os.PathLike,
    *,
    model_name: str,
    model_config: Mapping[str, Any] | None = None,
    normalization: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Save a model checkpoint atomically (temp file in the same directory + ``os.replace``).

    Args:
        model: the module whose ``state_dict()`` is saved.
        path: output file (parent directories created).
        model_name: registry name (``"enet"``, ``"joint"``, ``"naive_cnn"``, ...).
        model_config: the builder's keyword arguments (e.g. ``{"num_classes": 8}``).
        normalization: ``{"mean": [3], "std": [3]}`` for images scaled to [0, 1]
            (default :data:`DEFAULT_NORMALIZATION`).
        extra: more entries to store (must be ``weights_only``-loadable: tensors, numbers,
            strings, lists, dicts).

    Returns:
        The written path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload: dict[str, Any] = dict(extra or {})
    payload.update(
        format=CHECKPOINT_FORMAT,
        version=1,
        model_name=model_name,
        model_config=dict(model_config or {}),
        state_dict={k: v.detach().cpu() for k, v in model.state_dict().items()},
        normalization=_check_normalization("normalization", normalization or DEFAULT_NORMALIZATION),
    )
    save_torch_file(seal(payload), path)
    return path


MODEL_FILE = "model.pt"
# A run directory's weight files, in the order they are preferred (the trainers write best.pt
# and last.pt, geoseg.checkpoint_format).
RUN_WEIGHT_FILES = (MODEL_FILE, BEST, LAST)


def resolve_weights_file(path: str | os.PathLike) -> Path:
    """A weights file from a path: a file as is; a run directory's ``model.pt``, else
    ``best.pt``, else ``last.pt``.

    Raises:
        GeosegError: nothing usable at ``path``.
    """
    path = Path(path)
    if path.is_file():
        return path
    if path.is_dir():
        for name in RUN_WEIGHT_FILES:
            if (path / name).is_file():
                return path / name
        raise GeosegError(f"{path}: no {', '.join(RUN_WEIGHT_FILES)} in this run directory")
    raise GeosegError(f"{path}: no such checkpoint file or run directory")


def read_model_state(
    path: str | os.PathLike,
    *,
    expected_model: str | None = None,
    map_location: str | torch.device = "cpu",
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The one reader of model weights: a model checkpoint (``model.pt``, written by
    :func:`save_model_checkpoint`) or a training checkpoint (``best.pt``/``last.pt``), or a run
    directory holding one. Inference (:func:`load_model_checkpoint`) and the trainers
    (``training.common.load_state``) both read through it.

    Args:
        path: file or run directory (:func:`resolve_weights_file`).
        expected_model: registry name the checkpoint must hold (e.g. ``"enet"``).
        map_location: where to load the tensors.

    Returns:
        ``(state_dict, checkpoint)``.

    Raises:
        GeosegError: unreadable or corrupt file (SHA-256 mismatch), not a geoseg checkpoint,
            or another architecture than ``expected_model`` (the message names the file).
    """
    file = resolve_weights_file(path)
    ckpt = read_torch_file(file, map_location=map_location)
    if "state_dict" in ckpt:
        state = ckpt["state_dict"]
    elif "model" in ckpt and ckpt.get("format") is not None:
        ckpt = validate_checkpoint(ckpt, file)
        state = ckpt["model"]
    else:
        raise GeosegError(
            f"{file}: not a geoseg model or training checkpoint (missing 'state_dict', or "
            f"'model' and 'format'; found {sorted(map(str, ckpt))[:8]})"
        )
    name = ckpt.get("model_name")
    if expected_model is not None and name != expected_model:
        raise GeosegError(
            f"{file}: holds a {name!r} model, expected {expected_model!r} (another architecture)"
        )
    return dict(state), ckpt


def load_model_checkpoint(
    path: str | os.PathLike, *, map_location: str | torch.device = "cpu"
) -> tuple[nn.Module, dict[str, Any]]:
    """Rebuild a model from a checkpoint (:func:`read_model_state`).

    Args:
        path: the checkpoint file (or a run directory).
        map_location: where to load the tensors.

    Returns:
        ``(model in eval mode, checkpoint dict)``.

    Raises:
        GeosegError: missing or corrupt file (including a SHA-256 mismatch), CUDA asked for
            but unavailable, missing keys, unknown model, or weights that do not match the
            architecture (the message names the file).
    """
    from geoseg.models.registry import get_model

    path = Path(path)
    state, ckpt = read_model_state(path, map_location=map_location)
    if "model_name" not in ckpt:
        raise GeosegError(f"{path}: not a geoseg model checkpoint (missing ['model_name'])")
    try:
        model = get_model(ckpt["model_name"], **dict(ckpt.get("model_config") or {}))
    except GeosegError as err:
        raise GeosegError(f"{path}: {err}") from None
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as err:
        first = str(err).strip().splitlines()
        raise GeosegError(
            f"{path}: weights do not match the {ckpt['model_name']!r} architecture "
            f"({' '.join(first[:3])[:400]})"
        ) from None
    return model.eval(), ckpt


@dataclass
class SegmentationResult:
    """Outputs of a :class:`Segmenter` call (NumPy arrays).

    Attributes:
        probabilities: `(B, C, H, W)` float32 class probabilities.
        labels: `(B, H, W)` uint8 argmax class ids.
        normals: `(B, 3, H, W)` float32 unit normals (camera frame), or None.
        features: `(B, 128, ceil(H/8), ceil(W/8))` float32 layer-21 features, or None.
    """

    probabilities: np.ndarray
    labels: np.ndarray
    normals: np.ndarray | None = None
    features: np.ndarray | None = None


def _softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max(axis=1, keepdims=True))
    return e / e.sum(axis=1, keepdims=True)


def as_rgb(images: Any) -> np.ndarray:
    """Images as an RGB batch `(B, H, W, 3)`, grey ones replicated to three channels.

    A monochrome camera's frame (KITTI ``image_0``, say) is the grey image whose three channels
    are equal: the networks see exactly what they see for an RGB image of that grey (and
    ``training.frame_data.RandomGrayscale`` trains them on such images).

    Args:
        images: `(B, H, W, 3)`, `(H, W, 3)` (RGB), `(B, H, W, 1)`, `(H, W, 1)`, `(B, H, W)` or
            `(H, W)` (grey). A 3-D array whose last axis is 3 is one RGB image, any other 3-D
            array a batch of grey images (an image is at least ``MIN_IMAGE_SIDE`` wide).

    Returns:
        `(B, H, W, 3)`, of the input's dtype (a view or a copy).

    Raises:
        GeosegError: another number of dimensions or of channels.
    """
    images = np.asarray(images)
    if images.ndim == 2:
        images = images[None, :, :, None]
    elif images.ndim == 3:
        images = images[None] if images.shape[-1] in (1, 3) else images[..., None]
    if images.ndim != 4 or images.shape[-1] not in (1, 3):
        raise GeosegError(
            "images: expected RGB (B, H, W, 3) / (H, W, 3) or grey (B, H, W, 1) / (H, W, 1) / "
            f"(B, H, W) / (H, W), got shape {images.shape}"
        )
    if images.shape[-1] == 1:
        images = np.repeat(images, 3, axis=-1)
    return images


class Segmenter:
    """Image → labels (+ normals, features), over a torch module or an onnxruntime session.

    Build with :meth:`from_checkpoint` or :meth:`from_onnx`; call with RGB uint8 images.

    Args:
        backend: callable mapping a `(B, 3, H, W)` float32 NumPy batch to a dict of NumPy arrays
            with ``"logits"`` or ``"log_probs"``, and optionally ``"normals"``, ``"features"``.
        normalization: ``{"mean": [3], "std": [3]}`` for images scaled to [0, 1].
        model_name: name for messages and logs.
        source: the file the model came from.
        colour_transfer: maps the uint8 RGB images onto the training set's colour statistics
            before normalisation (:class:`geoseg.colour_transfer.ColourTransfer`, built with
            :func:`colour_transfer_for`); None = images as given. Also settable afterwards as
            the attribute of the same name.
    """

    def __init__(
        self,
        backend: Callable[[np.ndarray], Mapping[str, np.ndarray]],
        *,
        normalization: Mapping[str, Any] | None = None,
        model_name: str = "model",
        source: str | os.PathLike | None = None,
        colour_transfer: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        self.backend = backend
        self.colour_transfer = colour_transfer
        self.normalization = _check_normalization(
            "normalization", normalization or DEFAULT_NORMALIZATION
        )
        self.model_name = model_name
        self.source = None if source is None else Path(source)
        self._mean = np.asarray(self.normalization["mean"], np.float32)[None, :, None, None]
        self._std = np.asarray(self.normalization["std"], np.float32)[None, :, None, None]

    @classmethod
    def from_checkpoint(
        cls, path: str | os.PathLike, *, device: str | torch.device = "cpu"
    ) -> Segmenter:
        """Load a torch checkpoint (see :func:`load_model_checkpoint`) onto ``device``."""
        device = torch.device(device)
        model, ckpt = load_model_checkpoint(path, map_location=device)
        return cls.from_module(
            model,
            device=device,
            normalization=ckpt.get("normalization"),
            model_name=str(ckpt["model_name"]),
            source=path,
        )

    @classmethod
    def from_module(
        cls,
        model: nn.Module,
        *,
        device: str | torch.device = "cpu",
        normalization: Mapping[str, Any] | None = None,
        model_name: str = "model",
        source: str | os.PathLike | None = None,
    ) -> Segmenter:
        """A Segmenter over a torch segmentation network (ENet, joint, naive CNN) on ``device``.

        A failure inside torch (an allocator giving up on a large image, mostly) is a
        :class:`GeosegError` naming the batch's size and the way out.
        """
        from geoseg.models.naive_cnn import NaiveCNN

        device = torch.device(device)
        model.to(device).eval()
        if not isinstance(model, NaiveCNN) and not _is_image_model(model):
            raise GeosegError(f"{source}: model {model_name!r} is not a segmentation network")

        def backend(batch: np.ndarray) -> dict[str, np.ndarray]:
            try:
                x = torch.from_numpy(batch).to(device)
                with torch.inference_mode():
                    if isinstance(model, NaiveCNN):
                        out = {"log_probs": model.dense(x, band_rows=64)}
                    else:
                        out = model(x)
                return {k: v.float().cpu().numpy() for k, v in out.items()}
            except (RuntimeError, MemoryError) as err:  # allocator failures, mostly
                b, _, h, w = batch.shape
                first = (str(err).strip().splitlines() or [type(err).__name__])[0][:200]
                raise GeosegError(
                    f"{source}: the torch model failed on a batch of {b} image(s) of {w}x{h} "
                    f"pixels on {device} ({first}); downscale the images or use the ONNX model"
                ) from None

        return cls(backend, normalization=normalization, model_name=model_name, source=source)

    @classmethod
    def from_onnx(
        cls,
        path: str | os.PathLike,
        *,
        providers: Sequence[str] | None = None,
        frame_size: tuple[int, int] | str | None = "auto",
        threads: int | None = None,
    ) -> Segmenter:
        """Open an ONNX file written by :func:`geoseg.export.export_onnx`.

        Args:
            path: the ``.onnx`` file.
            providers: onnxruntime execution providers (default: CUDA when available, then CPU).
            frame_size: how onnxruntime sessions are fixed to input sizes (a fixed session runs
                the joint network at 640x480 in ~0.85x the dynamic session's time on this
                project's CPU): ``"auto"`` (default) fixes one session per batch shape on first
                use (``OnnxModel(fixed_dims="auto")``, a few shapes, ~0.2 s each); ``(H, W)``
                fixes the session to one image of that size (other inputs are rejected);
                ``None`` keeps one dynamic session.
            threads: onnxruntime intra-op threads (default: onnxruntime's).
        """
        from geoseg.export import OnnxModel

        fixed: Mapping[str, int] | str | None = None
        if frame_size == "auto":
            fixed = "auto"
        elif frame_size is not None:
            if isinstance(frame_size, str) or len(frame_size) != 2:
                raise GeosegError(
                    f"frame_size: expected (height, width), 'auto' or None, got {frame_size!r}"
                )
            height, width = frame_size
            fixed = {"batch": 1, "height": height, "width": width}
        onnx_model = OnnxModel(path, providers=providers, threads=threads, fixed_dims=fixed)
        outs = set(onnx_model.output_names)
        if not outs & {"logits", "log_probs"} or len(onnx_model.input_names) != 1:
            raise GeosegError(
                f"{path}: not a segmentation network (inputs {onnx_model.input_names}, "
                f"outputs {onnx_model.output_names}; expected one image input and 'logits' or "
                "'log_probs')"
            )
        return cls(
            onnx_model,
            normalization=onnx_model.metadata.get("normalization"),
            model_name=str(onnx_model.metadata.get("model_name", Path(path).stem)),
            source=path,
        )

    @classmethod
    def from_file(cls, path: str | os.PathLike, **kwargs) -> Segmenter:
        """:meth:`from_onnx` for ``.onnx`` files, :meth:`from_checkpoint` otherwise."""
        if str(path).lower().endswith(".onnx"):
            return cls.from_onnx(path, providers=kwargs.get("providers"))
        return cls.from_checkpoint(path, device=kwargs.get("device", "cpu"))

    def preprocess(self, images: np.ndarray) -> np.ndarray:
        """uint8 images → normalised float32 `(B, 3, H, W)`.

        Args:
            images: RGB `(B, H, W, 3)` or `(H, W, 3)`, or grey (a monochrome camera's frames)
                `(B, H, W)`, `(H, W)`, `(B, H, W, 1)` or `(H, W, 1)`, replicated to three
                channels (:func:`as_rgb`).
        """
        images = as_rgb(images)
        if images.dtype != np.uint8:
            raise GeosegError(
                f"images: expected uint8 RGB or grey images, got dtype {images.dtype}"
            )
        if images.shape[0] < 1:
            raise GeosegError(f"images: empty batch, shape {images.shape}")
        if min(images.shape[1:3]) < MIN_IMAGE_SIDE:
            raise GeosegError(
                f"images: {images.shape[2]}x{images.shape[1]} pixels is too small; the network "
                f"needs at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE}"
            )
        if self.colour_transfer is not None:
            images = self.colour_transfer(images)
        x = images.transpose(0, 3, 1, 2).astype(np.float32) / 255.0
        return np.ascontiguousarray((x - self._mean) / self._std)

    def __call__(self, images: np.ndarray) -> SegmentationResult:
        """Segment RGB images.

        Args:
            images: `(B, H, W, 3)` or `(H, W, 3)` uint8 RGB, or grey `(B, H, W)`, `(H, W)`,
                `(B, H, W, 1)`, `(H, W, 1)` (replicated to RGB, :func:`as_rgb`).

        Returns:
            A :class:`SegmentationResult` with a batch axis even for a single image.
        """
        out = self.backend(self.preprocess(images))
        if "logits" in out:
            scores = np.asarray(out["logits"], np.float32)
        elif "log_probs" in out:
            scores = np.asarray(out["log_probs"], np.float32)
        else:
            raise GeosegError(f"{self.source}: model returned no 'logits' or 'log_probs'")
        for name in ("logits", "log_probs", "normals", "features"):
            value = out.get(name)
            if value is None:
                continue
            value = np.asarray(value)  # log-probabilities may be -inf (a probability of 0)
            bad = np.isnan(value) | (
                value == np.inf if name == "log_probs" else ~np.isfinite(value)
            )
            if bad.any():
                raise GeosegError(
                    f"{self.source}: the model produced NaN or infinite {name} for this image "
                    "(corrupt or diverged weights?); no result is returned"
                )
        probs = _softmax(scores) if "logits" in out else np.exp(scores)
        return SegmentationResult(
            probabilities=probs.astype(np.float32, copy=False),
            labels=probs.argmax(axis=1).astype(np.uint8),
            normals=None if out.get("normals") is None else np.asarray(out["normals"], np.float32),
            features=None
            if out.get("features") is None
            else np.asarray(out["features"], np.float32),
        )


def training_colour_statistics(model_path: str | os.PathLike) -> Any:
    """The training set's colour statistics recorded in the ``model_card.json`` beside the
    weights file ``model_path`` (:func:`geoseg.colour_transfer.statistics_from_card`).

    Returns:
        A :class:`geoseg.colour_transfer.ColourStatistics`.

    Raises:
        GeosegError: no model card beside the weights, or a card without statistics.
    """
    import json

    from geoseg.colour_transfer import statistics_from_card

    card_path = Path(model_path).parent / "model_card.json"
    if not card_path.is_file():
        raise GeosegError(
            f"colour transfer: no model card {card_path} beside {model_path} to read the "
            "training set's colour statistics from"
        )
    return statistics_from_card(json.loads(card_path.read_text()), name=str(card_path))


def colour_transfer_for(
    model_path: str | os.PathLike,
    *,
    mode: str = "image",
    sequence: Sequence[np.ndarray] = (),
    match_std: bool = True,
) -> Any:
    """A colour transfer onto the training set of the weights at ``model_path``.

    The target statistics come from the ``model_card.json`` beside the weights file
    (:func:`geoseg.colour_transfer.statistics_from_card`).

    Args:
        model_path: the ``.onnx`` or ``.pt`` file (its folder holds the model card).
        mode: ``"image"`` maps each image from its own statistics; ``"sequence"`` maps every
            image from the pooled statistics of ``sequence`` (steadier along a drive).
        sequence: `(H, W, 3)` uint8 RGB images of the sequence (``mode="sequence"`` only).
        match_std: Reinhard's full transfer (means and stds per channel); False shifts the
            means only.

    Returns:
        A :class:`geoseg.colour_transfer.ColourTransfer` for :class:`Segmenter`.

    Raises:
        GeosegError: no model card beside the weights, a card without statistics, an unknown
            mode, or ``"sequence"`` without images.
    """
    from geoseg.colour_transfer import ColourTransfer

    if mode not in ("image", "sequence"):
        raise GeosegError(f"colour transfer mode: expected image or sequence, got {mode!r}")
    transfer = ColourTransfer(training_colour_statistics(model_path), match_std=match_std)
    if mode == "sequence":
        if len(sequence) == 0:
            raise GeosegError("colour transfer mode 'sequence': no images to pool statistics from")
        transfer.fit_sequence(sequence)
    return transfer


def _is_image_model(model: nn.Module) -> bool:
    from geoseg.models.enet import ENet
    from geoseg.models.joint import JointNet

    return isinstance(model, ENet | JointNet)


def normals_to_rgb(normals: np.ndarray) -> np.ndarray:
    """Encode unit normals `(3, H, W)` as an RGB uint8 image `(H, W, 3)`: ``(n + 1) / 2 * 255``."""
    check_shape("normals", normals, (3, None, None))
    rgb = (np.clip(normals.transpose(1, 2, 0), -1.0, 1.0) + 1.0) * 127.5
    return np.round(rgb).astype(np.uint8)
