"""Per-tick helpers on plain floats (simulation, sensors, envs): an exact finiteness test, a 3-vector norm."""

from __future__ import annotations

import math

import numpy as np


def all_finite(values: list[float]) -> bool:
    """Whether every value is finite (no NaN, no infinity).

    One sum answers for the common case (finite exactly when every entry is, unless finite entries overflow
    it); only a sum that is not finite is checked entry by entry, so the answer is always exact. About a
    tenth of ``np.isfinite(a).all()`` on a short vector's ``tolist()``.

    Args:
        values: Plain floats (a ``tolist()`` of a vector).
    """
    return math.isfinite(sum(values)) or all(map(math.isfinite, values))


def norm3(v: np.ndarray) -> float:
    """``float(np.linalg.norm(v))`` of a real vector (the same ``sqrt(v.dot(v))``), without its overhead.

    Args:
        v: A 1-D float array, e.g. a position difference (m), shape (3,).
    """
    return math.sqrt(v.dot(v))
