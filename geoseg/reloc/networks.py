"""The networks of the localiser: loading the trunk and heads, and running them.

The base/query embedding (:func:`make_embedder`: the learned head of eq. 5.1, the raw layer-21
features or a thumbnail placeholder) and the relative poses of the relative-pose head (eq. 5.2,
:class:`HeadRelativePose`, optionally gated with the near head, :class:`GatedRelPoseHead`), over
the trunk's layer-21 features of images resized to the shipped networks' size.
:class:`geoseg.reloc.localizer.Localizer` chains them; ``geoseg base build`` embeds a base with
them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from geoseg.errors import GeosegError, check_positive

__all__ = [
    "NEAR_GATE_M",
    "NETWORK_SIZE",
    "FeatureCache",
    "GatedRelPoseHead",
    "HeadRelativePose",
    "head_relative_poses",
    "load_head",
    "load_trunk",
    "make_embedder",
    "shipped_weights",
]

# The image size the shipped networks were trained on, (W, H).
NETWORK_SIZE = (320, 240)

# The near head's distance (m) below which :class:`GatedRelPoseHead` takes it; chosen on
# validation city 13 (docs/lessons.md, "Queries at the base poses").
NEAR_GATE_M = 0.2


def make_embedder(
    embedding: str,
    segmenter: Any = None,
    *,
    reloc_head: str | Path | None = None,
    network_size: tuple[int, int] | None = NETWORK_SIZE,
    pool: tuple[int, int] | None = None,
    device: str = "cpu",
) -> tuple[Any, str, Any]:
    """The base/query embedding of :meth:`geoseg.reloc.localizer.Localizer.from_base`.

    Args:
        embedding: ``learned``, ``layer21`` or ``thumbnail``.
        segmenter: the trunk (:class:`~geoseg.infer.Segmenter`); None loads the shipped ``seg``
            (not needed for ``thumbnail``).
        reloc_head, network_size, pool, device: see
            :meth:`geoseg.reloc.localizer.Localizer.from_base`.

    Returns:
        ``(embed_fn (images -> (B, D)) with a cache ``name``, a description, the feature
        function or None)``.
    """
    from geoseg.reloc.image_base import ThumbnailEmbedder

    if embedding not in ("learned", "layer21", "thumbnail"):
        raise GeosegError(f"embedding: expected learned, layer21 or thumbnail, got {embedding!r}")
    if embedding == "thumbnail":
        feature_fn = None
        if segmenter is not None:
            feature_fn = FeatureCache(segmenter, _resizer(network_size))
        embedder: Any = ThumbnailEmbedder()
        return embedder, f"{embedder.name} (placeholder, not the learned embedding)", feature_fn
    if segmenter is None:
        segmenter = load_trunk(None, device)
    feature_fn = FeatureCache(segmenter, _resizer(network_size))
    if embedding == "layer21":
        embedder = _FeatureEmbedder(feature_fn, None, pool, _weights_tag("layer21", segmenter))
        name = "raw layer-21 features"
    else:
        head_path = Path(reloc_head) if reloc_head is not None else shipped_weights("reloc")
        head = load_head(head_path, "reloc", device)
        embedder = _FeatureEmbedder(
            feature_fn, head, None, _weights_tag("reloc", segmenter, head_path)
        )
        name = f"learned ({head_path.parent.name}/{head_path.name})"
    if embedder.name is not None and network_size is not None:
        embedder.name += f"-{network_size[0]}x{network_size[1]}"
    return embedder, name, feature_fn


def shipped_weights(name: str) -> Path:
    from geoseg.pretrained import pretrained_file

    return pretrained_file(name, "model.pt")


def load_trunk(path: str | Path | None, device: str) -> Any:
    """A :class:`~geoseg.infer.Segmenter` exposing layer-21 features (default: shipped seg)."""
    from geoseg.infer import Segmenter

    path = Path(path) if path is not None else shipped_weights("seg")
    if str(path).lower().endswith(".onnx"):
        from geoseg.export import available_providers

        return Segmenter.from_onnx(path, providers=available_providers(device))
    return Segmenter.from_checkpoint(path, device=device)


def load_head(path: str | Path, kind: str, device: str) -> Any:
    from geoseg.infer import load_model_checkpoint
    from geoseg.models.reloc import RelocHead
    from geoseg.models.relpose import RelPoseHead

    model, _ = load_model_checkpoint(path, map_location=device)
    expected = {"reloc": RelocHead, "relpose": RelPoseHead}[kind]
    if not isinstance(model, expected):
        raise GeosegError(
            f"{kind}_head: {path} holds a {type(model).__name__}, expected a {expected.__name__}"
        )
    return model.to(device).eval()


def _weights_tag(kind: str, segmenter: Any, head: Path | None = None) -> str | None:
    """A cache key naming the weight files (folder, name, size, mtime): a changed file gives
    another key, so a stale cache is never read."""
    parts = [kind]
    for p in (getattr(segmenter, "source", None), head):
        if p is None:
            return None
        p = Path(p)
        st = p.stat()
        parts.append(f"{p.parent.name}-{p.stem}-{st.st_size}-{st.st_mtime_ns}")
    return "-".join(parts)


def _resizer(size: tuple[int, int] | None) -> Callable[[np.ndarray], np.ndarray]:
    if size is None:
        return lambda image: image
    w, h = int(size[0]), int(size[1])

    def resize(image: np.ndarray) -> np.ndarray:
        import cv2

        if image.shape[0] == h and image.shape[1] == w:
            return image
        return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)

    return resize


class FeatureCache:
    """Image -> layer-21 features ``(C, h, w)`` float32 of the resized image; the features of
    base images (keyed by index) are kept, as each may be matched by many queries."""

    def __init__(self, segmenter: Any, resize: Callable[[np.ndarray], np.ndarray]) -> None:
        from geoseg.reloc.image_base import layer21_features

        self.features = layer21_features(segmenter)
        self.resize = resize
        self.base: dict[int, np.ndarray] = {}

    def __call__(self, image: np.ndarray) -> np.ndarray:
        return self.features(self.resize(np.asarray(image)))

    def of_base(self, base: Any, i: int) -> np.ndarray:
        if i not in self.base:
            self.base[i] = self(base.load_image(i))
        return self.base[i]


class _FeatureEmbedder:
    """Layer-21 features -> embedding: through a head (eq. 5.1), or flattened (optionally
    pooled) raw (§5.1.1). ``name`` is the cache key (None: no cache)."""

    def __init__(self, features: FeatureCache, head: Any, pool: Any, name: str | None) -> None:
        self.features = features
        self.head = head
        self.pool = None if pool is None else (int(pool[0]), int(pool[1]))
        self.name = name if pool is None or name is None else f"{name}-{pool[0]}x{pool[1]}"
        self.feature_shape: tuple[int, ...] | None = None

    def __call__(self, images: Sequence[Any]) -> np.ndarray:
        """``B`` RGB images -> ``(B, D)`` float64."""
        import torch
        import torch.nn.functional as F

        out = []
        for image in images:
            f = torch.from_numpy(np.ascontiguousarray(self.features(image)))[None]
            if self.head is not None:
                device = next(self.head.parameters()).device
                with torch.no_grad():
                    res = self.head(f.to(device))
                v = (res["embedding"] if isinstance(res, dict) else res)[0]
            elif self.pool is not None:
                v = F.adaptive_avg_pool2d(f, self.pool).flatten()
            else:  # flattened maps: one size for all images
                if self.feature_shape is None:
                    self.feature_shape = tuple(f.shape[1:])
                elif tuple(f.shape[1:]) != self.feature_shape:
                    raise GeosegError(
                        f"feature maps of mismatched sizes: {tuple(f.shape[1:])} vs "
                        f"{self.feature_shape} (images of different sizes: pool the features "
                        "or resize the images)"
                    )
                v = f.flatten()
            out.append(v.double().cpu().numpy())
        return np.stack(out)


class HeadRelativePose:
    """Relative poses base -> query from the relative-pose head, all matches in one batch."""

    def __init__(self, base: Any, features: FeatureCache, head: Any, device: str) -> None:
        self.base = base
        self.features = features
        self.head = head
        self.device = device

    def __call__(self, idx: np.ndarray, query: Any) -> list[dict[str, Any]]:
        import torch

        fq = torch.from_numpy(self.features(query))
        fa = torch.stack([torch.from_numpy(self.features.of_base(self.base, int(i))) for i in idx])
        if fa.shape[1:] != fq.shape:
            raise GeosegError(
                f"feature maps of mismatched sizes {tuple(fq.shape)} (query) vs "
                f"{tuple(fa.shape[1:])} (base): the relative-pose head needs images of one size"
            )
        return head_relative_poses(
            self.head, fa.to(self.device), fq[None].expand_as(fa).to(self.device)
        )


class GatedRelPoseHead:
    """The relative-pose head with a second head for the distance of views of one place.

    The shipped head (``relpose``, ``configs/relpose.yaml``) learned baselines of 0.5-10 m and
    reads two views of one place as 2-3 m apart (its rotation and direction stay right); its
    fine-tune with views of one place in other conditions (``relpose_near``,
    ``configs/relpose_near.yaml``) reads those distances right but is less accurate on the
    0.5-10 m baselines. So the distance of each pair is the near head's where the near head reads
    it below ``near_m``, else the far head's; rotation and direction are always the far head's.
    Both heads sit on the frozen trunk's layer-21 features: the gate costs one more head pass
    per pair, no more trunk work.

    Called like a :class:`geoseg.models.relpose.RelPoseHead`: ``(feat_a, feat_b)`` ``(B, C, h,
    w)`` each -> ``{"rotation" (B, 3), "direction" (B, 3), "log_distance" (B,), "near" (B,)
    bool}`` (``near``: the pairs whose distance is the near head's).

    Args:
        far: the head for baselines from 0.5 m up (predicting distances).
        near: the head for views of one place (predicting distances).
        near_m: the gate, metres (> 0).

    Raises:
        GeosegError: a head without the distance output, or a bad ``near_m``.
    """

    predict_distance = True

    def __init__(self, far: Any, near: Any, *, near_m: float = NEAR_GATE_M) -> None:
        for name, head in (("far", far), ("near", near)):
            if not getattr(head, "predict_distance", False):
                raise GeosegError(f"{name}: the gate needs a relative-pose head with distances")
        check_positive("near_m", near_m)
        self.far, self.near, self.near_m = far, near, float(near_m)

    def __call__(self, feat_a: Any, feat_b: Any) -> dict[str, Any]:
        import torch

        out = dict(self.far(feat_a, feat_b))
        near = self.near(feat_a, feat_b)["log_distance"]
        pick = near < math.log(self.near_m)
        out["log_distance"] = torch.where(pick, near, out["log_distance"])
        out["near"] = pick
        return out

    def eval(self) -> GatedRelPoseHead:
        self.far.eval()
        self.near.eval()
        return self

    def to(self, device: Any) -> GatedRelPoseHead:
        self.far.to(device)
        self.near.to(device)
        return self

    def parameters(self) -> Any:
        yield from self.far.parameters()
        yield from self.near.parameters()


def head_relative_poses(head: Any, feat_a: Any, feat_b: Any) -> list[dict[str, Any]]:
    """The relative-pose head's outputs as :data:`geoseg.reloc.localizer.RelativePoseFn` dicts.

    Args:
        head: a :class:`geoseg.models.relpose.RelPoseHead` or :class:`GatedRelPoseHead`.
        feat_a: ``(B, C, h, w)`` features of the base images.
        feat_b: ``(B, C, h, w)`` features of the query (repeated).

    Returns:
        ``B`` dicts (``distance_m`` None when the head predicts no distance).
    """
    import torch

    from geoseg.models.relpose import so3_exp

    with torch.no_grad():
        out = head(feat_a, feat_b)
    R_ab = so3_exp(out["rotation"].double()).cpu().numpy()
    t_dir = out["direction"].double().cpu().numpy()
    dist = out.get("log_distance")
    dist = None if dist is None else dist.double().exp().cpu().numpy()
    return [
        {
            "ok": True,
            "reason": "",
            "R_ab": R_ab[b],
            "t_dir_ab": t_dir[b],
            "distance_m": None if dist is None else float(dist[b]),
            "n_inliers": None,
        }
        for b in range(len(R_ab))
    ]
