"""Compiled kernels: one place that decides how numba compiles the estimator's hot loops.

Issue #15 allows compiled kernels only where a measured hot path gains at least 2x, with on-disk caching
and without slowing ``viotb --help``. So: numba is imported here and only by the kernel modules that
use :func:`njit`, which the estimators import (never the CLI: ``tests/test_cli_import.py``); every kernel
is compiled once per machine and cached beside its source (``__pycache__``), and strict IEEE arithmetic
is kept (no ``fastmath``), so a kernel computes what its numpy reference computes up to the order of
its sums. Each kernel's numpy reference stays in the code base as the independent implementation its
tests compare against.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numba

F = TypeVar("F", bound=Callable)


def njit(fn: F) -> F:
    """``numba.njit`` with on-disk caching, the GIL released and numpy's error model (NaN, no raise).

    Args:
        fn: A function of numpy arrays and scalars in numba's nopython subset.

    Returns:
        The compiled function (compiled lazily on first call, then loaded from the cache).
    """
    return numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
