"""Typed configurations: dataclasses with defaults next to the code, YAML files that override them.

A component declares its configuration as a (possibly nested) dataclass. :func:`load_config`
builds one from a YAML file, a mapping and ``key.sub=value`` overrides, and rejects unknown keys
and wrong types with a :class:`~geoseg.errors.ConfigError` that names the key. No config framework
lives inside the library: this module is the whole mechanism.

Example::

    @dataclass
    class TrainConfig:
        epochs: int = 10
        lr: float = 5e-4

    cfg = load_config(TrainConfig, "configs/seg.yaml", overrides=["epochs=2"])
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml

from geoseg.errors import ConfigError

T = TypeVar("T")

# The repository's presets (configs/*.yaml next to the package in a source checkout).
REPO_CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def default_config_file(name: str) -> Path | None:
    """The preset ``configs/<name>`` of the working directory, else of the geoseg source tree.

    Commands use it when no ``--config`` is given, so that running them from another folder
    uses the same presets as from the repository root (None: no such preset anywhere).
    """
    for folder in (Path("configs"), REPO_CONFIGS):
        if (folder / name).is_file():
            return folder / name
    return None


def check_range(
    key: str,
    value: float | int | None,
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    high_open: bool = False,
) -> None:
    """Raise :class:`ConfigError` unless ``value`` (None passes) lies in the interval
    ``[low, high]`` (an end ``None`` is unbounded; ``*_open`` excludes that end)."""
    if value is None:
        return
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        left = "-inf" if low is None else f"{low:g}"
        right = "inf" if high is None else f"{high:g}"
        interval = f"{'(' if low_open or low is None else '['}{left}, {right}{')' if high_open or high is None else ']'}"
        raise ConfigError(f"{key}: expected a number in {interval}, got {value!r}")


def load_config(
    cls: type[T],
    source: str | Path | Mapping[str, Any] | None = None,
    *,
    overrides: Sequence[str] | Mapping[str, Any] = (),
) -> T:
    """Build a ``cls`` instance from defaults, a YAML file or mapping, then overrides.

    Args:
        cls: a dataclass type; nested dataclass fields are filled recursively.
        source: a YAML file path, a mapping, or None for the defaults.
        overrides: ``["a.b=3", ...]`` strings (values parsed as YAML) or a flat mapping
            ``{"a.b": 3}``, applied after ``source``.

    Raises:
        ConfigError: unreadable file, unknown key, wrong type.
    """
    data: dict[str, Any] = {}
    if isinstance(source, str | Path):
        data = read_yaml(source)
    elif source is not None:
        data = dict(source)
    for dotted, value in _parse_overrides(overrides):
        _set_dotted(data, dotted, value)
    return from_dict(cls, data)


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping (an empty file is an empty mapping)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"config file {path} is not valid YAML: {err}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"config file {path}: expected a mapping at top level, got {type(data).__name__}"
        )
    return data


def from_dict(cls: type[T], data: Mapping[str, Any], *, where: str = "") -> T:
    """Build a dataclass from a mapping, checking keys and types recursively."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where or cls.__name__}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(
            f"unknown config key(s) {', '.join(prefix + k for k in unknown)} for {cls.__name__}; "
            f"known: {', '.join(sorted(fields))}"
        )
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        key = f"{where}.{name}" if where else name
        kwargs[name] = _coerce(hints[name], value, key)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as err:
        if isinstance(err, ConfigError):
            raise
        raise ConfigError(f"{where or cls.__name__}: {err}") from None


def to_dict(config: Any) -> dict[str, Any]:
    """The plain-data form of a config dataclass (tuples become lists, paths strings: YAML/JSON)."""

    def plain(value: Any) -> Any:
        if isinstance(value, tuple | list):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, Path):
            return str(value)
        return value

    return plain(dataclasses.asdict(config))


def save_config(config: Any, path: str | Path) -> None:
    """Write a config dataclass as YAML (atomically)."""
    from geoseg.atomic import atomic_write

    atomic_write(path, yaml.safe_dump(to_dict(config), sort_keys=False))


def _coerce(hint: Any, value: Any, key: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if hint is Any:
        return _finite_plain(value, key)
    if dataclasses.is_dataclass(hint):
        return from_dict(hint, value if value is not None else {}, where=key)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(arg, value, key)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(f"{key}: {value!r} matches none of {hint}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{key}: expected one of {list(args)}, got {value!r}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list, got {type(value).__name__} {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{key}: expected {len(args)} items, got {len(value)}")
            return tuple(_coerce(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        items = [_coerce(item, v, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping, got {type(value).__name__}")
        return {k: _finite_plain(v, f"{key}.{k}") for k, v in value.items()}
    if hint is float:
        number = value
        if isinstance(value, str):
            # PyYAML reads "1e-3" (no dot) as a string: accept numeric strings for floats.
            try:
                number = float(value)
            except ValueError:
                pass
        if isinstance(number, bool) or not isinstance(number, int | float):
            raise ConfigError(f"{key}: expected a number, got {type(value).__name__} {value!r}")
        if not math.isfinite(number):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        return float(number)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true/false, got {type(value).__name__} {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {type(value).__name__} {value!r}")
        return value
    if hint is Path:
        if not isinstance(value, str | Path):
            raise ConfigError(f"{key}: expected a path, got {type(value).__name__} {value!r}")
        return Path(value)
    return value


def _finite_plain(value: Any, key: str) -> Any:
    """``value`` (free-form: a dict, list or scalar) after checking that it holds no NaN or
    infinite number; the error names the nested key (``data.synth.frames``)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{key}: expected a finite number, got {value!r}")
    if isinstance(value, Mapping):
        for k, v in value.items():
            _finite_plain(v, f"{key}.{k}")
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            _finite_plain(v, f"{key}[{i}]")
    return value


def _parse_overrides(overrides: Sequence[str] | Mapping[str, Any]) -> list[tuple[str, Any]]:
    if isinstance(overrides, Mapping):
        return list(overrides.items())
    pairs = []
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r}: expected key=value")
        dotted, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = raw
        pairs.append((dotted.strip(), value))
    return pairs


def _set_dotted(data: dict[str, Any], dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = data
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"override {dotted}: {part} is not a section")
        node = child
    node[parts[-1]] = value
