"""Where the tests find the shared real data: ``shared/`` beside the repository (CI), else /work/shared."""

from __future__ import annotations

from pathlib import Path

_BESIDE = Path(__file__).resolve().parents[2] / "shared"
SHARED = _BESIDE if _BESIDE.is_dir() else Path("/work/shared")
EUROC_MICRO = SHARED / "data" / "euroc_v1_01_micro"
"""The real EuRoC micro set (V1_01, stationary, 95 frames): ``EUROC_MICRO / "mav0"``."""
