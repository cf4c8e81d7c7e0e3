"""Relative-pose head on two ENet layer-21 feature maps (thesis §5.1.2, figs. 5.6-5.7, eq. 5.2).

A siamese encoder runs on each ``(B, 128, h, w)`` map, the two are fused (``[a, b, a * b]``,
plus a cost volume with ``correlation_radius > 0``, :func:`correlation_volume`) and an MLP
regresses a rotation vector and a unit direction (and, with ``predict_distance=True``, the log
of the baseline in metres, an extension of the thesis). Conventions: ``R_ab = R_wc_a^T R_wc_b``,
``t_dir_ab`` the unit direction from camera ``a``'s centre to ``b``'s in camera ``a``'s frame
(:func:`relative_pose_labels`; the ray :func:`geoseg.reloc.retrieval.absolute_position` casts
from a base camera), ``R = exp([w]x)`` (:func:`to_thesis_coefficients` /
:func:`from_thesis_coefficients` convert to the thesis's basis); the loss is eq. 5.2 with a
right rotation error. Exportable (dynamic batch and ``h``/``w``). The architecture, the
conventions in full and the reasons for the distance output and the cost volume:
``docs/networks.md`` ("The relative-pose head").
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from geoseg.errors import GeosegError, check_finite, check_shape
from geoseg.models.checks import is_exporting
from geoseg.models.reloc import check_features

logger = logging.getLogger(__name__)

__all__ = [
    "RelPoseHead",
    "correlation_volume",
    "from_thesis_coefficients",
    "log_distance_error",
    "relative_pose_labels",
    "relpose_head",
    "relpose_loss",
    "so3_exp",
    "so3_hat",
    "so3_log",
    "so3_vee",
    "to_thesis_coefficients",
]

# Below this squared angle the Taylor expansions are used (their truncation error is ~theta^6).
_SMALL = 1e-6
# Initial log-baseline output: ~4 m, mid-range of the training pairs (0.5-10 m).
_LOG_DISTANCE_INIT = float(np.log(4.0))
# cos(theta) below this uses the near-pi branch of the logarithm (theta > ~177.4 degrees).
_NEAR_PI_COS = -0.999


# ============================================================================ SO(3)


def so3_hat(w: torch.Tensor) -> torch.Tensor:
    """Usual hat: ``(..., 3)`` -> ``(..., 3, 3)`` skew matrix with ``hat(w) x = w x x``."""
    w1, w2, w3 = w.unbind(-1)
    z = torch.zeros_like(w1)
    return torch.stack(
        [
            torch.stack([z, -w3, w2], dim=-1),
            torch.stack([w3, z, -w1], dim=-1),
            torch.stack([-w2, w1, z], dim=-1),
        ],
        dim=-2,
    )


def so3_vee(m: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`so3_hat` on the skew part: ``(..., 3, 3)`` -> ``(..., 3)``."""
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        dim=-1,
    )


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: ``(..., 3)`` rotation vectors -> ``(..., 3, 3)`` rotation matrices.

    ``R = I + A [w]x + B [w]x^2`` with ``A = sin(t)/t``, ``B = (1 - cos t)/t^2``; for
    ``t^2 < 1e-6`` their Taylor series (``1 - t^2/6 + t^4/120``, ``1/2 - t^2/24 + t^4/720``) so
    that the value and gradient are exact and finite at ``w = 0``.
    """
    t2 = (w * w).sum(-1)
    small = t2 < _SMALL
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(t2_safe)
    a = torch.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - torch.cos(t)) / t2_safe)
    k = so3_hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(r: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` rotation matrices -> ``(..., 3)`` rotation vectors (angle in [0, pi]).

    With ``v = vee(R - R^T)/2 = sin(t) n`` and ``c = (tr R - 1)/2 = cos(t)``:

    * ``|v|^2 < 1e-6`` and ``c > 0`` (near the identity): ``w = v (1 + s^2/6 + 3 s^4/40)`` with
      ``s^2 = |v|^2`` (the series of ``asin(s)/s``): finite value and gradient at ``R = I``;
    * ``c < -0.999`` (near pi): the axis from the symmetric part,
      ``n n^T = ((R + R^T)/2 - c I) / (1 - c)``, column of largest diagonal, sign of ``v``;
    * otherwise ``w = v t / sin(t)`` with ``t = atan2(|v|, c)``.
    """
    v = so3_vee(r)
    c = ((r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2] - 1.0) * 0.5).clamp(-1.0, 1.0)
    s2 = (v * v).sum(-1)
    small = (s2 < _SMALL) & (c > 0)
    near_pi = c < _NEAR_PI_COS
    # general branch
    s2_safe = torch.where(small | near_pi, torch.ones_like(s2), s2)
    s = torch.sqrt(s2_safe)
    c_gen = torch.where(small | near_pi, torch.zeros_like(c), c)
    theta = torch.atan2(s, c_gen)
    w_general = v * (theta / s)[..., None]
    # identity branch
    w_small = v * (1.0 + s2 / 6.0 + 3.0 * s2 * s2 / 40.0)[..., None]
    # near-pi branch
    c_pi = torch.where(near_pi, c, -torch.ones_like(c))
    s_pi = torch.sqrt(torch.where(near_pi, s2, torch.zeros_like(s2)).clamp_min(1e-30))
    theta_pi = torch.atan2(s_pi, c_pi)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    sym = 0.5 * (r + r.transpose(-1, -2)) - c_pi[..., None, None] * eye
    nnt = sym / (1.0 - c_pi)[..., None, None]
    diag = torch.diagonal(nnt, dim1=-2, dim2=-1)
    j = diag.argmax(-1, keepdim=True)
    col = torch.gather(nnt, -1, j[..., None].expand(*nnt.shape[:-1], 1)).squeeze(-1)
    dj = torch.gather(diag, -1, j).clamp_min(1e-12)
    n = col / torch.sqrt(dj)
    sign = torch.where((n * v).sum(-1) < 0, -torch.ones_like(c), torch.ones_like(c))
    w_pi = n * (sign * theta_pi)[..., None]
    out = torch.where(small[..., None], w_small, w_general)
    return torch.where(near_pi[..., None], w_pi, out)


def to_thesis_coefficients(w: torch.Tensor) -> torch.Tensor:
    """Usual rotation vector ``(..., 3)`` -> thesis eq. 1.44 coefficients ``(-w3, -w2, -w1)``."""
    return -w.flip(-1)


def from_thesis_coefficients(alpha: torch.Tensor) -> torch.Tensor:
    """Thesis eq. 1.44 coefficients ``(..., 3)`` -> usual rotation vector ``(-a3, -a2, -a1)``."""
    return -alpha.flip(-1)


# ============================================================================ labels


def relative_pose_labels(R_wc_a: Any, t_wc_a: Any, R_wc_b: Any, t_wc_b: Any) -> tuple[Any, Any]:
    """Relative-pose targets of the pair ``(a, b)`` from two camera-to-world poses.

    ``R_ab = R_wc_a^T R_wc_b`` and ``t_dir_ab = t_ab / |t_ab|`` with
    ``t_ab = R_wc_a^T (t_wc_b - t_wc_a)``: the unit direction from camera a towards camera b,
    in camera a's frame (``X_a = R_ab X_b + t_ab``).

    Args:
        R_wc_a, R_wc_b: ``(3, 3)`` or ``(B, 3, 3)`` rotations (camera-to-world).
        t_wc_a, t_wc_b: ``(3,)`` or ``(B, 3)`` camera centres in the world frame.

    Returns:
        ``(R_ab (..., 3, 3), t_dir_ab (..., 3))``, torch tensors if the inputs are tensors, else
        float64 NumPy arrays.

    Raises:
        GeosegError: mismatched shapes, NaN, or coincident camera centres (no direction).
    """
    as_torch = isinstance(R_wc_a, torch.Tensor)
    vals = []
    for name, v in (("R_wc_a", R_wc_a), ("t_wc_a", t_wc_a), ("R_wc_b", R_wc_b), ("t_wc_b", t_wc_b)):
        t = v if isinstance(v, torch.Tensor) else torch.as_tensor(np.asarray(v, dtype=np.float64))
        check_finite(name, t)
        vals.append(t)
    ra, ta, rb, tb = vals
    batch = ra.shape[:-2]
    check_shape("R_wc_a", ra, (*batch, 3, 3))
    check_shape("R_wc_b", rb, (*batch, 3, 3))
    check_shape("t_wc_a", ta, (*batch, 3))
    check_shape("t_wc_b", tb, (*batch, 3))
    dtype = torch.promote_types(ra.dtype, ta.dtype)
    ra, ta, rb, tb = (x.to(dtype) for x in (ra, ta, rb, tb))
    rt = ra.transpose(-1, -2)
    r_ab = rt @ rb
    t_ab = (rt @ (tb - ta)[..., None])[..., 0]
    norm = torch.linalg.vector_norm(t_ab, dim=-1, keepdim=True)
    if bool((norm <= 1e-12).any()):
        raise GeosegError("t_wc_a, t_wc_b: coincident camera centres, the direction is undefined")
    t_dir = t_ab / norm
    if as_torch:
        return r_ab, t_dir
    return r_ab.numpy(), t_dir.numpy()


# ============================================================================ head + loss


def correlation_volume(a: torch.Tensor, b: torch.Tensor, radius: int) -> torch.Tensor:
    """Cosine cost volume between two feature maps.

    Args:
        a: ``(B, C, h, w)`` features of the first image.
        b: ``(B, C, h, w)`` features of the second image.
        radius: largest displacement ``r`` in cells, >= 1.

    Returns:
        ``(B, (2r + 1)^2, h, w)``: channel ``(dy + r) (2r + 1) + (dx + r)`` holds the cosine of
        ``a[..., y, x]`` and ``b[..., y + dy, x + dx]`` (0 where the displaced cell falls outside).
    """
    a = F.normalize(a, dim=1, eps=1e-6)
    b = F.pad(F.normalize(b, dim=1, eps=1e-6), (radius, radius, radius, radius))
    h, w = a.shape[-2], a.shape[-1]
    size = 2 * radius + 1
    return torch.cat(
        [
            (a * b[..., dy : dy + h, dx : dx + w]).sum(dim=1, keepdim=True)
            for dy in range(size)
            for dx in range(size)
        ],
        dim=1,
    )


def _conv_bn_relu(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class RelPoseHead(nn.Module):
    """Siamese relative-pose regressor of fig. 5.7.

    Args:
        in_channels: channels of the layer-21 features (128 for ENet).
        hidden_channels: channels of each encoder branch's output.
        fc_dim: width of the hidden layer of the regression MLP.
        correlation_radius: radius ``r`` of the cost volume added to the fusion
            (:func:`correlation_volume`, on the branch maps, i.e. 1/16 of the image); 0: none.
        predict_distance: also regress ``log |t_ab|`` (metres), output ``"log_distance"``.
    """

    def __init__(
        self,
        *,
        in_channels: int = 128,
        hidden_channels: int = 64,
        fc_dim: int = 256,
        correlation_radius: int = 0,
        predict_distance: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(predict_distance, bool):
            raise GeosegError(f"predict_distance: expected a bool, got {predict_distance!r}")
        for name, v, low in (
            ("in_channels", in_channels, 1),
            ("hidden_channels", hidden_channels, 1),
            ("fc_dim", fc_dim, 1),
            ("correlation_radius", correlation_radius, 0),
        ):
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise GeosegError(f"{name}: expected an int >= {low}, got {v!r}")
        self.in_channels = in_channels
        self.correlation_radius = correlation_radius
        self.predict_distance = predict_distance
        fused = 3 * hidden_channels + (2 * correlation_radius + 1) ** 2 * (correlation_radius > 0)
        self.branch = nn.Sequential(
            _conv_bn_relu(in_channels, in_channels, stride=2),
            _conv_bn_relu(in_channels, hidden_channels),
        )
        self.fuse = nn.Sequential(
            _conv_bn_relu(fused, 128),
            _conv_bn_relu(128, 128, stride=2),
        )
        self.regress = nn.Sequential(
            nn.Linear(256, fc_dim),
            nn.ReLU(inplace=True),
            nn.Linear(fc_dim, 6 + int(predict_distance)),
        )
        # start near the identity rotation (small rotation outputs) and, for the distance, near
        # a typical baseline of the training pairs
        with torch.no_grad():
            self.regress[-1].weight[:3].mul_(0.01)
            self.regress[-1].bias[:3].zero_()
            if predict_distance:
                self.regress[-1].weight[6:].mul_(0.01)
                self.regress[-1].bias[6:].fill_(_LOG_DISTANCE_INIT)

    def forward(self, feat_a: torch.Tensor, feat_b: torch.Tensor) -> dict[str, torch.Tensor]:
        """Predict the relative pose of the pair ``(a, b)``.

        Args:
            feat_a: ``(B, in_channels, h, w)`` layer-21 features of image a (the base image).
            feat_b: ``(B, in_channels, h, w)`` layer-21 features of image b (the query).

        Returns:
            ``{"rotation": (B, 3)`` rotation vector of ``R_ab`` (usual hat convention),
            ``"direction": (B, 3)`` unit direction a -> b in camera a's frame,
            ``"log_distance": (B,)}`` natural log of the baseline in metres (only with
            ``predict_distance``).
        """
        if not is_exporting():
            check_features("feat_a", feat_a, self.in_channels)
            check_features("feat_b", feat_b, self.in_channels)
            if feat_a.shape != feat_b.shape:
                raise GeosegError(
                    f"feat_b: expected the shape of feat_a {tuple(feat_a.shape)}, "
                    f"got {tuple(feat_b.shape)}"
                )
        a = self.branch(feat_a)
        b = self.branch(feat_b)
        parts = [a, b, a * b]
        if self.correlation_radius:
            parts.append(correlation_volume(a, b, self.correlation_radius))
        x = self.fuse(torch.cat(parts, dim=1))
        pooled = torch.cat([x.mean(dim=(2, 3)), x.amax(dim=(2, 3))], dim=1)
        out = self.regress(pooled)
        rotation = out[:, :3]
        direction = F.normalize(out[:, 3:6], p=2.0, dim=1, eps=1e-12)
        if self.predict_distance:
            return {"rotation": rotation, "direction": direction, "log_distance": out[:, 6]}
        return {"rotation": rotation, "direction": direction}


def relpose_head(
    *,
    in_channels: int = 128,
    hidden_channels: int = 64,
    fc_dim: int = 256,
    correlation_radius: int = 0,
    predict_distance: bool = False,
) -> RelPoseHead:
    """Build the relative-pose head (fig. 5.7). See :class:`RelPoseHead`."""
    return RelPoseHead(
        in_channels=in_channels,
        hidden_channels=hidden_channels,
        fc_dim=fc_dim,
        correlation_radius=correlation_radius,
        predict_distance=predict_distance,
    )


def log_distance_error(log_distance: torch.Tensor, distance_gt: torch.Tensor) -> torch.Tensor:
    """``(B,)`` error ``log_distance - log(distance_gt)`` of the head's baseline output.

    Args:
        log_distance: ``(B,)`` predicted ``log |t_ab|`` (metres).
        distance_gt: ``(B,)`` true baselines in metres, > 0.
    """
    check_shape("log_distance", log_distance, (None,))
    check_shape("distance_gt", distance_gt, (log_distance.shape[0],))
    if not bool((distance_gt > 0).all()):
        raise GeosegError("distance_gt: expected baselines > 0 m")
    return log_distance - torch.log(distance_gt.to(log_distance.dtype))


def relpose_loss(
    pred: dict[str, torch.Tensor],
    R_gt: torch.Tensor,
    t_dir_gt: torch.Tensor,
    *,
    lam: float = 1.0,
    distance_gt: torch.Tensor | None = None,
    mu: float = 1.0,
    direction_weight: torch.Tensor | None = None,
    reduction: str = "mean",
) -> torch.Tensor:
    """Eq. 5.2: ``lam (1 - T_est^T T_gt) + alpha^T alpha``, ``alpha = log(R_gt^T R_est)^vee``.

    With ``distance_gt``, plus ``mu (log_distance - log distance_gt)^2`` (the head's
    ``predict_distance`` output; an extension of eq. 5.2).

    Args:
        pred: ``{"rotation": (B, 3), "direction": (B, 3)}`` as returned by the head
            (``direction`` is re-normalised here).
        R_gt: ``(B, 3, 3)`` ground-truth ``R_ab``.
        t_dir_gt: ``(B, 3)`` ground-truth direction (normalised here).
        lam: weight ``lambda`` of the direction term (the thesis gives no value; 1 by
            default: ``1 - cos`` in ``[0, 2]`` against a squared angle in rad^2).
        distance_gt: ``(B,)`` true baselines ``|t_ab|`` in metres (> 0), or None: no distance
            term. Needs ``pred["log_distance"]`` ``(B,)``.
        mu: weight of the distance term, > 0.
        direction_weight: ``(B,)`` per-pair weight of the direction term (0 where the two
            views are at one place and the direction is undefined), or None: 1.
        reduction: ``"mean"``, ``"sum"`` or ``"none"`` (``(B,)``).

    Returns:
        Scalar loss, or ``(B,)`` with ``reduction="none"``.
    """
    if not isinstance(pred, dict) or "rotation" not in pred or "direction" not in pred:
        raise GeosegError("pred: expected a dict with 'rotation' and 'direction' tensors")
    rot, dirn = pred["rotation"], pred["direction"]
    check_shape("pred['rotation']", rot, (None, 3))
    bsz = rot.shape[0]
    check_shape("pred['direction']", dirn, (bsz, 3))
    check_shape("R_gt", R_gt, (bsz, 3, 3))
    check_shape("t_dir_gt", t_dir_gt, (bsz, 3))
    if reduction not in ("mean", "sum", "none"):
        raise GeosegError(f"reduction: expected 'mean', 'sum' or 'none', got {reduction!r}")
    R_gt = R_gt.to(rot.dtype)
    t_gt = F.normalize(t_dir_gt.to(rot.dtype), dim=1, eps=1e-12)
    t_est = F.normalize(dirn, dim=1, eps=1e-12)
    alpha = so3_log(R_gt.transpose(-1, -2) @ so3_exp(rot))
    direction = 1.0 - (t_est * t_gt).sum(-1)
    if direction_weight is not None:
        check_shape("direction_weight", direction_weight, (bsz,))
        direction = direction * direction_weight.to(direction.dtype)
    loss = lam * direction + (alpha * alpha).sum(-1)
    if distance_gt is not None:
        if "log_distance" not in pred:
            raise GeosegError(
                "pred: distance_gt given but no 'log_distance' output (a head built with "
                "predict_distance=True)"
            )
        if not mu > 0:
            raise GeosegError(f"mu: expected > 0, got {mu}")
        loss = loss + mu * log_distance_error(pred["log_distance"], distance_gt) ** 2
    if reduction == "mean":
        return loss.mean()
    if reduction == "sum":
        return loss.sum()
    return loss
