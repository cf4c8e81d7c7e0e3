"""Shared fixtures for the training tests.

``_restore_torch_determinism`` and ``_restore_grad_mode`` (autouse) put torch's global switches
back after each test: trainers turn deterministic algorithms on
(:mod:`training.reproducibility`) and ``bench/accuracy_reloc.py`` turns gradients off, which
would leak into later tests. A test module defining a fixture of the same name overrides these.
``run_files`` names the files every trainer's run directory holds (:mod:`training.common`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

# tiny_run.py (a helper module, also run as a script by the fault-injection tests) is imported
# by name from this folder.
sys.path.insert(0, str(Path(__file__).resolve().parent))


@pytest.fixture(autouse=True)
def _restore_torch_determinism():
    enabled = torch.are_deterministic_algorithms_enabled()
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    yield
    torch.use_deterministic_algorithms(enabled, warn_only=warn_only)


@pytest.fixture(autouse=True)
def _restore_grad_mode():
    enabled = torch.is_grad_enabled()
    yield
    torch.set_grad_enabled(enabled)


@pytest.fixture(scope="session")
def run_files() -> tuple[str, ...]:
    """The files of a finished run with ``export`` on (with ``plots`` on, ``loss.png`` too)."""
    return (
        "config.yaml",
        "last.pt",
        "best.pt",
        "metrics.csv",
        "metrics.json",
        "model.pt",
        "model.onnx",
        "model_card.json",
        "model_card.md",
    )
