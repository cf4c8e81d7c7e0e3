"""The bad-input suite's fixtures and its closing figures.

``harness.py`` (imported by name from this folder) holds the environment, the argv builders and
the classifier; ``env`` builds the environment once per session. At the end of the session the
counts per command (table cases, generated bad values; outcomes A-D, :mod:`harness`) are printed
by ``tests/conftest.py`` (which gathers them from pytest-xdist's workers).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import Env, build_env  # noqa: E402


@pytest.fixture(scope="session")
def env(tmp_path_factory, enet_files) -> Env:
    return build_env(tmp_path_factory.mktemp("bad_inputs"), enet_files)
