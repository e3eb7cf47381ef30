"""Shared pytest setup: single-threaded BLAS (imported before numpy) and offscreen GL by EGL."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
