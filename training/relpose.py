"""Train the relative-pose head on frozen ENet layer-21 features (thesis §5.1.2, eq. 5.2).

Same data path as :mod:`training.reloc` (shared in :mod:`training.heads`): the trunk of
``trunk_checkpoint`` is frozen and its features are computed once per traversal (cached), then
the head (:func:`geoseg.models.relpose.relpose_head`) trains on feature pairs only, fresh pairs
every epoch (:func:`geoseg.data.pairs.sample_relpose_pairs`; with distances also far, unrelated,
turned and near pairs, each teaching the distance term its own case). Validation: eq. 5.2 and the
rotation, direction (and relative baseline) errors on fixed pairs. ``model.pt`` /
``model.onnx`` hold the head alone. The pair kinds and their losses: ``docs/networks.md``
("Training the relative-pose head").

Usage::

    geoseg train relpose --config configs/relpose.yaml --set trunk_checkpoint=runs/seg
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from geoseg.config import check_range
from geoseg.data.pairs import NoEligiblePairError, sample_relpose_pairs
from geoseg.data.traversals import RouteFeatures
from geoseg.errors import ConfigError, GeosegError
from geoseg.models.registry import get_model
from geoseg.models.relpose import log_distance_error, relpose_loss, so3_exp
from training import common
from training.heads import (
    HeadTrainConfig,
    feature_shape,
    finish_head_run,
    fit_head,
    prepare_head_features,
    split_count,
)
from training.metrics import Meter

logger = logging.getLogger(__name__)

#: smallest baseline of a turned pair (sample_relpose_pairs needs a positive one)
_TURNED_MIN_BASELINE_M = 0.01

__all__ = [
    "CONFIG_CLASS",
    "PairRegressor",
    "PairSet",
    "RelPoseConfig",
    "RelPoseLoss",
    "RelPoseMeter",
    "main",
]


@dataclass
class RelPoseConfig(HeadTrainConfig):
    """Relative-pose head training run (fields beyond :class:`~training.heads.HeadTrainConfig`:
    ``trunk_checkpoint``, ``routes``, ``feature_batch_size``, ``export``).

    Attributes:
        pairs_per_epoch: fresh pairs drawn each epoch.
        val_pairs: fixed validation pairs.
        min_baseline_m, max_baseline_m: baseline range of a pair, metres.
        max_angle_deg: largest angle between the two optical axes.
        lam: weight of the direction term of eq. 5.2.
        mu: weight of the log-baseline term (heads with ``predict_distance`` only).
        far_pairs_per_epoch: extra pairs per epoch with baselines in
            ``(max_baseline_m, far_max_baseline_m]`` for the distance term alone (heads with
            ``predict_distance`` only; 0: none).
        far_max_baseline_m: largest baseline of the far pairs, metres.
        unrelated_pairs_per_epoch: extra pairs per epoch of views at least ``unrelated_min_m``
            apart, any orientation, that train a floor on the predicted distance (heads with
            ``predict_distance`` only; 0: none).
        unrelated_min_m: smallest distance between the views of an unrelated pair, metres.
        unrelated_floor_m: distance the head must predict at least for unrelated pairs, metres.
        turned_pairs_per_epoch: extra pairs per epoch of views at most ``turned_max_m`` apart
            whose optical axes are at least ``turned_min_angle_deg`` apart (the crossing street,
            the opposite direction, the far side of a turn), that train the same floor,
            ``turned_floor_m``: re-ranking by predicted distance must not prefer a nearby camera
            that looks elsewhere (heads with ``predict_distance`` only; 0: none).
        turned_max_m: largest distance between the views of a turned pair, metres.
        turned_min_angle_deg: smallest angle between the optical axes of a turned pair.
        turned_floor_m: distance the head must predict at least for turned pairs, metres.
        near_pairs_per_epoch: extra pairs per epoch of views at most ``near_max_baseline_m``
            apart (axes within ``max_angle_deg``), from the traversals that share poses
            (``routes.aligned_conditions``; 0: none).
        val_near_pairs: such pairs added to the validation pairs (0: none).
        near_max_baseline_m: largest baseline of a near pair, metres.
        distance_floor_m: the distance target is ``log max(d, distance_floor_m)``.
        direction_min_m: pairs nearer than this have no direction term (undefined at 0 m).
    """

    trainer: ClassVar[str] = "relpose"
    count_keys: ClassVar[tuple[str, ...]] = ("pairs_per_epoch", "val_pairs")

    model: str = "relpose"
    out_dir: Path = Path("runs/relpose")
    best_metric: str = "val_loss"
    best_mode: Literal["min", "max"] = "min"
    pairs_per_epoch: int = 4000
    val_pairs: int = 500
    min_baseline_m: float = 0.5
    max_baseline_m: float = 10.0
    max_angle_deg: float = 30.0
    lam: float = 1.0
    mu: float = 1.0
    far_pairs_per_epoch: int = 0
    far_max_baseline_m: float = 30.0
    unrelated_pairs_per_epoch: int = 0
    unrelated_min_m: float = 60.0
    unrelated_floor_m: float = 40.0
    turned_pairs_per_epoch: int = 0
    turned_max_m: float = 25.0
    turned_min_angle_deg: float = 45.0
    turned_floor_m: float = 30.0
    near_pairs_per_epoch: int = 0
    val_near_pairs: int = 0
    near_max_baseline_m: float = 0.5
    distance_floor_m: float = 0.1
    direction_min_m: float = 0.05

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0 < self.min_baseline_m <= self.max_baseline_m:
            raise ConfigError("min_baseline_m, max_baseline_m: expected 0 < min <= max")
        check_range("max_angle_deg", self.max_angle_deg, 0.0, 180.0, low_open=True)
        for name in ("far_max_baseline_m", "unrelated_min_m", "unrelated_floor_m", "turned_max_m"):
            check_range(name, getattr(self, name), 0.0, None, low_open=True)
        check_range("turned_floor_m", self.turned_floor_m, 0.0, None, low_open=True)
        for name in ("near_max_baseline_m", "distance_floor_m"):
            check_range(name, getattr(self, name), 0.0, None, low_open=True)
        check_range("direction_min_m", self.direction_min_m, 0.0)
        for name in ("near_pairs_per_epoch", "val_near_pairs"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if (
            self.near_pairs_per_epoch or self.val_near_pairs
        ) and not self.routes.aligned_conditions:
            raise ConfigError(
                "near_pairs_per_epoch, val_near_pairs: near pairs come from traversals at one "
                "route's poses; set routes.aligned_conditions >= 1"
            )
        check_range("turned_min_angle_deg", self.turned_min_angle_deg, 0.0, 180.0)
        for name in ("lam", "mu"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: expected > 0, got {getattr(self, name)}")
        for name in ("far_pairs_per_epoch", "unrelated_pairs_per_epoch", "turned_pairs_per_epoch"):
            count = getattr(self, name)
            if count < 0:
                raise ConfigError(f"{name}: expected >= 0, got {count}")
            if count and not dict(self.model_config or {}).get("predict_distance", False):
                raise ConfigError(
                    f"{name}: these pairs train the distance output only; set "
                    f"model_config.predict_distance: true (or {name}: 0)"
                )
        if self.unrelated_pairs_per_epoch and not (
            0 < self.unrelated_floor_m <= self.unrelated_min_m
        ):
            raise ConfigError(
                "unrelated_floor_m, unrelated_min_m: expected 0 < floor <= min, got "
                f"{self.unrelated_floor_m}, {self.unrelated_min_m}"
            )
        if self.turned_pairs_per_epoch and not (
            self.turned_max_m > 0
            and self.turned_floor_m > 0
            and self.max_angle_deg < self.turned_min_angle_deg <= 180.0
        ):
            raise ConfigError(
                "turned_max_m, turned_floor_m, turned_min_angle_deg: expected positive distances "
                f"and an angle in (max_angle_deg ({self.max_angle_deg}), 180], got "
                f"{self.turned_max_m}, {self.turned_floor_m}, {self.turned_min_angle_deg}"
            )
        if self.far_pairs_per_epoch:
            if not self.far_max_baseline_m > self.max_baseline_m:
                raise ConfigError(
                    f"far_max_baseline_m: expected > max_baseline_m ({self.max_baseline_m}), "
                    f"got {self.far_max_baseline_m}"
                )


CONFIG_CLASS = RelPoseConfig


class PairRegressor(nn.Module):
    """The relative-pose head on stacked pairs.

    Forward:
        x: ``(B, 2, C, h, w)`` features of (a, b).
        Returns the head's ``{"rotation": (B, 3), "direction": (B, 3)}``.
    """

    def __init__(self, head: nn.Module) -> None:
        super().__init__()
        self.head = head

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        if x.ndim != 5 or x.shape[1] != 2:
            raise GeosegError(f"x: expected (B, 2, C, h, w) stacked pairs, got {tuple(x.shape)}")
        return self.head(x[:, 0], x[:, 1])


class RelPoseLoss:
    """Eq. 5.2 (:func:`relpose_loss`) against ``batch["R_ab"]``, ``batch["t_dir_ab"]``, plus
    ``mu`` times the squared log-baseline error against ``max(batch["baseline_m"],
    distance_floor_m)`` when the head predicts distances; the direction term is dropped for
    pairs with ``baseline_m`` below ``direction_min_m`` (views of one place: no direction);
    ``batch["pose_weight"]`` (when present) weighs the eq. 5.2 terms per pair (0 for the far,
    distance-only pairs), and where ``batch["distance_floor"]`` is true ``baseline_m`` is a
    floor: only predictions nearer than it are penalised."""

    def __init__(
        self,
        lam: float = 1.0,
        mu: float = 1.0,
        *,
        distance_floor_m: float = 0.1,
        direction_min_m: float = 0.05,
    ) -> None:
        self.lam = float(lam)
        self.mu = float(mu)
        self.distance_floor_m = float(distance_floor_m)
        self.direction_min_m = float(direction_min_m)

    def __call__(self, outputs: dict[str, torch.Tensor], batch: dict[str, Any]) -> torch.Tensor:
        baseline = batch.get("baseline_m")
        direction_weight = None if baseline is None else baseline >= self.direction_min_m
        loss = relpose_loss(
            outputs,
            batch["R_ab"],
            batch["t_dir_ab"],
            lam=self.lam,
            direction_weight=direction_weight,
            reduction="none",
        )
        if "pose_weight" in batch:
            loss = loss * batch["pose_weight"].to(loss.dtype)
        if "log_distance" in outputs:
            err = log_distance_error(
                outputs["log_distance"], baseline.clamp(min=self.distance_floor_m)
            )
            if "distance_floor" in batch:
                err = torch.where(batch["distance_floor"], err.clamp(max=0.0), err)
            loss = loss + self.mu * err * err
        return loss.mean()


def pose_errors_deg(
    outputs: dict[str, torch.Tensor], R_gt: torch.Tensor, t_gt: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B,)`` rotation and direction errors in degrees of the head's outputs.

    Args:
        outputs: ``{"rotation": (B, 3), "direction": (B, 3)}``.
        R_gt: ``(B, 3, 3)`` true ``R_ab``.
        t_gt: ``(B, 3)`` true unit directions.
    """
    R = so3_exp(outputs["rotation"].detach().double().cpu())
    Rg = R_gt.detach().double().cpu()
    cos_r = ((Rg.transpose(-1, -2) @ R).diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    rot = torch.rad2deg(torch.arccos(cos_r.clamp(-1.0, 1.0)))
    d = torch.nn.functional.normalize(outputs["direction"].detach().double().cpu(), dim=1)
    g = torch.nn.functional.normalize(t_gt.detach().double().cpu(), dim=1)
    dirn = torch.rad2deg(torch.arccos((d * g).sum(1).clamp(-1.0, 1.0)))
    return rot, dirn


class RelPoseMeter(Meter):
    """Rotation and direction errors (degrees): means, medians (0.05-degree histograms) and the
    shares within the issue's targets (2 and 10 degrees); with distance outputs, the relative
    baseline error ``|d_est / d_gt - 1|`` (median from 0.1 % bins over [0, 3.6], mean, share
    within 20 %).

    Pairs nearer than ``near_max_baseline_m`` (views of one place) count for the rotation only,
    plus ``near_dist``: the predicted distance in metres (1 mm bins over [0, 3.6], share read
    within 0.5 m); pairs with a zero direction target have no direction error."""

    bins = 3600  # 0.05 degree over [0, 180]; 0.001 of relative distance error over [0, 3.6]
    # name -> (histogram range, unit suffix, "within" limit)
    errors = {
        "rot": (180.0, "deg", 2.0),
        "dir": (180.0, "deg", 10.0),
        "dist": (3.6, "rel", 0.2),
        "near_dist": (3.6, "m", 0.5),
    }

    def __init__(self, near_max_baseline_m: float = 0.5) -> None:
        self.near_max_baseline_m = float(near_max_baseline_m)
        super().__init__()

    def reset(self) -> None:
        self.state = {}
        for name in self.errors:
            self.state[f"{name}_hist"] = torch.zeros(self.bins, dtype=torch.float64)
            self.state[f"{name}_sum"] = torch.zeros((), dtype=torch.float64)

    def update(self, outputs: Any, batch: Any) -> None:
        rot, dirn = pose_errors_deg(outputs, batch["R_ab"], batch["t_dir_ab"])
        has_dir = torch.linalg.vector_norm(batch["t_dir_ab"].detach().cpu(), dim=1) > 0.5
        errs = {"rot": rot, "dir": dirn[has_dir]}
        if "log_distance" in outputs:
            d = outputs["log_distance"].detach().double().cpu().exp()
            gt = batch["baseline_m"].double().cpu()
            near = gt < self.near_max_baseline_m
            errs["dist"] = (d[~near] / gt[~near] - 1.0).abs()
            errs["near_dist"] = d[near]
        for name, err in errs.items():
            top = self.errors[name][0]
            idx = (err / top * self.bins).long().clamp(0, self.bins - 1)
            self.state[f"{name}_hist"] += torch.bincount(idx, minlength=self.bins).double()
            self.state[f"{name}_sum"] += err.sum()

    def compute(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for name, (top, unit, limit) in self.errors.items():
            hist = self.state[f"{name}_hist"]
            n = float(hist.sum())
            if n == 0:
                if name in ("rot", "dir"):  # no distance output or near pair: no such figures
                    out.update(
                        {f"{name}_median_{unit}": float("nan"), f"{name}_mean_{unit}": float("nan")}
                    )
                continue
            width = top / self.bins
            cdf = torch.cumsum(hist, 0)
            k = int(torch.searchsorted(cdf, torch.tensor(n / 2.0, dtype=torch.float64)))
            out[f"{name}_median_{unit}"] = (k + 0.5) * width
            out[f"{name}_mean_{unit}"] = float(self.state[f"{name}_sum"]) / n
            within = f"{limit:g}deg" if unit == "deg" else f"{limit:g}"
            out[f"{name}_within_{within}"] = float(hist[: round(limit / width)].sum()) / n
        return out


class PairSet(Dataset):
    """Relative-pose pairs over the traversals of several routes, redrawn by :meth:`resample`.

    Args:
        routes: the routes with their features.
        n: pairs per draw (spread evenly over routes and ordered traversal pairs, same-condition
            pairs included).
        seed: seeds every draw (``(seed, epoch)``).
        n_far: extra distance-only pairs per draw, baselines in
            ``(max_baseline_m, far_max_baseline_m]`` (``pose_weight`` 0).
        far_max_baseline_m: largest baseline of the far pairs (needed when ``n_far > 0``).
        n_unrelated: extra pairs per draw of views at least ``unrelated_min_m`` apart (any
            orientation), whose ``baseline_m`` is ``unrelated_floor_m``, a floor
            (``distance_floor`` true, ``pose_weight`` 0).
        unrelated_min_m, unrelated_floor_m: see :class:`RelPoseConfig`.
        n_turned: extra pairs per draw of views at most ``turned_max_m`` apart whose optical
            axes are at least ``turned_min_angle_deg`` apart, whose ``baseline_m`` is the floor
            ``turned_floor_m`` (``distance_floor`` true, ``pose_weight`` 0); spread over the
            route/traversal pairs that have such views.
        turned_max_m, turned_min_angle_deg, turned_floor_m: see :class:`RelPoseConfig`.
        n_near: extra pairs per draw of views at most ``near_max_baseline_m`` apart (axes
            within the pairs' ``max_angle_deg``; ``pose_weight`` 1) from two different
            traversals, spread over the route/traversal pairs that have such views (traversals
            sharing poses).
        near_max_baseline_m: see :class:`RelPoseConfig`.
        pair_kwargs: :func:`sample_relpose_pairs` thresholds.

    Items: ``{"image": (2, C, h, w) float32, "R_ab": (3, 3) float32, "t_dir_ab": (3,) float32,
    "baseline_m": () float32, "pose_weight": () float32 (1, or 0 for far, unrelated and turned
    pairs),
    "distance_floor": () bool, "same_condition": () bool, "index": (5,) int64 (route, trav a,
    trav b, a, b)}``; the parts follow one another in that order: pose, far, unrelated, turned,
    near pairs.
    """

    def __init__(
        self,
        routes: Sequence[RouteFeatures],
        n: int,
        *,
        seed: int = 0,
        n_far: int = 0,
        far_max_baseline_m: float | None = None,
        n_unrelated: int = 0,
        unrelated_min_m: float = 60.0,
        unrelated_floor_m: float = 40.0,
        n_turned: int = 0,
        turned_max_m: float = 25.0,
        turned_min_angle_deg: float = 45.0,
        turned_floor_m: float = 30.0,
        n_near: int = 0,
        near_max_baseline_m: float = 0.5,
        **pair_kwargs: Any,
    ) -> None:
        if not routes:
            raise GeosegError("routes: no route to draw pairs from")
        if n_far and far_max_baseline_m is None:
            raise GeosegError("far_max_baseline_m: required with far pairs (n_far > 0)")
        feature_shape(routes)
        self.routes = list(routes)
        self.n = int(n)
        self.n_far = int(n_far)
        self.far_max_baseline_m = far_max_baseline_m
        self.n_unrelated = int(n_unrelated)
        self.unrelated_min_m = float(unrelated_min_m)
        self.unrelated_floor_m = float(unrelated_floor_m)
        self.n_turned = int(n_turned)
        self.turned_max_m = float(turned_max_m)
        self.turned_min_angle_deg = float(turned_min_angle_deg)
        self.turned_floor_m = float(turned_floor_m)
        self.n_near = int(n_near)
        self.near_max_baseline_m = float(near_max_baseline_m)
        self._eligible: dict[tuple, list[tuple[int, int, int]]] = {}
        self.seed = int(seed)
        self.pair_kwargs = pair_kwargs
        self.resample(0)

    @staticmethod
    def _own(route: Any, near: bool) -> int:
        """How many of ``route``'s traversals to draw from: all for near pairs, else only
        its own (not its aligned traversals, whose 8 m keyframe grid would skew the
        baselines)."""
        aligned = getattr(route, "aligned", None)
        if near or aligned is None:
            return len(route.traversals)
        return len(route.spec.conditions)

    def _jobs(
        self, optional: bool, thresholds: dict[str, Any], cross: bool = False
    ) -> list[tuple[int, int, int]]:
        """The (route, traversal a, traversal b) triples to draw from; ``optional``: only those
        with an eligible pair (a route without a turn has no turned pair), computed once;
        ``cross``: two different traversals only (a keyframe paired with itself is one image)."""
        jobs = [
            (r, i, j)
            for r, route in enumerate(self.routes)
            for i in range(self._own(route, cross))
            for j in range(self._own(route, cross))
            if not (cross and i == j)
        ]
        if not optional:
            return jobs
        key = (cross, *sorted(thresholds.items()))
        if key not in self._eligible:
            eligible = []
            for r, i, j in jobs:
                travs = self.routes[r].traversals
                try:
                    sample_relpose_pairs(travs[i].poses, travs[j].poses, 1, **thresholds)
                except NoEligiblePairError:
                    continue
                eligible.append((r, i, j))
            if not eligible:
                raise GeosegError(f"routes: no pair of views with {thresholds}")
            self._eligible[key] = eligible
        return self._eligible[key]

    def _draw(
        self,
        n: int,
        rng: np.random.Generator,
        *,
        optional: bool = False,
        cross: bool = False,
        **thresholds: Any,
    ) -> tuple:
        """``n`` pairs spread over routes and ordered traversal pairs: ``(index (n, 5), R_ab,
        t_dir_ab, baseline_m)`` as NumPy arrays (``optional``: over those that have one;
        ``cross``: over pairs of two traversals)."""
        jobs = self._jobs(optional, thresholds, cross)
        index, R, t, baseline = [], [], [], []
        for (r, i, j), count in zip(jobs, split_count(n, len(jobs))):
            if count == 0:
                continue
            travs = self.routes[r].traversals
            pairs = sample_relpose_pairs(
                travs[i].poses, travs[j].poses, count, rng=rng, **thresholds
            )
            block = np.stack([np.full(count, r), np.full(count, i), np.full(count, j)], 1)
            index.append(np.concatenate([block, np.stack([pairs.idx_a, pairs.idx_b], 1)], 1))
            R.append(pairs.R_ab)
            t.append(pairs.t_dir_ab)
            baseline.append(pairs.baseline_m)
        return tuple(np.concatenate(x) for x in (index, R, t, baseline))

    def resample(self, epoch: int) -> None:
        """Draw this epoch's pairs (the pose pairs first: far and unrelated pairs leave them
        unchanged)."""
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, int(epoch), 5202]))
        parts = [self._draw(self.n, rng, **self.pair_kwargs)]
        weight, floor = [np.ones(self.n)], [np.zeros(self.n, dtype=bool)]
        if self.n_far:
            far = dict(self.pair_kwargs)
            far["min_baseline_m"] = far.get("max_baseline_m", 10.0) + 1e-6
            far["max_baseline_m"] = self.far_max_baseline_m
            parts.append(self._draw(self.n_far, rng, **far))
            weight.append(np.zeros(self.n_far))
            floor.append(np.zeros(self.n_far, dtype=bool))
        n_floor = self.n_unrelated + self.n_turned
        weight.append(np.zeros(n_floor))
        floor.append(np.ones(n_floor, dtype=bool))
        if self.n_unrelated:
            index, R, t, _ = self._draw(
                self.n_unrelated,
                rng,
                min_baseline_m=self.unrelated_min_m,
                max_baseline_m=1e9,
                max_angle_deg=180.0,
            )
            parts.append((index, R, t, np.full(len(index), self.unrelated_floor_m)))
        if self.n_turned:
            index, R, t, _ = self._draw(
                self.n_turned,
                rng,
                optional=True,
                min_baseline_m=_TURNED_MIN_BASELINE_M,
                max_baseline_m=self.turned_max_m,
                min_angle_deg=self.turned_min_angle_deg,
                max_angle_deg=180.0,
            )
            parts.append((index, R, t, np.full(len(index), self.turned_floor_m)))
        if self.n_near:
            near = {**self.pair_kwargs, "min_baseline_m": 0.0}
            near["max_baseline_m"] = self.near_max_baseline_m
            parts.append(self._draw(self.n_near, rng, optional=True, cross=True, **near))
            weight.append(np.ones(self.n_near))
            floor.append(np.zeros(self.n_near, dtype=bool))
        index, R, t, baseline = (np.concatenate(x) for x in zip(*parts))
        self.index = index.astype(np.int64)
        self.R_ab = torch.from_numpy(R).float()
        self.t_dir_ab = torch.from_numpy(t).float()
        self.baseline_m = torch.from_numpy(baseline).float()
        self.pose_weight = torch.from_numpy(np.concatenate(weight)).float()
        self.distance_floor = torch.from_numpy(np.concatenate(floor))

    def __len__(self) -> int:
        return self.n + self.n_far + self.n_unrelated + self.n_turned + self.n_near

    def __getitem__(self, k: int) -> dict[str, torch.Tensor]:
        r, i, j, a, b = (int(v) for v in self.index[k])
        feats = self.routes[r].features
        return {
            "image": torch.stack([feats[i][a], feats[j][b]]).float(),
            "R_ab": self.R_ab[k],
            "t_dir_ab": self.t_dir_ab[k],
            "baseline_m": self.baseline_m[k],
            "pose_weight": self.pose_weight[k],
            "distance_floor": self.distance_floor[k],
            "same_condition": torch.tensor(i == j),
            "index": torch.from_numpy(self.index[k].copy()),
        }


def main(cfg: RelPoseConfig, *, command: str | None = None) -> Path:
    """Train the relative-pose head as ``cfg`` says; returns the run directory.

    Raises:
        GeosegError: no ``trunk_checkpoint`` or one of another architecture, routes without
            eligible pairs, an existing run without ``resume``/``overwrite``.
    """
    data = prepare_head_features(cfg)
    common.seed_model_init(cfg.seed)
    head = get_model("relpose", **cfg.model_config)
    if cfg.init_checkpoint is not None:
        common.load_init_weights(head, cfg.init_checkpoint, model_name="relpose")
    model = PairRegressor(head)
    thresholds = {
        "min_baseline_m": cfg.min_baseline_m,
        "max_baseline_m": cfg.max_baseline_m,
        "max_angle_deg": cfg.max_angle_deg,
    }
    train_set = PairSet(
        data.train,
        cfg.pairs_per_epoch,
        seed=cfg.seed,
        n_far=cfg.far_pairs_per_epoch,
        far_max_baseline_m=cfg.far_max_baseline_m,
        n_unrelated=cfg.unrelated_pairs_per_epoch,
        unrelated_min_m=cfg.unrelated_min_m,
        unrelated_floor_m=cfg.unrelated_floor_m,
        n_turned=cfg.turned_pairs_per_epoch,
        turned_max_m=cfg.turned_max_m,
        turned_min_angle_deg=cfg.turned_min_angle_deg,
        turned_floor_m=cfg.turned_floor_m,
        n_near=cfg.near_pairs_per_epoch,
        near_max_baseline_m=cfg.near_max_baseline_m,
        **thresholds,
    )
    val_set = PairSet(
        data.val,
        cfg.val_pairs,
        seed=cfg.seed + 10_000,
        n_near=cfg.val_near_pairs,
        near_max_baseline_m=cfg.near_max_baseline_m,
        **thresholds,
    )
    loss = RelPoseLoss(
        cfg.lam, cfg.mu, distance_floor_m=cfg.distance_floor_m, direction_min_m=cfg.direction_min_m
    )
    run_dir = fit_head(
        cfg,
        model,
        train_set,
        val_set,
        loss,
        RelPoseMeter(near_max_baseline_m=cfg.near_max_baseline_m),
        model_name="relpose_pair",
    )
    return finish_head_run(
        run_dir,
        model,
        cfg,
        data,
        kind="relpose",
        input_names=("feat_a", "feat_b"),
        command=command,
        extra_card={
            "conventions": "R_ab = R_wc_a^T R_wc_b; direction a -> b in camera a's frame"
            + ("; log_distance = ln |t_ab| in metres" if head.predict_distance else "")
        },
    )
