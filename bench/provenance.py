"""Where a bench's figures come from: the keys every ``bench/results/*.json`` carries.

``provenance(split)`` gives ``command`` (the command line that ran), ``git_commit`` (the
checkout's commit, ``+dirty`` when it had uncommitted changes outside ``bench/results``), ``machine`` (CPU, cores, GPU,
the load when the run started), ``date`` (UTC, ISO 8601) and ``split`` (which data the figures
were measured on; see each bench's docstring).
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

__all__ = ["provenance", "git_commit", "machine"]


def git_commit() -> str:
    """The checkout's commit (``+dirty`` with uncommitted changes outside ``bench/results``), or
    ``unknown``."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            # results files are the benches' outputs: a run after another bench's is not dirty
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":!bench/results"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def machine() -> str:
    """CPU model, cores, GPU and the 1-minute load average at the call."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import torch

        gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    except ImportError:
        gpu = "no GPU"
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (
        f"{cpu}, {os.cpu_count()} cores, {gpu}, {platform.system()} {platform.release()}, "
        f"Python {platform.python_version()}, load {load:.1f} at start"
    )


def provenance(split: str, command: str | None = None) -> dict[str, str]:
    """The provenance keys of a results file (module docstring); call it when the run starts.

    ``command`` defaults to ``python`` and this process's ``sys.argv``; a bench whose ``main``
    takes its arguments as a list passes the command line those arguments make.
    """
    return {
        "command": command or " ".join(["python", *sys.argv]),
        "git_commit": git_commit(),
        "machine": machine(),
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "split": split,
    }
