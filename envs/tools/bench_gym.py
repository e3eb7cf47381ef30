"""Throughput of the Gymnasium envs: env steps per second and real-time factor, printed as JSON.

``python -m viotb.envs.tools.bench_gym [--steps N] [--num-envs K] [--repeats R]`` measures ``viotb/Hover-v0``
with the ``position`` action (the SE(3) controller holds the point, so episodes do not end early) for three
estimator set-ups (``ground-truth``, ``msckf`` + ``sim`` features, ``msckf`` + ``klt`` on rendered images),
each as a single env and as a vector env of K copies (``--vector async``, the default: an
``AsyncVectorEnv``, one worker process per copy, so K copies on K free cores should give close to K times the
single env's steps/s, reported as ``vector_speedup``; ``--vector sync``: a ``SyncVectorEnv`` in this
process). The real-time factor is ``env steps/s * ctrl_dt`` (simulated seconds per wall second, summed over
the vector's copies). Worker start-up, reset and a few warm-up steps are excluded; the median over repeats is
reported (DESIGN.md: about one run in ten lands in a slower mode).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from functools import partial

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium
import numpy as np
import viotb.envs  # noqa: F401  (registers the ids)

VECTOR_MODES = ("async", "sync")
"""Vector env kinds: ``gymnasium.vector.AsyncVectorEnv`` / ``SyncVectorEnv``."""

SETUPS = {
    "ground-truth": {"estimator": "ground-truth", "frontend": "sim"},
    "msckf+sim": {"estimator": "msckf", "frontend": "sim"},
    "msckf+klt": {"estimator": "msckf", "frontend": "klt"},
}
"""Set-up name -> env keyword arguments."""


def _make_hover(kwargs: dict) -> gymnasium.Env:
    """``viotb/Hover-v0`` with ``kwargs``.

    Module level, so a spawned worker imports this module (and with it the ids' registration) when it
    unpickles the factory.
    """
    return gymnasium.make("viotb/Hover-v0", **kwargs)


WARMUP_STEPS = 5
"""Untimed steps after the reset (a fresh worker's first steps pay one-off costs: lazy imports, caches)."""


def _steps_per_s(env: gymnasium.Env, n_steps: int, n_copies: int, seed: int) -> float:
    """Env steps per wall second over ``n_steps`` calls to ``step`` (after a reset and warm-up, not timed)."""
    env.reset(seed=seed)
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    for _ in range(WARMUP_STEPS):
        env.step(action)
    t0 = time.perf_counter()
    for _ in range(n_steps):
        env.step(action)
    return n_copies * n_steps / (time.perf_counter() - t0)


def bench(
    setup: str,
    n_steps: int,
    num_envs: int,
    repeats: int,
    seconds: float | None = None,
    vector: str = "async",
) -> dict:
    """Median env steps/s and real-time factor of one set-up, single env and vector env.

    Args:
        setup: A key of :data:`SETUPS`.
        n_steps: Env steps per measurement (ignored when ``seconds`` is given).
        num_envs: Copies in the vector env.
        repeats: Measurements (the median is reported).
        seconds: Simulated seconds per measurement instead of ``n_steps`` (``seconds / ctrl_dt`` steps, at
            most one episode).
        vector: A key of :data:`VECTOR_MODES`. ``async`` workers are spawned (a fresh interpreter: no GL
            context or thread pool inherited from this process; the package limits BLAS to one thread).

    Raises:
        ValueError: Unknown ``vector``.
    """
    if vector not in VECTOR_MODES:
        raise ValueError(f"unknown vector mode {vector!r}; allowed: {', '.join(map(repr, VECTOR_MODES))}")
    kwargs = {"action_type": "position", **SETUPS[setup]}
    single = gymnasium.make("viotb/Hover-v0", **kwargs)
    ctrl_dt = single.unwrapped.dt
    if seconds is not None:
        # Within one episode (the TimeLimit truncates at max_episode_steps).
        n_steps = max(1, min(round(seconds / ctrl_dt), single.spec.max_episode_steps or 10**9))
    rates = [_steps_per_s(single, n_steps, 1, seed) for seed in range(repeats)]
    single.close()
    fns = [partial(_make_hover, kwargs) for _ in range(num_envs)]
    if vector == "async":
        vec = gymnasium.vector.AsyncVectorEnv(fns, context="spawn")
    else:
        vec = gymnasium.vector.SyncVectorEnv(fns)
    vec_rates = [_steps_per_s(vec, n_steps, num_envs, seed) for seed in range(repeats)]
    vec.close()
    single_rate, vec_rate = float(np.median(rates)), float(np.median(vec_rates))
    return {
        "ctrl_dt_s": ctrl_dt,
        "single_steps_per_s": single_rate,
        "single_realtime_factor": single_rate * ctrl_dt,
        "vector_mode": vector,
        "vector_num_envs": num_envs,
        "vector_steps_per_s": vec_rate,
        "vector_realtime_factor": vec_rate * ctrl_dt,
        "vector_speedup": vec_rate / single_rate,
    }


def main(argv: list[str] | None = None) -> dict:
    """Parse arguments, run every set-up, print one JSON object (last line) and return it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="env steps per measurement")
    parser.add_argument("--num-envs", type=int, default=2, help="copies in the vector env")
    parser.add_argument("--vector", default="async", choices=VECTOR_MODES, help="vector env kind")
    parser.add_argument("--repeats", type=int, default=3, help="measurements per set-up (median reported)")
    parser.add_argument(
        "--setups", nargs="+", default=list(SETUPS), choices=list(SETUPS), help="set-ups to measure"
    )
    args = parser.parse_args(argv)
    for name in ("steps", "num_envs", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    result = {
        setup: bench(setup, args.steps, args.num_envs, args.repeats, vector=args.vector)
        for setup in args.setups
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
