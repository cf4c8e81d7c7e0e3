"""``python -m geoseg_cli ...`` equals the ``geoseg`` command (e.g. under ``torchrun -m``)."""

from geoseg_cli.cli import main

raise SystemExit(main())
