"""Model registry: ``get_model(name, **cfg)`` over the keyword-only builders.

Builders are looked up lazily (their module is imported on first use), so that listing names or
building one model never imports the others, and heads whose module is not written yet do not
break the registry.
"""

from __future__ import annotations

import importlib
import inspect
import logging
from collections.abc import Callable
from typing import Any

from torch import nn

from geoseg.errors import ConfigError, GeosegError

logger = logging.getLogger(__name__)

# name -> (module, builder function)
MODELS: dict[str, tuple[str, str]] = {
    "enet": ("geoseg.models.enet", "enet"),
    "joint": ("geoseg.models.joint", "joint"),
    "naive_cnn": ("geoseg.models.naive_cnn", "naive_cnn"),
    "reloc": ("geoseg.models.reloc", "reloc_head"),
    "relpose": ("geoseg.models.relpose", "relpose_head"),
}


def list_models() -> list[str]:
    """The registered model names."""
    return list(MODELS)


def get_builder(name: str) -> Callable[..., nn.Module]:
    """The builder function registered under ``name``.

    Raises:
        GeosegError: unknown name (the message lists the known ones) or a builder whose module
            is not available.
    """
    if name not in MODELS:
        raise GeosegError(f"model: unknown model {name!r}; known models: {', '.join(MODELS)}")
    module_name, attr = MODELS[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name == module_name:
            raise GeosegError(f"model: {name!r} is not available ({module_name} missing)") from None
        raise
    return getattr(module, attr)


# integer options that may be 0 (every other integer option counts something: >= 1)
_NON_NEGATIVE = ("correlation_radius", "table_seed")


def check_model_config(name: str, cfg: dict) -> Any:
    """Check ``cfg`` against the options of the builder registered under ``name`` (known
    keywords; integers >= 1, or >= 0 for the few that may be 0; booleans), without building;
    returns the builder.

    Raises:
        GeosegError: unknown name.
        ConfigError: a keyword the builder does not take, or a value of the wrong type.
    """
    builder = get_builder(name)
    params = inspect.signature(builder).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        unknown = sorted(set(cfg) - set(params))
        if unknown:
            raise ConfigError(
                f"model {name!r}: unknown option(s) {unknown}; accepted: {sorted(params)}"
            )
    for key, value in cfg.items():  # the builders' annotated option types, strictly
        kind = str(params[key].annotation) if key in params else ""
        if kind in ("int", "<class 'int'>"):
            low = 0 if key in _NON_NEGATIVE else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(
                    f"model {name!r}: {key}: expected an integer >= {low}, got {value!r}"
                )
        if kind in ("bool", "<class 'bool'>") and not isinstance(value, bool):
            raise ConfigError(f"model {name!r}: {key}: expected true/false, got {value!r}")
    return builder


def get_model(name: str, **cfg) -> nn.Module:
    """Build the model registered under ``name`` with keyword configuration ``cfg``.

    Args:
        name: one of :func:`list_models` (``enet``, ``joint``, ``naive_cnn``, ``reloc``,
            ``relpose``).
        **cfg: the builder's keyword arguments (e.g. ``num_classes=8``).

    Raises:
        GeosegError: unknown name.
        ConfigError: a keyword the builder does not take.
    """
    builder = check_model_config(name, cfg)
    try:
        return builder(**cfg)
    except (TypeError, ValueError, RuntimeError) as err:
        if isinstance(err, GeosegError):
            raise
        raise ConfigError(f"model {name!r}: options {cfg} rejected ({err})") from None
