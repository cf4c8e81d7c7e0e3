"""The bridge beside the SLAM (thesis fig. 4.21): inference and association off the main loop.

:class:`BridgeWorker` is the loop's per-keyframe hook (``run_slam(..., on_keyframe=worker)``).
At each keyframe it

1. applies, in the main thread and in submission order, what the worker thread has finished
   since: the network outputs sampled at a keyframe's observations (added to the points'
   evidence, :class:`~slam_bridge.bridge.evidence.PointEvidence`) and new associations (handed
   to the fusion's :class:`~slam_bridge.bridge.constraints.BuildingConstraints`);
2. submits the keyframe's image with a copy of its observations and rotation (inference;
   every ``infer_every``-th keyframe, for a network too slow to label them all);
3. every ``associate_every`` keyframes, submits a snapshot of the points (positions, evidence,
   the camera centre each is seen from) to the association: of the points seen in the last
   ``recent_keyframes`` keyframes only, since the fusion constrains the points of its window
   and an association is per point (the final association, :meth:`BridgeWorker.finish`, covers
   them all). The loop's thread gathers only those rows (:class:`PointRows`); the association's
   thread spreads them over the map's points.

By default the SLAM never waits: a job that is not finished is applied at a later keyframe
(its *lag*, in keyframes), and inference jobs beyond ``max_pending`` are dropped (that keyframe
adds no evidence); the result then depends on the machine's speed. With ``lag_keyframes = L``
the jobs submitted at keyframe ``k`` are applied at keyframe ``k + L`` exactly, waited for when
late, and none is dropped: a repeatable run, the same as the inline worker with the same lag. Association runs in a thread of its own (an association does not queue behind
inference). Inference runs in a thread too, or, given ``make_network``, in a **child process**
that builds the network once, at a lower scheduling priority than the loop: the network
runtime releases the GIL, but the resizing, smoothing and sampling around it do not, and in a
thread they take turns with the loop's Python code. A script that builds such a worker must
guard its entry point (``if __name__ == "__main__":``): the child is started by ``spawn``, which
imports the script's main module again.
With ``asynchronous=False`` the jobs run inline when submitted and their results are applied at
the next keyframe, as an asynchronous worker that kept up would apply them: the same numbers,
deterministically.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from slam_bridge.bridge.association import Association
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.bridge.evidence import PixelSampler, PointEvidence, sample_outputs
from slam_bridge.errors import SlamError
from slam_bridge.slam.map import Map

logger = logging.getLogger(__name__)

__all__ = ["AssociationInputs", "BridgeStats", "BridgeWorker", "PointRows", "segmenter_outputs"]

#: image ``(H, W, 3)`` uint8 RGB -> (probabilities ``(h, w, K)``, normals ``(h, w, 3)`` or None)
NetworkOutputs = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]]
#: ``(image, uv (N, 2), R_wc (3, 3))`` of one keyframe's inference
InferenceJob = tuple[np.ndarray, np.ndarray, np.ndarray]


def infer_and_sample(
    network: NetworkOutputs, job: InferenceJob, num_classes: int, smooth_at: PixelSampler | None
) -> tuple[object, float]:
    """The network's outputs at a keyframe's observations (:func:`~slam_bridge.bridge.evidence.
    sample_outputs`) and the seconds it took."""
    image, uv, R_wc = job
    t0 = time.perf_counter()
    probs, normals = network(image)
    size = (image.shape[1], image.shape[0])
    out = sample_outputs(probs, normals, uv, R_wc, size, num_classes, smooth_at)
    return out, time.perf_counter() - t0


# the child process's network and settings (:func:`_child_start`), one per child
_CHILD: dict = {}
#: scheduling priority of the child below the SLAM's (POSIX ``nice``): on a machine with few
#: cores the loop's own work goes first when both want the same core
CHILD_NICENESS = 10


def _child_start(
    make_network: Callable[[], NetworkOutputs], num_classes: int, smooth_at: PixelSampler | None
) -> None:
    if hasattr(os, "nice"):  # the loop first: the network gets the cycles the loop leaves
        os.nice(CHILD_NICENESS)
    _CHILD.update(num_classes=num_classes, smooth_at=smooth_at)
    try:
        _CHILD["network"] = make_network()
    except Exception as exc:  # raised by the first job, in the parent (an initializer's error
        _CHILD["error"] = exc  # would only break the pool)


def _child_network() -> NetworkOutputs:
    if "error" in _CHILD:
        raise _CHILD["error"]
    return _CHILD["network"]


def _child_infer(job: InferenceJob) -> tuple[object, float]:
    return infer_and_sample(_child_network(), job, _CHILD["num_classes"], _CHILD["smooth_at"])


def _child_call(fn: Callable[[NetworkOutputs], object]) -> object:
    return fn(_child_network())


def _built(network: NetworkOutputs) -> None:
    """Nothing: a first call that waits for the child's network to be built."""


@dataclass(frozen=True)
class AssociationInputs:
    """A snapshot of the map's points for an association (``P`` points).

    Attributes:
        keyframe: the keyframe at which it was taken.
        points: ``(P, 3)`` positions, NaN where not triangulated.
        mean_probs: ``(P, K)`` mean probability vectors (NaN rows: no evidence).
        labels: ``(P,)`` voted classes (-1: no evidence).
        normals: ``(P, 3)`` mean world-frame normals (NaN rows: none).
        centres: ``(P, 3)`` centre of the latest keyframe observing each point.
    """

    keyframe: int
    points: np.ndarray
    mean_probs: np.ndarray
    labels: np.ndarray
    normals: np.ndarray
    centres: np.ndarray


@dataclass
class BridgeStats:
    """What the worker did.

    Attributes:
        inference_seconds: per inference job (worker time).
        association_seconds: per association job.
        main_seconds: per keyframe, the hook's own time in the main loop.
        lags: keyframes between an association's submission and its use.
        dropped: inference jobs dropped (too many pending).
    """

    inference_seconds: list[float] = field(default_factory=list)
    association_seconds: list[float] = field(default_factory=list)
    main_seconds: list[float] = field(default_factory=list)
    lags: list[int] = field(default_factory=list)
    dropped: int = 0


class BridgeWorker:
    """Network inference, evidence and association beside the loop (module docstring).

    Args:
        network: the network's outputs for an image (None: no inference, for the ray-cast
            baseline, which needs the points' positions only).
        num_classes: ``K`` of its probabilities.
        associate: an association of a snapshot (e.g. :func:`~slam_bridge.bridge.association.
            associate_bayes` over the model's facades).
        constraints: the fusion's building provider, given each new association.
        smooth_at: the vectors a probability map gives at the sampled pixels (the Dirichlet
            filter's box means, :meth:`geoseg.dirichlet.DirichletFilter.smooth_at`).
        associate_every: keyframes between associations.
        infer_every: keyframes between inferences (1: every keyframe). A map point is seen in
            many keyframes, so a slow network labelling every few still reaches most points,
            deterministically (where dropping jobs depends on the machine's load).
        max_pending: most inference jobs waiting; more are dropped.
        asynchronous: run the jobs beside the loop (False: inline, deterministic).
        image_at: ``timestamp -> (H, W, 3) uint8`` image of a keyframe the hook gets without
            observations (those the start-up placed; None: they get no evidence).
        make_network: a picklable ``() -> network`` instead of ``network``: with
            ``asynchronous``, inference runs in a child process that calls it once (started,
            and its network built, before the constructor returns); inline, it is called
            here.
        recent_keyframes: the snapshots of the online associations hold the points observed
            in this many latest keyframes (None: all points). It must cover the fusion's window
            (the k-BA's ``l`` and ``history_keyframes``) with the lag of the associations.
        lag_keyframes: apply each job exactly this many keyframes after its submission,
            waiting for it when late (repeatable); None: as soon as it is done (inline: at the
            next keyframe).
    """

    def __init__(
        self,
        network: NetworkOutputs | None,
        num_classes: int,
        associate: Callable[[AssociationInputs], Association],
        constraints: BuildingConstraints,
        *,
        smooth_at: PixelSampler | None = None,
        associate_every: int = 5,
        infer_every: int = 1,
        max_pending: int = 4,
        asynchronous: bool = True,
        image_at: Callable[[float], np.ndarray] | None = None,
        make_network: Callable[[], NetworkOutputs] | None = None,
        recent_keyframes: int | None = None,
        lag_keyframes: int | None = None,
    ) -> None:
        if lag_keyframes is not None and lag_keyframes < 1:
            raise SlamError(f"lag_keyframes: expected >= 1 or None, got {lag_keyframes}")
        self.lag_keyframes = lag_keyframes
        if min(associate_every, infer_every, max_pending) < 1:
            raise SlamError("associate_every, infer_every and max_pending must be >= 1")
        if recent_keyframes is not None and recent_keyframes < 1:
            raise SlamError(f"recent_keyframes: expected >= 1 or None, got {recent_keyframes}")
        self.recent_keyframes = recent_keyframes
        self.num_classes = num_classes
        self.associate, self.constraints, self.smooth_at = associate, constraints, smooth_at
        self.associate_every, self.max_pending = associate_every, max_pending
        self.infer_every = infer_every
        self.asynchronous, self.image_at = asynchronous, image_at
        self.evidence: PointEvidence | None = None
        self.stats = BridgeStats()
        # one thread and one queue per kind: an association never waits behind inference
        self._pending: dict[str, deque[tuple[int, object, Future]]] = {
            "infer": deque(),
            "associate": deque(),
        }
        self.in_process = asynchronous and make_network is not None
        if make_network is not None and not asynchronous and network is None:
            network = make_network()
        self.network = network
        self._pools: dict[str, Executor] | None = None
        if asynchronous:
            self._pools = {"associate": ThreadPoolExecutor(1, "bridge-associate")}
            if self.in_process:  # spawn: the parent's threads (onnxruntime's) do not fork well
                self._pools["infer"] = ProcessPoolExecutor(
                    1,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_child_start,
                    initargs=(make_network, num_classes, smooth_at),
                )
                try:
                    self.call_network(_built)  # started and built now: its errors raise here
                except BaseException:
                    self.close()
                    raise
            else:
                self._pools["infer"] = ThreadPoolExecutor(1, "bridge-infer")

    # ------------------------------------------------------------------ the loop's hook
    def __call__(self, slam_map: Map, k: int, obs) -> None:
        """Apply finished jobs, then submit keyframe ``k``'s (module docstring); ``obs`` is its
        :class:`~slam_bridge.frontend.base.KeyframeObservations`, or None (a start keyframe)."""
        t0 = time.perf_counter()
        if self.evidence is None:
            self.evidence = PointEvidence(slam_map, self.num_classes, self.smooth_at)
        self._apply(slam_map, k, wait=False)
        infer = (self.network is not None or self.in_process) and k % self.infer_every == 0
        image = None if obs is None or not infer else obs.image
        if infer and image is None and self.image_at is not None:
            image = self.image_at(float(slam_map.timestamps[k]))
        if infer and image is not None and 0 <= k < slam_map.num_keyframes:
            waiting = sum(not f.done() for _, _, f in self._pending["infer"])
            if waiting >= self.max_pending and self.lag_keyframes is None:
                self.stats.dropped += 1
            else:
                idx = slam_map.keyframe_observations(k)
                idx = idx[slam_map.obs_active[idx]]
                job = (image, slam_map.obs_uv[idx].copy(), slam_map.R_wc[k].copy())
                fn = _child_infer if self.in_process else self._infer
                self._submit("infer", k, slam_map.obs_point[idx].copy(), fn, job)
        if k % self.associate_every == 0:
            snapshot = self._snapshot(slam_map, k, recent=self.recent_keyframes)
            self._submit("associate", k, None, self._associate, snapshot)
        self.stats.main_seconds.append(time.perf_counter() - t0)

    def finish(self, slam_map: Map) -> Association | None:
        """Wait for every job, apply them, associate the final map once more and stop the
        thread. Returns the final association (None before any keyframe)."""
        if self.evidence is None:
            return None
        k = slam_map.num_keyframes
        self._apply(slam_map, k, wait=True)
        final = self.associate(self._snapshot(slam_map, k, recent=None).inputs())
        self.constraints.update(final)
        self.close()
        return final

    def close(self) -> None:
        """Stop the threads (and the child process), dropping the jobs not started (after a
        failed run, say)."""
        if self._pools is not None:
            for pool in self._pools.values():
                pool.shutdown(wait=True, cancel_futures=True)
            self._pools = None

    def call_network(self, fn: Callable[[NetworkOutputs], object]) -> object:
        """``fn(network)`` where the network lives (the child process: ``fn`` picklable),
        waited for; its errors are raised here."""
        if self.in_process:
            return self._pools["infer"].submit(_child_call, fn).result()
        return fn(self.network)

    # ------------------------------------------------------------------ jobs
    def _submit(self, kind: str, k: int, payload, fn, arg) -> None:
        if self._pools is None:
            fut: Future = Future()
            fut.set_result(fn(arg))
        else:
            fut = self._pools[kind].submit(fn, arg)
        self._pending[kind].append((k, payload, fut))

    def _infer(self, job: InferenceJob) -> tuple[object, float]:
        return infer_and_sample(self.network, job, self.num_classes, self.smooth_at)

    def _associate(self, rows: PointRows) -> tuple[Association, float]:
        t0 = time.perf_counter()
        out = self.associate(rows.inputs())
        return out, time.perf_counter() - t0

    def _apply(self, slam_map: Map, k: int, wait: bool) -> None:
        """Apply the finished jobs of each kind in submission order (all when ``wait``)."""
        lag = self.lag_keyframes
        for kind, pending in self._pending.items():
            while pending and (
                wait or (pending[0][2].done() if lag is None else k - pending[0][0] >= lag)
            ):
                k_sub, payload, fut = pending.popleft()
                result, seconds = fut.result()  # re-raises a job's error here, in the main thread
                if kind == "infer":
                    self.evidence.add_samples(k_sub, payload, result)
                    self.stats.inference_seconds.append(seconds)
                else:
                    self.constraints.update(result)
                    self.stats.association_seconds.append(seconds)
                    self.stats.lags.append(k - k_sub)

    def _snapshot(self, slam_map: Map, k: int, recent: int | None) -> PointRows:
        """The triangulated points observed in keyframes ``k - recent .. k`` (all with None).
        Only those rows are gathered here, in the loop's thread; the association's thread
        spreads them over the map's points (:meth:`PointRows.inputs`)."""
        ev, m = self.evidence, slam_map
        first = 0 if recent is None else int(m.starts[min(max(0, k - recent), m.num_keyframes)])
        last = np.full(m.num_points, -1, np.int64)  # the latest keyframe observing each point
        np.maximum.at(last, m.obs_point[first:], m.obs_keyframe[first:])
        ids = np.flatnonzero(last >= 0)
        ids = ids[m.triangulated[ids]]  # the points an association can place
        return PointRows(
            keyframe=k,
            num_points=m.num_points,
            ids=ids,
            points=m.X_w[ids],
            mean_probs=ev.mean_probs(ids),
            labels=ev.labels(ids),
            normals=ev.normals(ids),
            centres=m.t_wc[last[ids]],
        )


@dataclass(frozen=True)
class PointRows:
    """Some of a map's points, as :class:`AssociationInputs` holds them (``N`` rows).

    Attributes:
        keyframe: the keyframe at which they were taken.
        num_points: ``P``, the map's points then.
        ids: ``(N,)`` their point ids.
        points, mean_probs, labels, normals, centres: their rows of
            :class:`AssociationInputs`' arrays.
    """

    keyframe: int
    num_points: int
    ids: np.ndarray
    points: np.ndarray
    mean_probs: np.ndarray
    labels: np.ndarray
    normals: np.ndarray
    centres: np.ndarray

    def inputs(self) -> AssociationInputs:
        """The association's inputs over all ``P`` points: the other rows empty (NaN
        positions: not associated)."""
        P, ids = self.num_points, self.ids

        def spread(rows: np.ndarray, empty: float) -> np.ndarray:
            out = np.full((P, *rows.shape[1:]), empty, dtype=rows.dtype)
            out[ids] = rows
            return out

        return AssociationInputs(
            keyframe=self.keyframe,
            points=spread(self.points, np.nan),
            mean_probs=spread(self.mean_probs, np.nan),
            labels=spread(self.labels, -1),
            normals=spread(self.normals, np.nan),
            centres=spread(self.centres, np.nan),
        )


def segmenter_outputs(
    segmenter,
    input_size: tuple[int, int] | None = None,
    colour_transfer: Callable[[np.ndarray], np.ndarray] | None = None,
) -> NetworkOutputs:
    """A :class:`geoseg.infer.Segmenter` as the worker's network.

    Args:
        segmenter: the network (the joint network gives normals, the naive CNN none).
        input_size: ``(W, H)`` the image is resized to first (area interpolation), the size
            the network was trained at; None: as it comes.
        colour_transfer: ``(H, W, 3) uint8 RGB -> the same``, applied after the resizing (a
            grey image made RGB first): e.g. a :class:`geoseg.colour_transfer.ColourTransfer`
            onto the training set's colours; None: the image as it comes.

    Returns:
        ``image (H, W, 3) uint8 -> (probabilities (h, w, K), normals (h, w, 3) or None)``.
    """
    import cv2

    from geoseg.infer import as_rgb

    def run(image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        if input_size is not None and (image.shape[1], image.shape[0]) != tuple(input_size):
            image = cv2.resize(image, tuple(input_size), interpolation=cv2.INTER_AREA)
        if colour_transfer is not None:  # after resizing: a quarter of the pixels to map
            image = colour_transfer(as_rgb(image)[0])
        out = segmenter(image)
        probs = out.probabilities[0].transpose(1, 2, 0)
        normals = None if out.normals is None else out.normals[0].transpose(1, 2, 0)
        return probs, normals

    return run
