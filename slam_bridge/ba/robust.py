"""Robust kernels ``rho(s)`` of the squared whitened residual norm ``s = ||r||^2``.

A factor family's cost is ``sum_m rho(s_m)``. The assembler
(:func:`slam_bridge.ba.normal_equations.assemble`) uses iteratively reweighted least squares: each
residual row's Jacobian products are weighted by ``rho'(s_m)`` (the Gauss-Newton Hessian of the
robust cost, without the ``rho''`` term), which is what Ceres and GTSAM do by default as well.

Kernels (``delta``/``sigma`` in whitened units, i.e. pixels for a 1-px reprojection sigma):

* :class:`TrivialKernel`: ``rho(s) = s``.
* :class:`HuberKernel`: ``rho(s) = s`` for ``s <= delta^2``, ``2 delta sqrt(s) - delta^2`` above.
* :class:`GemanMcClureKernel`: ``rho(s) = sigma^2 s / (sigma^2 + s)`` (bounded by ``sigma^2``).
* :class:`DeadZoneKernel`: ``rho(s) = (sqrt(s) - band)^2`` beyond ``band``, 0 within: a prior
  that lets a measurement's small biases pass and pulls back only large misses.

Use :func:`get_kernel` to build one by name (``"trivial"``, ``"huber"``, ``"geman_mcclure"``).
Kernels are pluggable: any object with ``rho(s)`` and ``weight(s)`` (``= rho'(s)``) works.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from geoseg.errors import check_positive
from slam_bridge.errors import SlamError

logger = logging.getLogger(__name__)

__all__ = [
    "RobustKernel",
    "TrivialKernel",
    "HuberKernel",
    "GemanMcClureKernel",
    "DeadZoneKernel",
    "get_kernel",
]


@runtime_checkable
class RobustKernel(Protocol):
    """Protocol of a robust kernel: ``rho(s)`` and its derivative ``weight(s) = rho'(s)``."""

    def rho(self, s: np.ndarray) -> np.ndarray:
        """``(M,)`` squared norms -> ``(M,)`` robust costs."""
        ...

    def weight(self, s: np.ndarray) -> np.ndarray:
        """``(M,)`` squared norms -> ``(M,)`` IRLS weights ``rho'(s)``."""
        ...


@dataclass(frozen=True)
class TrivialKernel:
    """``rho(s) = s``: plain least squares."""

    def rho(self, s: np.ndarray) -> np.ndarray:
        return np.asarray(s, dtype=np.float64)

    def weight(self, s: np.ndarray) -> np.ndarray:
        return np.ones_like(np.asarray(s, dtype=np.float64))


@dataclass(frozen=True)
class HuberKernel:
    """Huber: quadratic up to ``|r| = delta``, linear beyond (``rho(s) = 2 delta sqrt(s) - delta^2``)."""

    delta: float = 1.0

    def __post_init__(self) -> None:
        check_positive("delta", self.delta)

    def rho(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=np.float64)
        d = self.delta
        return np.where(s <= d * d, s, 2.0 * d * np.sqrt(np.maximum(s, d * d)) - d * d)

    def weight(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=np.float64)
        d = self.delta
        return np.where(s <= d * d, 1.0, d / np.sqrt(np.maximum(s, d * d)))


@dataclass(frozen=True)
class GemanMcClureKernel:
    """Geman-McClure with scale ``sigma``: ``rho(s) = sigma^2 s / (sigma^2 + s)``."""

    sigma: float = 1.0

    def __post_init__(self) -> None:
        check_positive("sigma", self.sigma)

    def rho(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=np.float64)
        c2 = self.sigma**2
        return c2 * s / (c2 + s)

    def weight(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=np.float64)
        c2 = self.sigma**2
        return (c2 / (c2 + s)) ** 2


@dataclass(frozen=True)
class DeadZoneKernel:
    """No cost within ``|r| <= band``, ``(|r| - band)^2`` beyond (continuous slope at ``band``)."""

    band: float = 1.0

    def __post_init__(self) -> None:
        check_positive("band", self.band)

    def rho(self, s: np.ndarray) -> np.ndarray:
        r = np.sqrt(np.maximum(np.asarray(s, dtype=np.float64), 0.0))
        return np.maximum(r - self.band, 0.0) ** 2

    def weight(self, s: np.ndarray) -> np.ndarray:
        r = np.sqrt(np.maximum(np.asarray(s, dtype=np.float64), 0.0))
        return np.where(r > self.band, 1.0 - self.band / np.maximum(r, 1e-300), 0.0)


_KERNELS = {
    "trivial": TrivialKernel,
    "none": TrivialKernel,
    "huber": HuberKernel,
    "geman_mcclure": GemanMcClureKernel,
    "gm": GemanMcClureKernel,
}


def get_kernel(kernel: str | RobustKernel | None, scale: float | None = None) -> RobustKernel:
    """Build a kernel by name, or pass an existing kernel through.

    Args:
        kernel: ``None``/``"trivial"``, ``"huber"``, ``"geman_mcclure"`` (``"gm"``) or a kernel.
        scale: ``delta`` (Huber) or ``sigma`` (Geman-McClure); the kernel's default if None.

    Returns:
        A :class:`RobustKernel`.
    """
    if kernel is None:
        return TrivialKernel()
    if not isinstance(kernel, str):
        if not isinstance(kernel, RobustKernel):
            raise SlamError(f"kernel: expected a name or an object with rho/weight, got {kernel!r}")
        return kernel
    cls = _KERNELS.get(kernel.lower())
    if cls is None:
        raise SlamError(f"kernel: unknown robust kernel {kernel!r}; choose from {sorted(_KERNELS)}")
    if cls is TrivialKernel or scale is None:
        return cls()
    return cls(scale)
