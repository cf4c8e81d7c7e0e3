"""geoseg: deep-learning-assisted, georeferenced vehicle localisation (Salehi, 2018).

The package holds the networks and their inference (:mod:`geoseg.models`, :mod:`geoseg.export`),
the Dirichlet false-positive filter, relocalisation, and the synthetic urban world
(:mod:`geoseg.synth`) that everything trains and is evaluated on.
"""

import logging

from geoseg.errors import GeosegError

__version__ = "0.1.0"
__all__ = ["GeosegError", "__version__"]

# One package logger; the CLI configures handlers, the library never does.
logging.getLogger(__name__).addHandler(logging.NullHandler())
