"""geoseg command-line subcommands: one module each, ``configure(parser)`` and ``run(args)``."""
