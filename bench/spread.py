"""A bench's figures over several renders: the mean, its spread and every render's value.

One render of a city is one draw of the data: a figure a reader can trust is the mean over
several, with their spread beside it (issue 58). :func:`over_renders` turns the figures of each
render into those of the results file:

* a number that differs between the renders, or one named in ``spread``: the mean over the
  renders that have it (a render's NaN or None is a figure it could not measure), and its values
  in render order under ``per_render[key]``; a ``spread`` key gets ``<key>_std`` beside it, the
  sample standard deviation (0 for one render);
* anything else the renders agree on (a setting, a text, a figure that did not move): its value;
* a non-number that differs: under ``per_render`` only.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

__all__ = ["over_renders"]


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _finite(values: list) -> list[float]:
    return [float(v) for v in values if _number(v) and math.isfinite(v)]


def _plain(v: Any) -> Any:
    """JSON's ``null`` for a NaN or an infinity."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def over_renders(renders: Mapping[str, Mapping[str, Any]], spread: Iterable[str] = ()) -> dict:
    """The figures of ``renders`` (``{render name: {key: value}}``) as one results dict (module
    docstring), keys in the first render's order, then ``per_render``.

    Returns ``{key: mean or shared value, <key>_std: ..., "per_render": {key: [value per
    render]}}``.
    """
    spread = set(spread)
    rows = list(renders.values())
    keys = list(dict.fromkeys(k for row in rows for k in row))
    out: dict[str, Any] = {}
    per_render: dict[str, list] = {}
    for key in keys:
        values = [_plain(row.get(key)) for row in rows]
        numeric = all(v is None or _number(v) for v in values) and any(_number(v) for v in values)
        if numeric and (key in spread or len(set(values)) > 1):
            finite = _finite(values)
            mean = sum(finite) / len(finite) if finite else None
            out[key] = mean
            if key in spread:
                std = math.sqrt(sum((v - mean) ** 2 for v in finite) / max(len(finite) - 1, 1))
                out[f"{key}_std"] = std if finite else None
            per_render[key] = values
        elif all(v == values[0] for v in values):
            out[key] = values[0]
        else:
            per_render[key] = values
    out["per_render"] = per_render
    return out
