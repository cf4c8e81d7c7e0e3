"""The ``geoseg`` command line: the application on top of the three libraries.

:mod:`geoseg_cli.cli` is the entry point (``[project.scripts] geoseg``, or ``python -m
geoseg_cli``); :mod:`geoseg_cli.commands` holds one module per subcommand. The command line
sits above ``geoseg``, ``training`` and ``slam_bridge`` and may import any of them; none of them
imports it (docs/architecture.md, the layer rule, tests/test_layers.py).
"""
