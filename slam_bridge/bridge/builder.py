"""One bridge from settings: the network, the association rule and the fusion's building rows.

:func:`build_bridge` is what ``geoseg slam run --buildings`` and the chapter-4 experiment use:
the association (``bayes``: the joint network + eq. 4.14; ``dirichlet``: the naive CNN + the
shipped Dirichlet filter; ``raycast``: the chapter-2 baseline, no network) over a building model
(``facades.csv``, and for ``raycast`` its mesh), wired into a
:class:`~slam_bridge.bridge.worker.BridgeWorker`. The network is tried once on a blank image
before the SLAM starts, so that a network without the ``building`` class, or one whose outputs
do not match the images, is refused up front rather than at the first keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoseg.classes import BUILDING, NUM_CLASSES
from geoseg.errors import check_positive
from slam_bridge.bridge import association as assoc
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.bridge.facades import Facades
from slam_bridge.bridge.worker import BridgeWorker, NetworkOutputs, segmenter_outputs
from slam_bridge.errors import SlamError

__all__ = ["ASSOCIATIONS", "BridgeConfig", "load_network", "check_network", "build_bridge"]

ASSOCIATIONS = ("bayes", "dirichlet", "raycast")
#: the shipped weights of each association's network (``geoseg.pretrained``)
SHIPPED_WEIGHTS = {"bayes": "normals", "dirichlet": "naive"}


@dataclass
class BridgeConfig:
    """The bridge's settings (``bridge:`` in ``configs/slam_images.yaml``).

    Attributes:
        association: ``bayes``, ``dirichlet`` or ``raycast`` (module docstring).
        radius_m: farthest facade a point may be associated with (eq. 4.14's ``r``).
        sigma_m: Geman-McClure scale of a building row (eq. 4.2).
        window_weight: the building rows of one fused window weigh together at most this much,
            in GPS fixes (None: no cap). A GIS model's facades are off by a metre or so, a GPS
            fix by less: the default is about ``sigma_gps^2 / sigma_model^2`` for a 0.75 m GPS
            and a model off by 1.2 m (``geoseg render``'s error model).
        network_size: ``(W, H)`` the images are resized to for the network (the size the
            shipped networks were trained at).
        network_threads: onnxruntime threads of the network: it runs beside the SLAM, and
            more threads than its share of the cores slow the SLAM's own loop.
        associate_every: keyframes between associations.
        infer_every: keyframes between inferences (1: all; more for a network too slow for
            every keyframe, :class:`~slam_bridge.bridge.worker.BridgeWorker`).
        asynchronous: inference and association in worker threads beside the SLAM (False:
            inline, deterministic, the same numbers as a worker that keeps up).
    """

    association: str = "bayes"
    radius_m: float = 3.0
    sigma_m: float = 0.5
    window_weight: float | None = 0.4
    network_size: tuple[int, int] = (320, 240)
    network_threads: int = 1
    associate_every: int = 5
    infer_every: int = 1
    asynchronous: bool = True

    def __post_init__(self) -> None:
        if self.association not in ASSOCIATIONS:
            raise SlamError(
                f"association: expected one of {list(ASSOCIATIONS)}, got {self.association!r}"
            )
        check_positive("radius_m", self.radius_m)
        check_positive("sigma_m", self.sigma_m)
        if self.network_threads < 1:
            raise SlamError(f"network_threads: expected >= 1, got {self.network_threads}")


def load_network(association: str, weights: str | Path | None = None, threads: int | None = 1):
    """The Segmenter of an association's network: ``weights`` (a ``.onnx`` or ``.pt`` file, or
    a folder holding ``model.onnx``), else the shipped one; ``threads``: onnxruntime's. None
    for ``raycast``."""
    from geoseg.infer import Segmenter
    from geoseg.pretrained import pretrained_file

    if association == "raycast":
        return None
    if weights is None:
        path = pretrained_file(SHIPPED_WEIGHTS[association], "model.onnx")
    else:
        path = Path(weights) / "model.onnx" if Path(weights).is_dir() else Path(weights)
    if path.suffix.lower() == ".onnx":
        return Segmenter.from_onnx(path, threads=threads)
    return Segmenter.from_file(path)


def check_network(network: NetworkOutputs, image_size: tuple[int, int], needs_normals: bool):
    """Run the network once on a grey image of ``image_size``.

    Raises:
        SlamError: it does not give ``NUM_CLASSES`` probabilities (the ``building`` class at
            :data:`geoseg.classes.BUILDING`), gives maps of another aspect ratio than the
            images, or gives no normals when the association needs them.
    """
    W, H = image_size
    probs, normals = network(np.full((H, W, 3), 128, np.uint8))
    if probs.ndim != 3 or probs.shape[2] != NUM_CLASSES:
        raise SlamError(
            f"network: gives {probs.shape[-1]} classes, the bridge needs geoseg's "
            f"{NUM_CLASSES} (building = class {BUILDING})"
        )
    h, w = probs.shape[:2]
    if abs(W * h / H - w) > 1.0:
        raise SlamError(f"network: {w}x{h} maps for {W}x{H} images (another aspect ratio)")
    if needs_normals and normals is None:
        raise SlamError("network: gives no normals; eq. 4.14 needs the joint network's")


def build_bridge(
    cfg: BridgeConfig,
    facades: Facades,
    *,
    image_size: tuple[int, int],
    mesh=None,
    segmenter=None,
    dirichlet_filter=None,
) -> BridgeWorker:
    """The worker of ``cfg.association`` over ``facades``.

    Args:
        cfg: the settings.
        facades: the building model.
        image_size: ``(W, H)`` of the SLAM's images (the network is checked on it).
        mesh: the model's mesh (``raycast``; :class:`trimesh.Trimesh`).
        segmenter: the network (default: :func:`load_network`'s shipped one).
        dirichlet_filter: the ``dirichlet`` rule's filter (default: the shipped one); its 5x5
            smoothing is applied to every network's maps before sampling.

    Raises:
        SlamError: a missing mesh for ``raycast``, a network the bridge cannot use
            (:func:`check_network`).
    """
    from geoseg.dirichlet import load_filter
    from geoseg.pretrained import pretrained_file

    method = cfg.association
    network = None
    if method != "raycast":
        segmenter = segmenter or load_network(method, threads=cfg.network_threads)
        network = segmenter_outputs(segmenter, tuple(cfg.network_size))
        check_network(network, image_size, needs_normals=method == "bayes")
    dirichlet_filter = dirichlet_filter or (
        load_filter(pretrained_file("dirichlet", "dirichlet.json")) if network else None
    )
    r = cfg.radius_m
    if method == "raycast":
        if mesh is None:
            raise SlamError("raycast: the building model's mesh is needed (buildings_model.ply)")
        rule = lambda s: assoc.associate_raycast(facades, mesh, s.points, s.centres, r)  # noqa: E731
    elif method == "dirichlet":
        f = dirichlet_filter
        rule = lambda s: assoc.associate_dirichlet(facades, s.points, s.mean_probs, f, r)  # noqa: E731
    else:
        rule = lambda s: assoc.associate_bayes(  # noqa: E731
            facades, s.points, s.labels, s.normals, BUILDING, r
        )
    constraints = BuildingConstraints(facades, sigma_m=cfg.sigma_m, window_weight=cfg.window_weight)
    return BridgeWorker(
        network,
        NUM_CLASSES,
        rule,
        constraints,
        smooth=dirichlet_filter.smooth if network is not None else None,
        associate_every=cfg.associate_every,
        infer_every=cfg.infer_every,
        asynchronous=cfg.asynchronous,
    )
