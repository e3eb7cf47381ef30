"""Tests of the package import: BLAS and OpenCV run single-threaded whatever the import order."""

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


def test_opencv_runs_one_thread_in_either_import_order_unless_the_user_says():
    """One OpenCV thread by default (measured faster on 2 cores); OPENCV_FOR_THREADS_NUM overrides it."""
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FOR_THREADS_NUM"}
    for code in (
        "import viotb, cv2; print(cv2.getNumThreads())",
        "import cv2, viotb; print(cv2.getNumThreads())",
    ):
        out = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
        )
        assert out.stdout.strip() == "1", out
    code = "import viotb, cv2; print(cv2.getNumThreads())"
    env["OPENCV_FOR_THREADS_NUM"] = "2"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "2", out
