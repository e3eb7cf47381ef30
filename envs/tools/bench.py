"""``viotb bench``: the speed figures the issues ask for, as one JSON object.

Figures are medians over repeats (software GL has a slow mode about one run in ten) and real-time factors
(simulated seconds per wall second), so they read as ratios on a noisy machine. Sections:

- ``render``: render ms/frame at 320x240 and 640x480, physics steps/s (:mod:`viotb.envs.tools.bench_render`);
- ``record``: real-time factor of ``viotb record figure8`` (320x240, 20 Hz camera, 200 Hz IMU);
- ``estimator``: MSCKF median / p99 ms per frame (KLT tracking + update) on that recording, and the
  ``window`` optimizer's (``window_*`` keys);
- ``closed_loop``: ``realtime_factor`` of ``viotb fly fly-hover`` with the image front end and in sim mode,
  and ``cpu_realtime_factor`` (simulated seconds per CPU second of the process: stable on a shared machine);
- ``gym``: ``viotb/Hover-v0`` env steps/s and real-time factor per estimator set-up, one env and a vector of
  two (:mod:`viotb.envs.tools.bench_gym`, with its CPU-time figures), ``seconds`` of simulated time per
  measurement.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

ProgressFn = Callable[[float, float], None]

SECTIONS = ("render", "record", "estimator", "closed_loop", "gym")


def run_bench(
    sections: tuple[str, ...] = SECTIONS,
    seconds: float = 10.0,
    repeats: int = 3,
    progress: ProgressFn | None = None,
) -> dict:
    """Run the selected benchmark sections.

    Args:
        sections: Subset of :data:`SECTIONS`.
        seconds: Simulated duration of the record and closed-loop runs (s).
        repeats: Repeats of each timed run (medians are reported).
        progress: Optional ``(done, total)`` callback over sections.

    Raises:
        ValueError: Unknown section.
    """
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        raise ValueError(f"unknown bench sections {sorted(unknown)}; allowed: {list(SECTIONS)}")
    out: dict = {"seconds": seconds, "repeats": repeats}
    done = 0
    with tempfile.TemporaryDirectory() as tmp:
        rec_dir = Path(tmp) / "figure8"
        if "render" in sections:
            from viotb.envs.tools.bench_render import bench_render

            out["render"] = bench_render(repeats=max(repeats, 3))
        done += 1
        if progress:
            progress(done, len(SECTIONS))
        if "record" in sections or "estimator" in sections:
            from viotb.envs.data.record import record_scenario

            rtfs = []
            for k in range(repeats if "record" in sections else 1):
                rec = record_scenario("figure8", rec_dir, seed=k, seconds=seconds, overwrite=True)
                rtfs.append(rec["realtime_factor"])
            out["record"] = {"scenario": "figure8", "realtime_factor_median": float(np.median(rtfs)), **rec}
        done += 1
        if progress:
            progress(done, len(SECTIONS))
        if "estimator" in sections:
            from viotb.envs.data.evaluate import EvalOptions, evaluate_dataset

            keys = ("ms_per_frame_median", "ms_per_frame_p99", "frames", "ate_posyaw_m")
            ev = evaluate_dataset(rec_dir, Path(tmp) / "eval", EvalOptions("msckf", "klt"))
            out["estimator"] = {k: ev.get(k) for k in keys}
            ev = evaluate_dataset(rec_dir, Path(tmp) / "eval_window", EvalOptions("window", "klt"))
            out["estimator"].update({f"window_{k}": ev.get(k) for k in keys})
        done += 1
        if progress:
            progress(done, len(SECTIONS))
        if "closed_loop" in sections:
            from viotb.envs.run.fly import fly

            runs: dict[str, list[dict]] = {"klt": [], "sim": []}
            for k in range(repeats):  # the front ends alternate: a change of load hits both alike
                for frontend, metrics in runs.items():
                    metrics.append(fly("fly-hover", "msckf", seconds, k, frontend)[0])
            cl = {}
            for frontend, metrics in runs.items():
                for key in ("realtime_factor", "cpu_realtime_factor"):
                    cl[f"{key}_{frontend}_median"] = float(np.median([m[key] for m in metrics]))
            out["closed_loop"] = cl
        done += 1
        if progress:
            progress(done, len(SECTIONS))
        if "gym" in sections:
            from viotb.envs.tools.bench_gym import SETUPS, bench

            out["gym"] = {name: bench(name, 0, 2, repeats, seconds=seconds) for name in SETUPS}
        done += 1
        if progress:
            progress(done, len(SECTIONS))
    return out
