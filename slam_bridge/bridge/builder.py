"""One bridge from settings: the network, the association rule and the fusion's building rows.

:func:`build_bridge` is what ``geoseg slam run --buildings`` and the chapter-4 experiment use:
the association (``bayes``: the joint network + eq. 4.14; ``dirichlet``: the naive CNN + its
Dirichlet filter, :func:`load_dirichlet_filter`; ``raycast``: the chapter-2 baseline, no
network) over a building model (``facades.csv``, and for ``raycast`` its mesh), wired into a
:class:`~slam_bridge.bridge.worker.BridgeWorker`. The network is tried once on a blank image
before the SLAM starts, so that a network without the ``building`` class, or one whose outputs
do not match the images, is refused up front rather than at the first keyframe.

With ``colour_transfer`` (``slam run --colour-transfer REF``) the network sees each keyframe
with the colour statistics of a reference (thesis §4.3.2, Reinhard et al. 2001:
:mod:`geoseg.colour_transfer`): ``card``, the training set's, recorded in the network's model
card, or those of a reference image or folder of images (:func:`colour_transfer_of`). Each
keyframe is mapped from its own statistics, as ``geoseg infer --colour-transfer image`` maps
each image: a stateless map gives the same input wherever the network runs (inline, a thread,
the child process) and whichever keyframes a busy worker drops, and it follows the light as it
changes along a drive; statistics pooled over the keyframes seen so far would be steadier
against a frame that one facade fills, but depend on which keyframes came first.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from geoseg.classes import BUILDING, NUM_CLASSES
from geoseg.errors import check_positive
from slam_bridge.bridge import association as assoc
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.bridge.facades import Facades
from slam_bridge.bridge.worker import BridgeWorker, NetworkOutputs, segmenter_outputs
from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = [
    "ASSOCIATIONS",
    "BridgeConfig",
    "check_covers_window",
    "colour_transfer_of",
    "load_dirichlet_filter",
    "load_network",
    "resolve_weights",
    "network_file",
    "network_outputs",
    "check_network",
    "build_bridge",
]

ASSOCIATIONS = ("bayes", "dirichlet", "raycast")
WORKERS = ("process", "thread")
#: the shipped weights of each association's network (``geoseg.pretrained``)
SHIPPED_WEIGHTS = {"bayes": "normals", "dirichlet": "naive"}
#: ``network: real`` (photographs): the association's network for real photographs
#: (``street`` when installed, else ``normals_real``: :func:`geoseg.pretrained.real_photo_network`)
REAL_PHOTO = "real"
#: ``colour_transfer: card``: the training set's colour statistics, from the network's model card
CARD_REFERENCE = "card"
#: the shipped Dirichlet filter calibrated on each shipped naive CNN
SHIPPED_FILTERS = {"naive": "dirichlet", "naive_real": "dirichlet_real"}


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
        asynchronous: inference and association beside the SLAM (False: inline,
            deterministic, the same numbers as a worker that keeps up).
        worker: where the asynchronous inference runs: ``process`` (a child process with its
            own copy of the network: nothing of it competes with the loop for the GIL) or
            ``thread``. A network given as an object (not as weights) runs in a thread.
        recent_keyframes: the online associations cover the points seen in this many latest
            keyframes (None: all points, a snapshot that grows with the map); at least the
            k-BA window's ``l + history_keyframes`` (checked by the SLAM's config).
        lag_keyframes: the worker's results for keyframe ``k`` are applied at keyframe
            ``k + lag_keyframes`` exactly, waited for when late (a repeatable run: its result
            does not depend on the machine's speed); None: as soon as they are ready, never
            waited for (the fastest run, but two runs may differ).
        network: the association's network when the caller names none (``slam run``'s
            ``--network``): a ``.onnx``/``.pt`` file, a folder or a shipped name; ``real``: the
            network for real photographs (bayes: ``street`` when installed, else
            ``normals_real``; dirichlet: ``naive_real``), as ``configs/slam_images.yaml`` sets;
            None: :data:`SHIPPED_WEIGHTS` (the synthetic city's, as the chapter-4 experiment
            on rendered drives uses).
        colour_transfer: map each keyframe onto a reference's colour statistics before the
            network (module docstring): ``card`` (the network's training set, from its model
            card), an image, a folder of images (directly or in ``rgb/``) or a JSON file of
            statistics (:func:`geoseg.colour_transfer.reference_statistics`); None: the
            keyframes as they are. Unused by ``raycast`` (no network).
        colour_means_only: with ``colour_transfer``, shift the colour means only (keep the
            keyframe's contrast and saturation) instead of matching means and standard
            deviations (``geoseg infer --colour-means-only``).
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
    worker: str = "process"
    recent_keyframes: int | None = 150
    lag_keyframes: int | None = None
    network: str | None = None
    colour_transfer: str | None = None
    colour_means_only: bool = False

    def __post_init__(self) -> None:
        if self.colour_transfer is not None:
            if not isinstance(self.colour_transfer, (str, Path)) or not str(self.colour_transfer):
                raise SlamError(
                    "colour_transfer: expected 'card', an image, a folder of images or a JSON "
                    f"file, got {self.colour_transfer!r}"
                )
            self.colour_transfer = str(self.colour_transfer)
        if self.lag_keyframes is not None and self.lag_keyframes < 1:
            raise SlamError(f"lag_keyframes: expected >= 1 or None, got {self.lag_keyframes}")
        if self.association not in ASSOCIATIONS:
            raise SlamError(
                f"association: expected one of {list(ASSOCIATIONS)}, got {self.association!r}"
            )
        if self.worker not in WORKERS:
            raise SlamError(f"worker: expected one of {list(WORKERS)}, got {self.worker!r}")
        check_positive("radius_m", self.radius_m)
        check_positive("sigma_m", self.sigma_m)
        if self.network_threads < 1:
            raise SlamError(f"network_threads: expected >= 1, got {self.network_threads}")
        if self.recent_keyframes is not None and self.recent_keyframes < 1:
            raise SlamError(f"recent_keyframes: expected >= 1 or None, got {self.recent_keyframes}")


def check_covers_window(cfg: BridgeConfig, window) -> None:
    """Raise a :class:`SlamError` when the online associations' ``recent_keyframes`` do not
    cover the points of a fusion window (``window``: a
    :class:`slam_bridge.slam.windows.WindowConfig`)."""
    span = window.l + window.history_keyframes
    if cfg.recent_keyframes is not None and cfg.recent_keyframes < span:
        raise SlamError(
            f"bridge.recent_keyframes: {cfg.recent_keyframes} keyframes do not cover the k-BA "
            f"window's l + history_keyframes = {span}"
        )


def resolve_weights(association: str, weights: str | Path | None) -> str | Path | None:
    """``weights``, with ``real`` (:data:`REAL_PHOTO`) replaced by the association's network for
    real photographs (:func:`geoseg.pretrained.real_photo_network` for ``bayes``,
    ``naive_real`` for ``dirichlet``)."""
    if weights is None or str(weights) != REAL_PHOTO:
        return weights
    from geoseg.pretrained import real_photo_network

    return real_photo_network() if association == "bayes" else "naive_real"


def load_network(association: str, weights: str | Path | None = None, threads: int | None = 1):
    """The Segmenter of an association's network: ``weights`` (a ``.onnx`` or ``.pt`` file, a
    folder holding ``model.onnx``, or the name of shipped weights, e.g. ``normals_real`` for
    real photographs, or ``real``: :func:`resolve_weights`), else the association's shipped one;
    ``threads``: onnxruntime's. None for ``raycast``."""
    from geoseg.infer import Segmenter

    if association == "raycast":
        return None
    path = network_file(association, weights)
    if path.suffix.lower() == ".onnx":
        return Segmenter.from_onnx(path, threads=threads)
    return Segmenter.from_file(path)


def network_file(association: str, weights: str | Path | None = None) -> Path:
    """The weights file :func:`load_network` loads for ``association`` (``bayes`` or
    ``dirichlet``): ``weights`` resolved (a folder: its ``model.onnx``), else the shipped one."""
    from geoseg.pretrained import path_or_shipped, pretrained_file

    weights = resolve_weights(association, weights)
    if weights is None:
        return pretrained_file(SHIPPED_WEIGHTS[association], "model.onnx")
    path = path_or_shipped(weights)
    return path / "model.onnx" if path.is_dir() else path


def colour_transfer_of(cfg: BridgeConfig, weights: str | Path | None = None, segmenter=None):
    """The map of ``cfg.colour_transfer`` (module docstring), or None when off or for
    ``raycast``.

    Args:
        cfg: the settings (``colour_transfer``, ``colour_means_only``, ``association``).
        weights: the network's weights, as :func:`load_network` takes them (``card`` reads the
            model card beside them).
        segmenter: or the network as an object: ``card`` reads the card beside its ``source``.

    Returns:
        A :class:`geoseg.colour_transfer.ColourTransfer` mapping each image from its own
        statistics (picklable: it travels to the worker's child process).

    Raises:
        SlamError: a reference that is not there or not readable, or ``card`` for weights
            without a model card (or a network object that names no weights file).
    """
    from geoseg.colour_transfer import ColourTransfer, reference_statistics
    from geoseg.errors import GeosegError
    from geoseg.infer import training_colour_statistics

    ref = cfg.colour_transfer
    if ref is None or cfg.association == "raycast":
        return None
    model_path = None  # card: the weights' own errors are theirs, raised here unwrapped
    if ref == CARD_REFERENCE:
        model_path = network_file(cfg.association, weights) if segmenter is None else None
    try:
        if ref != CARD_REFERENCE:
            target = reference_statistics(ref)
        elif model_path is not None:
            target = training_colour_statistics(model_path)
        elif getattr(segmenter, "source", None) is not None:
            target = training_colour_statistics(segmenter.source)
        else:
            raise GeosegError(
                "card: the network object names no weights file whose model card to read; "
                "give a reference image or folder instead"
            )
    except GeosegError as exc:
        raise SlamError(f"bridge.colour_transfer {ref!r}: {exc}") from None
    return ColourTransfer(target, match_std=not cfg.colour_means_only)


def load_dirichlet_filter(filter_spec=None, weights: str | Path | None = None):
    """The Dirichlet filter of the ``dirichlet`` association.

    Args:
        filter_spec: a filter (returned as is), a ``dirichlet.json`` file, a folder holding
            one (a ``geoseg train dirichlet`` run) or the name of shipped filters
            (``dirichlet_real``); None: the one shipped for ``weights``.
        weights: the naive CNN it filters (:func:`load_network`; None: the shipped
            ``naive``): a shipped naive CNN, by name or by its folder or files, gets the filter
            calibrated on it for its domain (``naive_real`` -> ``dirichlet_real``, for
            photographs; ``dirichlet_real_synth`` is its filter for renders); any other the shipped
            ``dirichlet``, with a warning (a filter is calibrated on one network's
            probabilities).

    Raises:
        GeosegError: no such file, or not a filter file.
    """
    from geoseg.dirichlet import load_filter
    from geoseg.pretrained import path_or_shipped

    if filter_spec is not None and not isinstance(filter_spec, (str, Path)):
        return filter_spec
    if filter_spec is None:
        name = _shipped_naive(weights)
        filter_spec = SHIPPED_FILTERS.get(name, "dirichlet")
        if name is None:
            logger.warning(
                "dirichlet: no filter given for the network %s; using the shipped one, "
                "calibrated on the shipped naive CNN (fit one: geoseg train dirichlet)",
                weights,
            )
    path = path_or_shipped(filter_spec)
    return load_filter(path / "dirichlet.json" if path.is_dir() else path)


def _shipped_naive(weights: str | Path | None) -> str | None:
    """The name of the shipped naive CNN ``weights`` names or lies in (None: another)."""
    from geoseg.pretrained import WEIGHTS_DIR

    if weights is None:
        return "naive"
    if str(weights) in SHIPPED_FILTERS:
        return str(weights)
    path = Path(weights)
    folder = (path if path.is_dir() else path.parent).resolve()
    return next((n for n in SHIPPED_FILTERS if folder == (WEIGHTS_DIR / n).resolve()), None)


def network_outputs(
    association: str,
    weights: str | Path | None,
    threads: int | None,
    size: tuple[int, int],
    colour_transfer=None,
) -> NetworkOutputs:
    """The worker's network (:func:`load_network` through
    :func:`~slam_bridge.bridge.worker.segmenter_outputs` at ``size``, its inputs mapped by
    ``colour_transfer`` first: :func:`colour_transfer_of`); with :func:`functools.partial`, the
    picklable recipe a child process builds it from."""
    return segmenter_outputs(load_network(association, weights, threads), size, colour_transfer)


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
    weights: str | Path | None = None,
    dirichlet_filter=None,
) -> BridgeWorker:
    """The worker of ``cfg.association`` over ``facades``.

    Args:
        cfg: the settings.
        facades: the building model.
        image_size: ``(W, H)`` of the SLAM's images (the network is checked on it).
        mesh: the model's mesh (``raycast``; :class:`trimesh.Trimesh`).
        segmenter: the network as an object (a :class:`geoseg.infer.Segmenter`, say); it runs
            in a thread or inline.
        weights: else the network's weights (:func:`load_network`; ``real``: the network for
            real photographs; default: ``cfg.network``, else the shipped ones).
        dirichlet_filter: the ``dirichlet`` rule's filter, or where to read it
            (:func:`load_dirichlet_filter`; default: the one shipped for ``weights``); its 5x5
            smoothing is applied to every network's maps before sampling.

    Raises:
        SlamError: a missing mesh for ``raycast``, a network the bridge cannot use
            (:func:`check_network`), a colour reference it cannot read
            (:func:`colour_transfer_of`).
    """
    method = cfg.association
    if weights is None and cfg.network is not None and segmenter is None:
        weights = cfg.network
    weights = resolve_weights(method, weights)
    network, make_network = None, None
    size = tuple(cfg.network_size)
    uses_network = method != "raycast"
    colour = colour_transfer_of(cfg, weights, segmenter)  # a bad reference fails before the run
    if uses_network and segmenter is not None:
        network = segmenter_outputs(segmenter, size, colour)
    elif uses_network and cfg.worker == "process":
        make_network = partial(network_outputs, method, weights, cfg.network_threads, size, colour)
    elif uses_network:
        network = network_outputs(method, weights, cfg.network_threads, size, colour)
    if uses_network:  # bayes uses the filter's smoothing only: the shipped one
        spec = dirichlet_filter if method == "dirichlet" else dirichlet_filter or "dirichlet"
        dirichlet_filter = load_dirichlet_filter(spec, weights)
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
    worker = BridgeWorker(
        network,
        NUM_CLASSES,
        rule,
        constraints,
        smooth_at=dirichlet_filter.smooth_at if uses_network else None,
        associate_every=cfg.associate_every,
        infer_every=cfg.infer_every,
        asynchronous=cfg.asynchronous,
        make_network=make_network,
        recent_keyframes=cfg.recent_keyframes,
        lag_keyframes=cfg.lag_keyframes,
    )
    if uses_network:
        try:
            worker.call_network(
                partial(check_network, image_size=image_size, needs_normals=method == "bayes")
            )
        except BaseException:
            worker.close()
            raise
    return worker
