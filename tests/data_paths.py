"""Where the tests find the shared real data: ``shared/`` beside the repository (CI), else /work/shared."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

_BESIDE = Path(__file__).resolve().parents[2] / "shared"
SHARED = _BESIDE if _BESIDE.is_dir() else Path("/work/shared")
EUROC_MICRO = SHARED / "data" / "euroc_v1_01_micro"
"""The real EuRoC micro set (V1_01, stationary, 95 frames): ``EUROC_MICRO / "mav0"``."""

REPO = Path(__file__).resolve().parents[1]
"""The repository root (``benchmarks/``, ``examples/`` beside the package rooms)."""


def load_repo_script(relative_path: str) -> ModuleType:
    """Import a script of the repository (e.g. ``benchmarks/klt_track_error.py``) as a module."""
    path = REPO / relative_path
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
