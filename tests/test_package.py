"""Tests of the package import: BLAS runs single-threaded even when numpy was imported first."""

from __future__ import annotations

import os
import subprocess
import sys


def test_blas_is_single_threaded_whatever_the_import_order():
    """A threaded BLAS changes the summation order, and closed-loop flights amplify the round-off."""
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    code = (
        "import numpy, viotb\n"
        "from threadpoolctl import threadpool_info\n"
        "print(max([i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'] or [1]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1", out
