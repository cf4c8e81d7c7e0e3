"""Data-parallel training across processes: ``torchrun`` + DistributedDataParallel.

Launch any trainer with ``torchrun --nproc_per_node=N ...``; :func:`init_distributed` reads the
environment that torchrun sets (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR``,
``MASTER_PORT``) and joins the process group (``nccl`` on GPUs, ``gloo`` on CPU). Without those
variables everything here degrades to a single process: samplers are ordinary, reductions are
identity, and every process is the main one.

Each process sees ``batch_size`` samples per step through a :class:`DistributedSampler`; DDP
averages the gradients, so N processes with per-process batch b match one process with batch
N*b (for losses that are means over the batch, and without batch-norm statistics effects).
"""

from __future__ import annotations

import datetime
import logging
import os
import socket
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import (
    DataLoader,
    Dataset,
    DistributedSampler,
    RandomSampler,
    Sampler,
    SequentialSampler,
)

from geoseg.errors import GeosegError
from training.reproducibility import make_generator, seed_worker

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DistInfo:
    """Where this process sits: ``rank`` of ``world_size`` processes, ``local_rank`` on its
    machine, the ``backend`` (None when not distributed) and its ``device``."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None
    device: torch.device = torch.device("cpu")

    @property
    def distributed(self) -> bool:
        """True when more than one process takes part."""
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """True on rank 0 (the process that logs and writes files)."""
        return self.rank == 0


def resolve_device(device: str | torch.device = "auto", local_rank: int = 0) -> torch.device:
    """``"auto"`` → ``cuda:<local_rank>`` when CUDA is available, else CPU; others verbatim.

    Raises:
        GeosegError: CUDA requested but not available.
    """
    if isinstance(device, torch.device):
        device = str(device)
    if device == "auto":
        return (
            torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
        )
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise GeosegError(f"device: {device!r} requested but CUDA is not available here")
    if device == "cuda":
        return torch.device(f"cuda:{local_rank}")
    try:
        return torch.device(device)
    except RuntimeError as err:
        raise GeosegError(f"device: {device!r} is not a device ({err})") from None


def init_distributed(
    device: str = "auto", *, backend: str | None = None, timeout_s: float = 300.0
) -> DistInfo:
    """Join the process group described by torchrun's environment variables.

    Args:
        device: as :func:`resolve_device`; with CUDA each process takes ``cuda:<LOCAL_RANK>``.
        backend: ``"gloo"`` or ``"nccl"``; default nccl on CUDA devices, gloo otherwise.
        timeout_s: collective timeout.

    Returns:
        This process's :class:`DistInfo` (a single-process one when ``WORLD_SIZE`` is unset or 1).

    Raises:
        GeosegError: incomplete environment (e.g. ``RANK`` without ``MASTER_PORT``).
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    dev = resolve_device(device, local_rank)
    if world_size <= 1:
        return DistInfo(device=dev)
    missing = [k for k in ("RANK", "MASTER_ADDR", "MASTER_PORT") if k not in os.environ]
    if missing:
        raise GeosegError(
            f"distributed environment: WORLD_SIZE={world_size} but {', '.join(missing)} unset "
            "(launch with torchrun)"
        )
    rank = int(os.environ["RANK"])
    backend = backend or ("nccl" if dev.type == "cuda" else "gloo")
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if not dist.is_initialized():
        dist.init_process_group(
            backend=backend,
            init_method="env://",
            rank=rank,
            world_size=world_size,
            timeout=datetime.timedelta(seconds=timeout_s),
        )
    logger.info("process %d/%d joined (%s, %s)", rank, world_size, backend, dev)
    return DistInfo(rank, world_size, local_rank, backend, dev)


def cleanup() -> None:
    """Leave the process group (no-op when not distributed)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def is_distributed() -> bool:
    """True inside an initialised process group of more than one process."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def get_rank() -> int:
    """This process's rank (0 when not distributed)."""
    return dist.get_rank() if is_distributed() else 0


def get_world_size() -> int:
    """Number of processes (1 when not distributed)."""
    return dist.get_world_size() if is_distributed() else 1


def is_main_process() -> bool:
    """True on rank 0 or when not distributed: the process that logs and writes files."""
    return get_rank() == 0


def barrier() -> None:
    """Wait for every process (no-op when not distributed)."""
    if is_distributed():
        dist.barrier()


def cpu_threads_per_process(requested: int | None, num_workers: int) -> int:
    """torch intra-op threads for one training process on the CPU.

    ``requested`` wins when given; otherwise the cores are shared between the processes of the
    job and each process's data workers (at least one thread). Oversubscribed OpenMP threads
    busy-wait on each other: on a 2-core machine with one renderer worker, 2 threads made an
    ENet step ~5x slower than 1 (``bench/train_speed.py``).
    """
    if requested is not None:
        return int(requested)
    cores = os.cpu_count() or 1
    return max(1, cores // get_world_size() - num_workers)


def wrap_model(
    model: nn.Module, device: torch.device, *, find_unused_parameters: bool = False
) -> nn.Module:
    """Wrap ``model`` (already on ``device``) in DistributedDataParallel when distributed.

    Args:
        model: the module; frozen parameters (``requires_grad=False``) are ignored by DDP.
        device: its device.
        find_unused_parameters: set when some trainable parameters get no gradient in a step
            (e.g. an output head that the loss does not use).
    """
    if not is_distributed() or isinstance(model, nn.parallel.DistributedDataParallel):
        return model
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return nn.parallel.DistributedDataParallel(
            model, device_ids=[index], find_unused_parameters=find_unused_parameters
        )
    return nn.parallel.DistributedDataParallel(model, find_unused_parameters=find_unused_parameters)


def quiet_non_main_ranks(names: tuple[str, ...] = ("geoseg", "training")) -> None:
    """Raise these loggers' level to WARNING on every rank but 0 (call once after
    :func:`init_distributed`, e.g. from the CLI), so that progress is logged once."""
    if not is_main_process():
        for name in names:
            logging.getLogger(name).setLevel(logging.WARNING)


def make_sampler(dataset: Dataset, *, shuffle: bool, seed: int = 0) -> Sampler:
    """A :class:`DistributedSampler` (each process its shard, reshuffled per epoch by
    ``set_epoch``) when distributed, else a seeded :class:`RandomSampler` or a
    :class:`SequentialSampler`.

    A DistributedSampler pads the shards to equal length by repeating samples: when the dataset
    size is not a multiple of the world size, a few samples count twice in DDP metrics.
    """
    if is_distributed():
        return DistributedSampler(dataset, shuffle=shuffle, seed=seed, drop_last=False)
    if shuffle:
        return RandomSampler(dataset, generator=make_generator(seed))
    return SequentialSampler(dataset)


def make_loader(
    dataset: Dataset,
    *,
    batch_size: int,
    shuffle: bool,
    seed: int = 0,
    num_workers: int = 0,
    drop_last: bool = False,
    pin_memory: bool = False,
) -> DataLoader:
    """A deterministic DataLoader: the sampler of :func:`make_sampler`, a seeded generator for
    the workers' base seed, and :func:`~training.reproducibility.seed_worker`."""
    return DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=make_sampler(dataset, shuffle=shuffle, seed=seed),
        num_workers=num_workers,
        drop_last=drop_last,
        pin_memory=pin_memory,
        generator=make_generator(seed + 1),
        worker_init_fn=seed_worker if num_workers else None,
        persistent_workers=False,
    )


def set_epoch(loader: Any, epoch: int) -> None:
    """Tell a loader's :class:`DistributedSampler` which epoch starts (for its shuffling)."""
    for sampler in (
        getattr(loader, "sampler", None),
        getattr(getattr(loader, "batch_sampler", None), "sampler", None),
    ):
        if isinstance(sampler, DistributedSampler):
            sampler.set_epoch(epoch)


def _collective_device() -> torch.device:
    if dist.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def all_reduce_sum_(tensor: torch.Tensor) -> torch.Tensor:
    """Sum ``tensor`` over processes, in place (moved to the backend's device and back)."""
    if not is_distributed():
        return tensor
    dev = _collective_device()
    work = tensor.to(dev)
    dist.all_reduce(work, op=dist.ReduceOp.SUM)
    if work is not tensor:
        tensor.copy_(work)
    return tensor


def reduce_meter_(meter: Any) -> None:
    """Sum a :class:`training.metrics.Meter`'s accumulators over processes, in place."""
    if is_distributed():
        meter.reduce_(all_reduce_sum_)


def all_reduce_mean(values: Mapping[str, float], weight: float = 1.0) -> dict[str, float]:
    """Weighted mean of scalar values over processes (weights: e.g. each process's samples).

    Args:
        values: name → local value (a mean over this process's ``weight`` samples).
        weight: this process's weight.

    Returns:
        name → global weighted mean (the input, unchanged, when not distributed).
    """
    if not is_distributed():
        return dict(values)
    keys = sorted(values)
    buf = torch.tensor(
        [float(values[k]) * weight for k in keys] + [float(weight)], dtype=torch.float64
    )
    all_reduce_sum_(buf)
    total = float(buf[-1])
    return {k: float(v) / total if total else float("nan") for k, v in zip(keys, buf[:-1].tolist())}


def find_free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` a moment ago (for ``MASTER_PORT``)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])
