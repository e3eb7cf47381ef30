"""Tests of envs/tools/jsonout.py: strict JSON with null and a reason for every non-finite number."""

from __future__ import annotations

import json

import numpy as np
from viotb.envs.tools.jsonout import dumps_strict, strict_result


def _strict_loads(text: str) -> dict:
    def refuse(name: str) -> None:
        raise ValueError(f"non-strict JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_values_become_null_with_a_note_at_any_depth():
    result = {
        "rpe_1m_pct": float("nan"),
        "ms": np.float64("inf"),
        "n": np.int64(3),
        "nested": {"x": [1.0, -np.inf]},
        "notes": ["kept"],
    }
    obj = _strict_loads(dumps_strict(result, {"rpe_1m_pct": "path shorter than 1 m"}))
    assert obj["rpe_1m_pct"] is None and obj["ms"] is None and obj["nested"]["x"] == [1.0, None]
    assert obj["n"] == 3
    assert obj["notes"] == [
        "kept",
        "rpe_1m_pct: null (path shorter than 1 m)",
        "ms: null (not a finite number)",
        "nested.x[1]: null (not a finite number)",
    ]


def test_finite_results_get_no_notes():
    assert "notes" not in strict_result({"a": 1.0, "b": True, "c": None, "d": "text"})
