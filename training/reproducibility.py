"""Seeding, deterministic settings and RNG state capture/restore.

Every random source a training run touches (Python's :mod:`random`, NumPy's global generator,
torch's CPU and CUDA generators, and the ``torch.Generator`` objects that drive a DataLoader's
shuffling) can be captured into plain data (tensors, ints, floats) that ``torch.load(...,
weights_only=True)`` accepts, and restored later, so a resumed run continues bit for bit.
"""

from __future__ import annotations

import logging
import os
import random
from collections.abc import Iterable
from typing import Any

import numpy as np
import torch

from geoseg.errors import GeosegError

logger = logging.getLogger(__name__)


def seed_everything(seed: int, *, deterministic: bool = True) -> None:
    """Seed Python, NumPy and torch (CPU and CUDA), optionally forcing deterministic kernels.

    Args:
        seed: a non-negative integer.
        deterministic: when True, ``torch.use_deterministic_algorithms(True)`` (warn only for
            ops without a deterministic implementation), cuDNN benchmarking off and
            ``CUBLAS_WORKSPACE_CONFIG`` set, so that runs on the same machine repeat exactly.
    """
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise GeosegError(f"seed: expected a non-negative integer, got {seed!r}")
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    if deterministic:
        set_deterministic(True)


def set_deterministic(enabled: bool = True) -> None:
    """Switch torch's deterministic-algorithm mode and cuDNN's benchmark mode."""
    if enabled:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(enabled, warn_only=True)
    # Deterministic mode also NaN-fills every new tensor; our kernels never read uninitialised
    # memory (three Adam steps are bit-identical either way) and the fill cost ~10 % of an ENet
    # step on the CPU (bench/train_speed.py).
    torch.utils.deterministic.fill_uninitialized_memory = False
    torch.backends.cudnn.deterministic = enabled
    torch.backends.cudnn.benchmark = not enabled


def make_generator(seed: int) -> torch.Generator:
    """A CPU ``torch.Generator`` seeded with ``seed`` (for a DataLoader's ``generator=``)."""
    gen = torch.Generator()
    gen.manual_seed(int(seed))
    return gen


def seed_worker(worker_id: int) -> None:
    """DataLoader ``worker_init_fn``: seed Python and NumPy in a worker from torch's seed.

    torch seeds each worker with ``base_seed + worker_id`` where ``base_seed`` comes from the
    loader's generator; this propagates that seed to the other libraries.
    """
    seed = torch.initial_seed() % 2**32
    random.seed(seed)
    np.random.seed(seed)


def capture_rng_state() -> dict[str, Any]:
    """The global RNG states as plain data accepted by ``torch.load(weights_only=True)``.

    Returns:
        A mapping with ``python`` (a dict: ``version`` int, ``state`` int64 tensor of 625
        entries, ``gauss`` float or None), ``numpy`` (``keys`` int64 tensor (624,), ``pos``,
        ``has_gauss``, ``gauss``), ``torch`` (uint8 tensor) and ``cuda`` (list of uint8 tensors,
        empty without CUDA).
    """
    version, py_state, gauss_next = random.getstate()
    np_name, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state(legacy=True)
    if np_name != "MT19937":  # pragma: no cover - NumPy's legacy global generator is MT19937
        raise GeosegError(f"unsupported NumPy global generator {np_name}")
    cuda = []
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        cuda = [s.clone() for s in torch.cuda.get_rng_state_all()]
    return {
        "python": {
            "version": int(version),
            "state": torch.tensor(py_state, dtype=torch.int64),
            "gauss": gauss_next,
        },
        "numpy": {
            "keys": torch.from_numpy(np.asarray(np_keys, dtype=np.int64).copy()),
            "pos": int(np_pos),
            "has_gauss": int(np_has_gauss),
            "gauss": float(np_gauss),
        },
        "torch": torch.get_rng_state().clone(),
        "cuda": cuda,
    }


def restore_rng_state(state: dict[str, Any]) -> None:
    """Restore the global RNG states captured by :func:`capture_rng_state`.

    CUDA states are restored only when CUDA is available and the device count matches (a
    checkpoint from a GPU machine resumes on a CPU machine, with a log message).
    """
    try:
        py = state["python"]
        random.setstate(
            (py["version"], tuple(int(v) for v in py["state"].cpu().tolist()), py["gauss"])
        )
        np_state = state["numpy"]
        np.random.set_state(
            (
                "MT19937",
                np_state["keys"].cpu().numpy().astype(np.uint32),
                int(np_state["pos"]),
                int(np_state["has_gauss"]),
                float(np_state["gauss"]),
            )
        )
        torch.set_rng_state(state["torch"].cpu())
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as err:
        raise GeosegError(f"RNG state: malformed ({type(err).__name__}: {err})") from None
    cuda = state.get("cuda") or []
    if cuda:
        if torch.cuda.is_available() and torch.cuda.device_count() == len(cuda):
            torch.cuda.set_rng_state_all([s.cpu() for s in cuda])
        else:
            logger.info("checkpoint holds %d CUDA RNG states; not restored here", len(cuda))


def capture_generators(generators: Iterable[torch.Generator]) -> list[torch.Tensor]:
    """The states (uint8 tensors) of ``generators``, in order."""
    return [g.get_state().clone() for g in generators]


def restore_generators(generators: Iterable[torch.Generator], states: list[torch.Tensor]) -> None:
    """Restore ``generators`` from :func:`capture_generators` output (same order and count)."""
    generators = list(generators)
    if len(generators) != len(states):
        raise GeosegError(
            f"generator states: expected {len(generators)} (one per data-loader generator), "
            f"got {len(states)}"
        )
    for gen, st in zip(generators, states):
        gen.set_state(st.cpu())


def loader_generators(loader: Any) -> list[torch.Generator]:
    """The distinct ``torch.Generator`` objects that drive a DataLoader's randomness.

    Looks at ``loader.generator``, ``loader.sampler.generator`` and
    ``loader.batch_sampler.sampler.generator`` (deduplicated, in that order).
    """
    found: list[torch.Generator] = []
    candidates = [
        getattr(loader, "generator", None),
        getattr(getattr(loader, "sampler", None), "generator", None),
        getattr(
            getattr(getattr(loader, "batch_sampler", None), "sampler", None), "generator", None
        ),
    ]
    for gen in candidates:
        if isinstance(gen, torch.Generator) and not any(gen is g for g in found):
            found.append(gen)
    return found
