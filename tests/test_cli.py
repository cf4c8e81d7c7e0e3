"""The `geoseg` entry point: help lists every subcommand."""

import subprocess
import sys

from geoseg_cli.cli import COMMANDS, main


def test_help_lists_every_subcommand(capsys) -> None:
    assert main([]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_console_script_runs() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "geoseg_cli", "--help"], capture_output=True, text=True, check=True
    )
    assert "render" in proc.stdout and "demo" in proc.stdout
