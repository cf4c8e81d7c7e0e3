"""Relocalisation embedding head on ENet layer-21 features (thesis §5.1.1, fig. 5.5, eq. 5.1).

The head sits after the (frozen) ENet trunk, whose layer 21 (bottleneck 3.6) gives
``(B, 128, h, w)`` features with ``h = H / 8``, ``w = W / 8``. Following fig. 5.5 it "reduces the
dimensionality and allows a few simple transformations to bring the clusters together": two
convolutions (3x3 stride 2 keeping 128 channels, then 1x1 down to ``hidden_channels``), global
mean and max pooling concatenated, and a linear layer to ``embedding_dim``. The same module
(shared weights) embeds the three images of a triplet.

L2-normalised or raw. The thesis trains with eq. 5.1 on L2 distances between the embeddings
and does not say whether they are normalised. We L2-normalise by default (``normalize=True``):
eq. 5.1 equals ``softplus(d+ - d-)`` and only depends on the *difference* of distances, so with
raw embeddings the network lowers the loss by inflating the embedding scale without improving
the ranking, and the loss goes to 0 on easy triplets. On the unit sphere ``d`` lies in
``[0, 2]``, the loss keeps a floor of ``softplus(-2) ~= 0.127`` and keeps pushing hard triplets,
and retrieval by L2 distance equals retrieval by cosine similarity. ``normalize=False`` gives
the raw embedding. :func:`triplet_loss` has a ``scale`` (inverse temperature, default 1 = the
thesis) for sharper losses on normalised embeddings.

:class:`RawFeatureEmbedder` is the §5.1.1 baseline: the raw layer-21 features, optionally
average-pooled, flattened; matched by Euclidean distance (7.2 % wrong top-1 on the thesis's
spring/winter tram sequences, 0.4 % with a GPS window). Both modules return
``{"embedding": (B, D)}`` and feed :class:`geoseg.reloc.retrieval.RetrievalIndex`.

Export: the forward passes use only convolutions, batch norm, ``mean``/``amax`` over the
spatial dimensions and ``F.normalize``; input checks are skipped while tracing/exporting, so
``torch.onnx.export(..., dynamo=True)`` works with dynamic batch and ``h``/``w``.
"""

from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from torch import nn

from geoseg.errors import GeosegError, check_finite
from geoseg.models.checks import is_exporting

logger = logging.getLogger(__name__)

__all__ = [
    "RawFeatureEmbedder",
    "RelocHead",
    "check_features",
    "raw_feature_embedder",
    "reloc_head",
    "triplet_loss",
]


def check_features(name: str, x: object, in_channels: int) -> None:
    """Validate a layer-21 feature map ``(B, in_channels, h, w)`` (floating, finite).

    Raises:
        GeosegError: naming ``name``, for a non-tensor, a wrong rank or channel count, an
            integer dtype or NaN/inf values.
    """
    if not isinstance(x, torch.Tensor):
        raise GeosegError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 4 or x.shape[1] != in_channels:
        raise GeosegError(f"{name}: expected shape (B, {in_channels}, h, w), got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise GeosegError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if x.shape[0] == 0 or x.shape[2] == 0 or x.shape[3] == 0:
        raise GeosegError(f"{name}: empty tensor of shape {tuple(x.shape)}")
    check_finite(name, x)


def _conv_bn_relu(cin: int, cout: int, k: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class RelocHead(nn.Module):
    """Siamese embedding head of fig. 5.5 (one branch; weights shared across the triplet).

    Args:
        in_channels: channels of the layer-21 features (128 for ENet).
        embedding_dim: ``D``.
        hidden_channels: channels after the 1x1 reduction.
        normalize: L2-normalise the embedding (default; see the module docstring).
    """

    def __init__(
        self,
        *,
        in_channels: int = 128,
        embedding_dim: int = 128,
        hidden_channels: int = 64,
        normalize: bool = True,
    ) -> None:
        super().__init__()
        for name, v in (
            ("in_channels", in_channels),
            ("embedding_dim", embedding_dim),
            ("hidden_channels", hidden_channels),
        ):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise GeosegError(f"{name}: expected an int >= 1, got {v!r}")
        self.in_channels = in_channels
        self.embedding_dim = embedding_dim
        self.normalize = bool(normalize)
        self.reduce = nn.Sequential(
            _conv_bn_relu(in_channels, in_channels, 3, stride=2),
            _conv_bn_relu(in_channels, hidden_channels, 1),
        )
        self.fc = nn.Linear(2 * hidden_channels, embedding_dim)

    def forward(self, features: torch.Tensor) -> dict[str, torch.Tensor]:
        """Embed layer-21 features.

        Args:
            features: ``(B, in_channels, h, w)`` float.

        Returns:
            ``{"embedding": (B, embedding_dim)}``, unit L2 norm when ``normalize``.
        """
        if not is_exporting():
            check_features("features", features, self.in_channels)
        x = self.reduce(features)
        pooled = torch.cat([x.mean(dim=(2, 3)), x.amax(dim=(2, 3))], dim=1)
        emb = self.fc(pooled)
        if self.normalize:
            emb = F.normalize(emb, p=2.0, dim=1, eps=1e-12)
        return {"embedding": emb}


def reloc_head(
    *,
    in_channels: int = 128,
    embedding_dim: int = 128,
    normalize: bool = True,
    hidden_channels: int = 64,
) -> RelocHead:
    """Build the relocalisation embedding head (fig. 5.5). See :class:`RelocHead`."""
    return RelocHead(
        in_channels=in_channels,
        embedding_dim=embedding_dim,
        hidden_channels=hidden_channels,
        normalize=normalize,
    )


class RawFeatureEmbedder(nn.Module):
    """Baseline of §5.1.1: flattened (optionally average-pooled) raw layer-21 features.

    Args:
        in_channels: expected channels of the features (128 for ENet).
        pool: average-pooling factor (kernel = stride = ``pool``) before flattening; None keeps
            the full resolution. The embedding size then depends on ``h``, ``w``.
        output_size: ``(h', w')`` adaptive average pooling target instead of ``pool``, which
            makes ``D = in_channels * h' * w'`` independent of the image size.
        normalize: L2-normalise the flattened vector (the thesis compares raw features: False).
    """

    def __init__(
        self,
        *,
        in_channels: int = 128,
        pool: int | None = None,
        output_size: tuple[int, int] | None = None,
        normalize: bool = False,
    ) -> None:
        super().__init__()
        if pool is not None and output_size is not None:
            raise GeosegError("pool, output_size: give at most one of them")
        if pool is not None and (isinstance(pool, bool) or not isinstance(pool, int) or pool < 1):
            raise GeosegError(f"pool: expected an int >= 1, got {pool!r}")
        if output_size is not None:
            if len(output_size) != 2 or any(int(s) < 1 for s in output_size):
                raise GeosegError(f"output_size: expected (h', w') >= 1, got {output_size!r}")
            output_size = (int(output_size[0]), int(output_size[1]))
        self.in_channels = in_channels
        self.pool = pool
        self.output_size = output_size
        self.normalize = bool(normalize)

    def forward(self, features: torch.Tensor) -> dict[str, torch.Tensor]:
        """Flatten layer-21 features.

        Args:
            features: ``(B, in_channels, h, w)`` float.

        Returns:
            ``{"embedding": (B, D)}`` with ``D = in_channels * h' * w'``.
        """
        if not is_exporting():
            check_features("features", features, self.in_channels)
            if self.pool is not None and (
                features.shape[2] < self.pool or features.shape[3] < self.pool
            ):
                raise GeosegError(
                    f"features: spatial size {tuple(features.shape[2:])} smaller than "
                    f"pool={self.pool}"
                )
        x = features
        if self.output_size is not None:
            x = F.adaptive_avg_pool2d(x, self.output_size)
        elif self.pool is not None and self.pool > 1:
            x = F.avg_pool2d(x, self.pool, stride=self.pool)
        emb = x.flatten(1)
        if self.normalize:
            emb = F.normalize(emb, p=2.0, dim=1, eps=1e-12)
        return {"embedding": emb}


def raw_feature_embedder(
    *,
    in_channels: int = 128,
    pool: int | None = None,
    output_size: tuple[int, int] | None = None,
    normalize: bool = False,
) -> RawFeatureEmbedder:
    """Build the raw layer-21 matching baseline. See :class:`RawFeatureEmbedder`."""
    return RawFeatureEmbedder(
        in_channels=in_channels, pool=pool, output_size=output_size, normalize=normalize
    )


def _l2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(B,)`` Euclidean distances with a finite gradient at ``a == b``."""
    sq = (a - b).square().sum(dim=1)
    return torch.sqrt(torch.clamp(sq, min=1e-12))


def triplet_loss(
    ref: torch.Tensor,
    match: torch.Tensor,
    other: torch.Tensor,
    *,
    scale: float = 1.0,
    reduction: str = "mean",
) -> torch.Tensor:
    """Eq. 5.1: ``-log(e^{-d+} / (e^{-d+} + e^{-d-}))`` with L2 distances.

    ``d+ = |ref - match|``, ``d- = |ref - other|``. Since
    ``e^{-d+} / (e^{-d+} + e^{-d-}) = 1 / (1 + e^{d+ - d-})``, the loss equals
    ``softplus(d+ - d-)``, computed as such (stable for any distance gap). ``scale`` multiplies
    the distance gap (``softplus(scale (d+ - d-))``; 1 = the thesis). Distances below 1e-6 are
    clamped (``sqrt(max(|.|^2, 1e-12))``) so that identical embeddings have a finite gradient.

    Args:
        ref, match, other: ``(B, D)`` embeddings.
        scale: inverse temperature, > 0.
        reduction: ``"mean"``, ``"sum"`` or ``"none"`` (``(B,)``).

    Returns:
        Scalar loss, or ``(B,)`` with ``reduction="none"``.
    """
    if not isinstance(ref, torch.Tensor) or ref.ndim != 2:
        raise GeosegError(f"ref: expected a (B, D) tensor, got {getattr(ref, 'shape', ref)!r}")
    for name, t in (("match", match), ("other", other)):
        if not isinstance(t, torch.Tensor) or t.shape != ref.shape:
            raise GeosegError(
                f"{name}: expected shape {tuple(ref.shape)}, got {tuple(getattr(t, 'shape', ()))}"
            )
    if reduction not in ("mean", "sum", "none"):
        raise GeosegError(f"reduction: expected 'mean', 'sum' or 'none', got {reduction!r}")
    if not scale > 0:
        raise GeosegError(f"scale: expected > 0, got {scale!r}")
    loss = F.softplus(scale * (_l2(ref, match) - _l2(ref, other)))
    if reduction == "mean":
        return loss.mean()
    if reduction == "sum":
        return loss.sum()
    return loss
