"""The package error and the guards used at public boundaries.

Every bad input that reaches a public function is reported by :class:`GeosegError` (a
``ValueError``) with a message that names the argument, what was expected and what came; never by
an ``assert`` or a traceback from deep inside NumPy or torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


class GeosegError(ValueError):
    """A bad input, configuration or file, with a message that names the problem."""


class ConfigError(GeosegError):
    """A configuration key that does not exist, a wrong type or an out-of-range value."""


class OutputError(GeosegError, OSError):
    """A file or folder that cannot be written (full disk, read-only folder, a file in the way).

    Both a :class:`GeosegError` (commands print its message, no traceback) and an
    :class:`OSError` (code that tolerates failed writes, e.g. of a cache, keeps catching it).
    ``errno`` is the underlying error's number when there is one.
    """

    def __init__(self, message: str, *, errno: int | None = None) -> None:
        if errno is None:
            OSError.__init__(self, message)
        else:
            OSError.__init__(self, errno, message)
        self.message = message

    def __str__(self) -> str:
        return self.message

    def __reduce__(self):  # picklable across worker processes
        return (_output_error, (self.message, self.errno))


def _output_error(message: str, errno: int | None) -> OutputError:
    return OutputError(message, errno=errno)


def _shape_of(value: Any) -> tuple[int, ...] | None:
    shape = getattr(value, "shape", None)
    return None if shape is None else tuple(int(s) for s in shape)


def check_shape(name: str, value: Any, expected: Sequence[int | None]) -> None:
    """Raise unless ``value`` has ``len(expected)`` dimensions matching ``expected``.

    Args:
        name: the argument's name, used in the message.
        value: a NumPy array or torch tensor.
        expected: one entry per dimension; ``None`` accepts any size, e.g. ``(None, 3)`` for
            ``(N, 3)``.
    """
    shape = _shape_of(value)
    if shape is None:
        raise GeosegError(
            f"{name}: expected an array of shape {_fmt(expected)}, got {type(value).__name__}"
        )
    if len(shape) != len(expected) or any(
        e is not None and e != s for e, s in zip(expected, shape)
    ):
        raise GeosegError(f"{name}: expected shape {_fmt(expected)}, got {shape}")


def check_finite(name: str, value: Any) -> None:
    """Raise if ``value`` (array or tensor) holds NaN or infinite entries."""
    if hasattr(value, "detach"):  # torch tensor: stay on its device
        import torch

        finite = bool(torch.isfinite(value).all()) if value.is_floating_point() else True
    else:
        arr = np.asarray(value)
        finite = bool(np.isfinite(arr).all()) if np.issubdtype(arr.dtype, np.inexact) else True
    if not finite:
        raise GeosegError(f"{name}: contains NaN or infinite values")


def check_positive(name: str, value: float | int, *, strict: bool = True) -> None:
    """Raise unless ``value`` is a number ``> 0`` (``>= 0`` when ``strict`` is False)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise GeosegError(f"{name}: expected a number, got {type(value).__name__}")
    if not np.isfinite(value) or (value <= 0 if strict else value < 0):
        bound = "> 0" if strict else ">= 0"
        raise GeosegError(f"{name}: expected a finite number {bound}, got {value}")


def _fmt(expected: Sequence[int | None]) -> str:
    return "(" + ", ".join("*" if e is None else str(e) for e in expected) + ")"
