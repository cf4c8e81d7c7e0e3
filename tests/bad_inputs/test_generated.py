"""Generated values for every numeric option of every command and every numeric config key.

Every ``--option`` is found by introspecting the command's parser; a numeric one declares its
legal values in :data:`DOMAINS` (options that are not numbers are listed in
:data:`NON_NUMERIC`). Hypothesis draws values (NaN, infinities, huge and negative numbers, junk
text); those outside the domain must be refused with exit 2, and no value may give a traceback
or lose data. A new option without a declaration fails :func:`test_every_numeric_option_declares_its_domain`:
new options are covered by default. Every numeric key of every config dataclass (``--set``)
gets the same values: refused with a ``ConfigError`` naming the key, or kept finite.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

import pytest
from harness import (
    COVERED,
    GENERATED,
    Argv,
    Env,
    classify,
    demo_argv,
    export_argv,
    infer_argv,
    localize_argv,
    render_argv,
    stub_work,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from geoseg_cli.cli import COMMANDS, build_parser

# Each option of each command: (predicate of the legal values, example legal value). Values the
# predicate rejects must be refused with exit 2; options missing here fail the coverage test.
Domain = Callable[[object], bool]


def _positive(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def _non_negative(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v >= 0


def _int_at_least(low: int) -> Domain:
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= low


def _unit(v) -> bool:
    return isinstance(v, int | float) and math.isfinite(v) and 0 <= v <= 1


DOMAINS: dict[tuple[str, str], Domain] = {
    ("render", "--frames"): _int_at_least(1),
    ("render", "--fps"): lambda v: _positive(v) and 0.01 <= v <= 1000,
    ("render", "--seed"): lambda v: _int_at_least(0)(v) and v < 2**63,
    ("render", "--workers"): lambda v: _int_at_least(1)(v) and v <= 64,
    ("demo", "--frames"): _int_at_least(1),
    ("demo", "--drive-m"): lambda v: _non_negative(v) and v <= 5000,
    ("demo", "--fps"): lambda v: _positive(v) and 0.01 <= v <= 1000,
    ("demo", "--seed"): lambda v: _int_at_least(0)(v) and v < 2**63,
    ("export", "--seed"): lambda v: _int_at_least(0)(v) and v < 2**63,
    ("export", "--height"): lambda v: _int_at_least(1)(v) and v <= 8192,
    ("export", "--width"): lambda v: _int_at_least(1)(v) and v <= 8192,
    ("infer", "--alpha"): _unit,
    ("localize", "--k"): _int_at_least(1),
    ("localize", "--radius"): _positive,
    ("localize", "--gps-sigma"): _positive,
    ("localize", "--distance-rel-sigma"): _positive,
    ("localize", "--appearance-weight"): _non_negative,
    ("localize", "--position-k"): _int_at_least(1),
    ("localize", "--min-agreeing-rays"): _int_at_least(1),
    ("localize", "--focal"): _positive,
    ("localize", "--step-m"): _non_negative,
    ("localize", "--appearance-scale"): _positive,
}
# Options that are not numbers: paths, names, free-form overrides, flags, choices (argparse
# checks choices); the tables above and the library tests cover their bad values.
NON_NUMERIC = {
    "render": {
        "--config",
        "--out",
        "--condition",
        "--rig",
        "--size",
        "--set",
        "--gis",
        "--force",
        "--overwrite",
    },
    "demo": {"--out", "--config", "--size", "--conditions", "--set", "--force", "--overwrite"},
    "train": {"--config", "--resume", "--overwrite", "--device", "--out", "--set"},
    "export": {"--checkpoint", "--model", "--out", "--overwrite", "--config", "--static"},
    "infer": {
        "--model",
        "--out",
        "--device",
        "--probabilities",
        "--overwrite",
        "--colour-transfer",
        "--colour-means-only",
    },
    "localize": {
        "--base",
        "--gps",
        "--embedding",
        "--relative-pose",
        "--network-size",
        "--model",
        "--reloc-head",
        "--relpose-head",
        "--no-rerank",
        "--structure",
        "--pool",
        "--features",
        "--sequence",
        "--device",
        "--no-cache",
        "--out",
        "--overwrite",
    },
    "base": set(),  # its options belong to its action (base build): the table covers them
    "slam": set(),  # its options belong to its action (slam run): the table covers them
    "bench": set(),
}
# The context each numeric option needs to be used at all (other options it depends on).
CONTEXT: dict[tuple[str, str], list[str]] = {
    ("localize", "--radius"): ["--gps", "{e.inputs}/gps.csv"],
    ("localize", "--gps-sigma"): ["--sequence", "filter", "--gps", "{e.inputs}/gps.csv"],
    ("localize", "--step-m"): ["--sequence", "filter"],
    ("localize", "--appearance-scale"): ["--sequence", "filter"],
    ("localize", "--focal"): [],
}
BASE_ARGV: dict[str, Argv] = {
    "render": render_argv(),
    "demo": demo_argv(),
    "export": export_argv("--model", "naive_cnn", "--out", "{e.root}/outs/gen.onnx"),
    "infer": infer_argv(),
    "localize": localize_argv(),
}


def _options(command: str) -> dict[str, argparse.Action]:
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {
        s: a
        for a in sub.choices[command]._actions
        for s in a.option_strings
        if s.startswith("--") and s != "--help"
    }


@pytest.mark.parametrize("command", COVERED)
def test_every_numeric_option_declares_its_domain(command: str) -> None:
    missing = [
        name
        for name in _options(command)
        if (command, name) not in DOMAINS and name not in NON_NUMERIC[command]
    ]
    assert not missing, f"declare the legal values of {command} {missing} in DOMAINS"
    assert set(COMMANDS) - set(COVERED) <= {"slam-eval"}, "add the new command's cases"


VALUES = st.one_of(
    st.sampled_from([0, -1, 1, 2, 2**63, -(2**63), 0.5, 1e-160, 1e308]),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(min_value=-(2**65), max_value=2**65),
    st.sampled_from(["nan", "inf", "-inf", "", "abc", "1e999", "0x10", "1_000"]),
)


@pytest.mark.parametrize(
    "key", sorted(k for k in DOMAINS if k[0] in BASE_ARGV), ids=lambda k: f"{k[0]}{k[1]}"
)
@settings(
    max_examples=6,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(value=VALUES)
def test_generated_option_values(key, value, env: Env, monkeypatch, capsys) -> None:
    command, option = key
    stub_work(monkeypatch)
    parsed = _parse_like_argparse(_options(command)[option], value)
    argv = BASE_ARGV[command](env)
    context = [x.format(e=env) for x in CONTEXT.get(key, [])]
    outcome, detail = classify([*argv, *context, option, str(value)], env, capsys, "")
    assert outcome in ("A", "ok"), f"{command} {option} {value!r}: {outcome}: {detail}"
    legal = parsed is not None and DOMAINS[key](parsed)
    if not legal:
        GENERATED[command]["A" if outcome == "A" else "C"] += 1
        assert outcome == "A", f"{command} {option} {value!r} was accepted"


def _parse_like_argparse(action: argparse.Action, value) -> object:
    """What argparse would pass the command for ``str(value)`` (None: argparse refuses it)."""
    try:
        return action.type(str(value)) if action.type is not None else str(value)
    except (TypeError, ValueError):
        return None


# ============================================================================ config keys

CONFIG_CLASSES = {
    "train seg": "training.seg:SegConfig",
    "train normals": "training.normals:NormalsConfig",
    "train naive": "training.naive:NaiveConfig",
    "train dirichlet": "training.dirichlet_fit:DirichletConfig",
    "train reloc": "training.reloc:RelocConfig",
    "train relpose": "training.relpose:RelPoseConfig",
    "render world": "geoseg.synth.world:WorldConfig",
    "render gis": "geoseg.synth.export:GisConfig",
}


def _numeric_keys(cls, prefix: str = "") -> list[str]:
    """Dotted names of every int/float leaf of a config dataclass (``--set`` keys)."""
    import dataclasses
    import typing

    keys = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            keys += _numeric_keys(hint, f"{prefix}{f.name}.")
        elif hint in (int, float) or set(typing.get_args(hint)) & {int, float}:
            keys.append(prefix + f.name)
    return keys


def _config_class(spec: str):
    import importlib

    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


CONFIG_KEYS = [
    (k, key) for k, spec in CONFIG_CLASSES.items() for key in _numeric_keys(_config_class(spec))
]


@pytest.mark.parametrize("key", CONFIG_KEYS, ids=[f"{a}:{b}" for a, b in CONFIG_KEYS])
@settings(max_examples=6, deadline=None, derandomize=True, database=None)
@given(value=VALUES)
def test_generated_config_values(key, value) -> None:
    """Every numeric key of every config: a generated value is refused with a ConfigError naming
    the key, or accepted as a finite number; never a traceback, never a NaN kept."""
    from geoseg.config import load_config
    from geoseg.errors import GeosegError

    owner, dotted = key
    cls = _config_class(CONFIG_CLASSES[owner])
    name = owner.split()[0]
    try:
        cfg = load_config(cls, None, overrides=[f"{dotted}={value}"])
    except GeosegError as err:
        GENERATED[name]["A"] += 1
        assert dotted.split(".")[-1] in str(err) or "section" in str(err), str(err)
        return
    except Exception as exc:  # noqa: BLE001 - any other type is a traceback for the user
        GENERATED[name]["B"] += 1
        raise AssertionError(f"{owner} {dotted}={value!r}: {type(exc).__name__}: {exc}") from exc
    node = cfg
    for part in dotted.split("."):
        node = getattr(node, part)
    finite = node is None or (isinstance(node, int | float) and math.isfinite(node))
    if not finite:
        GENERATED[name]["C"] += 1
    assert finite, f"{owner} {dotted}={value!r} kept as {node!r}"
