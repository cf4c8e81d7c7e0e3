"""Joint labels + surface-normals network (thesis fig. 4.18): a shared ENet trunk, two heads.

The ENet trunk up to layer 21 is shared, then two heads with the architecture of the remaining
ENet layers (bottlenecks 3.7, 3.8, stage 4, stage 5 and the final transposed convolution) predict
the label logits (C channels) and the surface normals (3 channels, L2-normalised to unit length,
camera frame). The decoders unpool with the max-pooling indices of the shared encoder.

Layer counting (one layer per ENet block, as in the issue): initial = 1, 1.0 = 2, 1.1-1.4 = 3-6,
2.0 = 7, 2.1-2.8 = 8-15, 3.1-3.8 = 16-23, so layer 21 is bottleneck 3.6 and the heads start at
3.7. The thesis text (§4.3.2) says the branching layer "must sit in the decoder"; with ENet's
29 blocks that would need another counting (e.g. counting every convolution or module). We follow
the issue's block counting, which puts layer 21 at the end of the encoder, and say so here.

Training follows the thesis (no dataset has both labels and normals): train a plain
:class:`~geoseg.models.enet.ENet` for segmentation, copy it in with :meth:`JointNet.load_enet_weights`,
then call :meth:`JointNet.freeze_trunk_and_labels` (or build with ``freeze_trunk=True``) and train
the normals head alone (transfer learning). Frozen modules get ``requires_grad=False`` and stay
in eval mode (batch-norm running statistics and dropout frozen) even under ``model.train()``.

For 8 classes the network has 434,466 parameters: 359,199 for the ENet part and 75,267 (+21.0 %)
for the normals head (the thesis reports ~10 % for its layer-21 branch).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

from geoseg.classes import NUM_CLASSES
from geoseg.errors import GeosegError, check_positive
from geoseg.models.checks import check_image_tensor
from geoseg.models.enet import ENet, ENetHead, ENetTrunk, crop_to, pad_to_multiple

logger = logging.getLogger(__name__)


class UnitNormals(nn.Module):
    """Surface normals L2-normalised along the channels: `(B, 3, H, W)` → unit vectors
    (``F.normalize``, ``eps`` guarding zero vectors). A module so that the ONNX export can swap
    in a form onnxruntime runs faster (:mod:`geoseg.export_rewrites`)."""

    def __init__(self, eps: float = 1e-6) -> None:
        super().__init__()
        self.eps = eps

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return F.normalize(raw, dim=1, eps=self.eps)


class JointNet(nn.Module):
    """Shared ENet trunk (layers 1-21) + label head + normals head.

    Args:
        num_classes: label classes C.
        in_channels: image channels.
        freeze_trunk: freeze the trunk and the label head at construction
            (see :meth:`freeze_trunk_and_labels`).

    Forward:
        x: `(B, 3, H, W)` float normalised image, any H, W >= 1 (replicate-padded to multiples of
        8 internally, outputs cropped back).

        Returns ``{"logits": (B, C, H, W), "normals": (B, 3, H, W) unit vectors,
        "features": (B, 128, ceil(H/8), ceil(W/8))}`` (layer-21 map of the padded input).
    """

    def __init__(
        self, *, num_classes: int = NUM_CLASSES, in_channels: int = 3, freeze_trunk: bool = False
    ) -> None:
        super().__init__()
        check_positive("num_classes", num_classes)
        self.num_classes = num_classes
        self.in_channels = in_channels
        self.trunk = ENetTrunk(in_channels)
        self.label_head = ENetHead(num_classes)
        self.normal_head = ENetHead(3)
        self.unit_normals = UnitNormals()
        self._frozen = False
        if freeze_trunk:
            self.freeze_trunk_and_labels()

    @property
    def frozen(self) -> bool:
        """Whether the trunk and the label head are frozen."""
        return self._frozen

    def freeze_trunk_and_labels(self, frozen: bool = True) -> JointNet:
        """Freeze (or unfreeze) the trunk and the label head for training the normals head.

        Frozen parameters get ``requires_grad=False`` and the frozen modules stay in eval mode
        (batch-norm statistics and dropout fixed) even when ``train()`` is called.

        Returns:
            ``self``.
        """
        self._frozen = frozen
        for module in (self.trunk, self.label_head):
            for p in module.parameters():
                p.requires_grad_(not frozen)
        return self.train(self.training)

    def train(self, mode: bool = True) -> JointNet:
        super().train(mode)
        if self._frozen:
            self.trunk.eval()
            self.label_head.eval()
        return self

    def load_enet_weights(self, enet_state: ENet | Mapping[str, torch.Tensor]) -> JointNet:
        """Initialise the trunk and the label head from a trained plain ENet.

        Args:
            enet_state: an :class:`ENet` or its ``state_dict()`` (keys ``trunk.*`` and ``head.*``).

        Returns:
            ``self``.

        Raises:
            GeosegError: keys or shapes that do not match (another architecture or class count).
        """
        state = enet_state.state_dict() if isinstance(enet_state, nn.Module) else enet_state
        trunk = {k[len("trunk.") :]: v for k, v in state.items() if k.startswith("trunk.")}
        head = {k[len("head.") :]: v for k, v in state.items() if k.startswith("head.")}
        others = [k for k in state if not k.startswith(("trunk.", "head."))]
        if others:
            raise GeosegError(f"enet_state: unexpected keys for an ENet state dict: {others[:5]}")
        for name, module, sub in (("trunk", self.trunk, trunk), ("head", self.label_head, head)):
            try:
                module.load_state_dict(sub, strict=True)
            except RuntimeError as err:
                raise GeosegError(f"enet_state: does not match the joint {name}: {err}") from None
        return self

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        check_image_tensor("x", x, channels=self.in_channels)
        h, w = x.shape[-2], x.shape[-1]
        features, indices1, indices2 = self.trunk(pad_to_multiple(x))
        logits = crop_to(self.label_head(features, indices1, indices2), h, w)
        raw = crop_to(self.normal_head(features, indices1, indices2), h, w)
        normals = self.unit_normals(raw)
        return {"logits": logits, "normals": normals, "features": features}


def joint(
    *, num_classes: int = NUM_CLASSES, in_channels: int = 3, freeze_trunk: bool = False
) -> JointNet:
    """Build the joint labels + normals network (randomly initialised); see :class:`JointNet`."""
    return JointNet(num_classes=num_classes, in_channels=in_channels, freeze_trunk=freeze_trunk)
