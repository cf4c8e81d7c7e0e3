"""Training of geoseg's networks: one module per trainer sharing one loop, checkpoints, resume."""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
