"""The training-checkpoint format: what marks a file as a geoseg training checkpoint, and the
check every reader applies.

It lives in ``geoseg`` (not beside the trainers that write it, :mod:`training.checkpoint`) so
that :mod:`geoseg.infer` reads a run's ``best.pt`` / ``last.pt`` without importing ``training``.

A checkpoint is one ``torch.save``-d mapping of plain data (tensors, numbers, strings, lists,
dicts) so that it loads with ``torch.load(path, weights_only=True)`` and nothing else:

================== ==============================================================
key                content
================== ==============================================================
``format``         ``"geoseg-checkpoint"`` (marks the file as ours)
``version``        format version, :data:`FORMAT_VERSION`
``model_name``     registry name of the architecture (``str`` or None)
``model_config``   the builder's keyword arguments (plain dict)
``model``          the model's ``state_dict`` (unwrapped from DDP)
``optimizer``      the optimizer's ``state_dict`` or None
``scheduler``      the LR scheduler's ``state_dict`` or None
``scaler``         the AMP grad scaler's ``state_dict`` or None
``epoch``          number of completed epochs
``global_step``    number of completed optimizer steps
``rng``            :func:`training.reproducibility.capture_rng_state` output
``generators``     states of the data loader's ``torch.Generator`` objects
``config``         the run's configuration (plain dict)
``history``        per-epoch metric rows (list of dicts)
``best``           best validation value so far (float or None)
``best_epoch``     the epoch that value comes from (int or None)
``extra``          anything else the caller wants to keep (plain data)
``sha256``         SHA-256 of everything above (:mod:`geoseg.integrity`), checked on load
================== ==============================================================
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from geoseg.errors import GeosegError

FORMAT = "geoseg-checkpoint"
FORMAT_VERSION = 1
LAST = "last.pt"
BEST = "best.pt"
#: keys a checkpoint must hold to be read (:func:`validate_checkpoint`)
REQUIRED_KEYS = ("format", "version", "model", "epoch", "global_step")


def validate_checkpoint(data: Mapping[str, Any], path: str | Path) -> dict[str, Any]:
    """Check that a loaded mapping is a geoseg training checkpoint this version reads.

    Raises:
        GeosegError: another format, missing keys, a newer format version (names the file).
    """
    if not isinstance(data, Mapping) or data.get("format") != FORMAT:
        what = (
            f"keys {sorted(map(str, data))[:8]}"
            if isinstance(data, Mapping)
            else type(data).__name__
        )
        raise GeosegError(f"checkpoint {path} is not a geoseg checkpoint (found {what})")
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise GeosegError(f"checkpoint {path} is incomplete: missing {', '.join(missing)}")
    if int(data["version"]) > FORMAT_VERSION:
        raise GeosegError(
            f"checkpoint {path} has format version {data['version']}, newer than this geoseg "
            f"({FORMAT_VERSION})"
        )
    return dict(data)
