"""Benchmark of the simulator: offscreen render time per frame and physics steps per second.

Run ``python -m viotb.envs.tools.bench_render`` to print one JSON object. Software GL has a slow mode in about
one run out of ten, so every figure is the median over ``repeats`` timed batches.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np
from viotb.envs.sim.render import OffscreenRenderer
from viotb.envs.sim.simulation import Simulation
from viotb.models.constants import HOVER_KEYFRAME

RENDER_SIZES = ((320, 240), (640, 480))
"""Image sizes (width, height) timed."""


def _median_ms(fn, repeats: int, frames: int) -> float:
    """Median over ``repeats`` batches of the mean time of ``fn()`` (ms per call)."""
    fn()  # warm-up (context, texture upload)
    batches = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(frames):
            fn()
        batches.append((time.perf_counter() - start) / frames * 1e3)
    return float(np.median(batches))


def bench_render(
    repeats: int = 5, frames: int = 20, physics_steps: int = 5000, scene: str = "textured_room"
) -> dict:
    """Time gray rendering at 320x240 and 640x480, depth at 320x240, and physics stepping.

    Args:
        repeats: Timed batches per figure (the median is reported).
        frames: Frames per batch.
        physics_steps: ``mj_step`` calls per batch.
        scene: Scene name.

    Returns:
        ``{"scene", "gl_backend", "render_gray_ms_320x240", "render_gray_ms_640x480",
        "render_depth_ms_320x240", "physics_steps_per_s", "repeats"}``.

    Raises:
        ValueError: Non-positive counts or an unknown scene.
    """
    if min(repeats, frames, physics_steps) <= 0:
        counts = f"repeats={repeats}, frames={frames}, physics_steps={physics_steps}"
        raise ValueError(f"counts must be positive, got {counts}")
    sim = Simulation("quadrotor", scene)
    sim.reset(HOVER_KEYFRAME)
    result: dict = {"scene": scene, "repeats": repeats}
    for width, height in RENDER_SIZES:
        with OffscreenRenderer(sim.model, width=width, height=height) as renderer:
            result[f"render_gray_ms_{width}x{height}"] = _median_ms(
                lambda r=renderer: r.render_gray(sim.data), repeats, frames
            )
            if (width, height) == RENDER_SIZES[0]:
                result[f"render_depth_ms_{width}x{height}"] = _median_ms(
                    lambda r=renderer: r.render_depth(sim.data), repeats, frames
                )
    result["gl_backend"] = os.environ.get("MUJOCO_GL", "")
    step_ms = _median_ms(lambda: sim.step(n_steps=physics_steps), repeats, 1)
    result["physics_steps_per_s"] = physics_steps / (step_ms * 1e-3)
    return result


def main() -> None:
    """Print the benchmark as one JSON line."""
    print(json.dumps(bench_render()))


if __name__ == "__main__":
    main()
