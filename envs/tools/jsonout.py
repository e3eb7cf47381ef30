"""Strict JSON for every ``--json`` output: no ``NaN``/``Infinity``, ``null`` with the reason in ``notes``.

Python's :mod:`json` writes ``NaN`` and ``Infinity`` by default, which strict parsers (``jq``, browsers, Go)
reject. :func:`strict_result` replaces every non-finite float (at any depth) with ``None`` and adds one line
per replaced key to the result's ``notes`` list, keeping any notes the command already wrote; the reasons a
command knows best (``"rpe_1m_pct": "path shorter than 1 m"``) are passed in and win over the generic one.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping

import numpy as np


def _plain(value: object, path: str, found: list[str]) -> object:
    """``value`` with numpy scalars made Python and non-finite floats made None (their paths in ``found``)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v, f"{path}.{k}" if path else str(k), found) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{path}[{i}]", found) for i, v in enumerate(value)]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), path, found)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        number = float(value)
        if math.isfinite(number):
            return number
        found.append(path)
        return None
    return value


def plain_json(obj: object) -> object:
    """``obj`` with numpy scalars and arrays made plain Python and every non-finite float made None."""
    return _plain(obj, "", [])


def strict_result(result: Mapping, reasons: Mapping[str, str] | None = None) -> dict:
    """``result`` made strict-JSON-safe, with a ``notes`` entry for every value that became ``null``.

    Args:
        result: A command's result (nested dicts, lists, numbers, numpy scalars and arrays allowed).
        reasons: Known reasons per top-level key (used instead of the generic "not a finite number").

    Returns:
        A new dict; ``notes`` (a list of strings) is present when any value was replaced or a note existed.
    """
    reasons = dict(reasons or {})
    found: list[str] = []
    clean = _plain(dict(result), "", found)
    notes = [str(n) for n in clean.pop("notes", None) or []]
    for path in found:
        why = reasons.get(path.split(".")[0].split("[")[0], "not a finite number")
        notes.append(f"{path}: null ({why})")
    if notes:
        clean["notes"] = notes
    return clean


def dumps_strict(result: Mapping, reasons: Mapping[str, str] | None = None, indent: int | None = None) -> str:
    """One strict JSON document (``allow_nan=False``) of :func:`strict_result`."""
    return json.dumps(strict_result(result, reasons), indent=indent, allow_nan=False)
