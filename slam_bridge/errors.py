"""The error raised by ``slam_bridge`` for bad inputs and infeasible problems."""

from __future__ import annotations

from geoseg.errors import GeosegError

__all__ = ["SlamError"]


class SlamError(GeosegError):
    """A bad input or an ill-posed problem in ``slam_bridge`` (a ``ValueError``).

    Raised for NaN/infinite observations, points behind every camera, empty windows, singular
    systems that damping cannot fix, and the like, with a message naming the problem.
    """
