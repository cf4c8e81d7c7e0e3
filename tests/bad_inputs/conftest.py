"""The bad-input suite's fixtures and its closing figures.

``harness.py`` (imported by name from this folder) holds the environment, the argv builders and
the classifier; ``env`` builds the environment once per session. At the end of the session the
counts per command (table cases, generated bad values; outcomes A-D, :mod:`harness`) are printed.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import GENERATED, OUTCOMES, REPORTED, Env, build_env  # noqa: E402


@pytest.fixture(scope="session")
def env(tmp_path_factory, enet_files) -> Env:
    return build_env(tmp_path_factory.mktemp("bad_inputs"), enet_files)


def pytest_terminal_summary(terminalreporter) -> None:
    rows = []
    for command in REPORTED:
        for kind, counts in (("table", OUTCOMES), ("generated", GENERATED)):
            c = counts[command]
            if c:
                rows.append(
                    f"{command:<11} {kind:>9} {sum(c.values()):>5} {c['A']:>5} {c['B']:>3} "
                    f"{c['C']:>3} {c['D']:>3}"
                )
    if rows:
        terminalreporter.write_sep(
            "-",
            "bad inputs and faults tried (A clear error, B traceback, "
            "C silent wrong result, D data loss)",
        )
        terminalreporter.write_line(
            f"{'command':<11} {'':>9} {'tried':>5} {'A':>5} {'B':>3} {'C':>3} {'D':>3}"
        )
        for row in rows:
            terminalreporter.write_line(row)
