"""The switch of the compiled (numba) kernels of the bundle adjustment.

The state's retraction, :func:`slam_bridge.ba.normal_equations.assemble`, the Schur solver and
the reprojection / pose-graph factors run compiled loops when numba is installed; the pure-NumPy
path gives the same results up to rounding.
"""

from __future__ import annotations

import os

try:  # optional accelerator: compiled loops for the hot paths (same results up to rounding)
    import numba as _numba
except ImportError:  # pragma: no cover - depends on the environment
    _numba = None

__all__ = ["USE_NUMBA", "numba_enabled"]

#: Use the compiled (numba) kernels of :func:`slam_bridge.ba.normal_equations.assemble`, the Schur
#: solver and the reprojection factor when numba is installed. ``False`` (or the environment
#: variable ``SLAM_BRIDGE_NUMBA=0`` at import) selects the pure-NumPy path.
USE_NUMBA = _numba is not None and os.environ.get("SLAM_BRIDGE_NUMBA", "1") != "0"


def _njit(fn):
    """``numba.njit`` (cached on disk) when numba is installed, else ``fn`` itself (unused then)."""
    if _numba is None:
        return fn
    return _numba.njit(cache=True, nogil=True)(fn)


def numba_enabled() -> bool:
    """True when the compiled kernels are used (numba installed and :data:`USE_NUMBA`)."""
    return bool(USE_NUMBA) and _numba is not None
