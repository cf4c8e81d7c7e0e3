"""Ctrl-C during a command: a clear line saying what was kept, and the shell's exit code."""

from __future__ import annotations

import types

from geoseg_cli import cli


def test_an_interrupted_command_says_what_was_kept(monkeypatch, tmp_path, capsys):
    def run(args):
        raise KeyboardInterrupt

    real = cli._load("geoseg_cli.commands.render")
    stand_in = types.SimpleNamespace(configure=real.configure, run=run)
    monkeypatch.setattr(cli, "_load", lambda name: stand_in)
    code = cli.main(["render", "--out", str(tmp_path / "drive"), "--frames", "2"])
    assert code == cli.EXIT_INTERRUPTED == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and str(tmp_path / "drive") in err and "unfinished" in err
