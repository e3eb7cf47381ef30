"""Throughput of the Gymnasium envs: env steps per second and real-time factor, printed as JSON.

``python -m viotb.envs.tools.bench_gym [--steps N] [--num-envs K] [--repeats R]`` measures ``viotb/Hover-v0``
with the ``position`` action (the SE(3) controller holds the point, so episodes do not end early) for three
estimator set-ups (``ground-truth``, ``msckf`` + ``sim`` features, ``msckf`` + ``klt`` on rendered images),
each as a single env and as a vector env of K copies (``--vector async``, the default: ``make_vector_env``'s
``AsyncVectorEnv``, one spawned worker process per copy, each limited to one OpenCV / llvmpipe / BLAS
thread, so K copies on K free cores should give close to K times the single env's steps/s, reported as
``vector_speedup``; ``--vector sync``: a ``SyncVectorEnv`` in this process). The real-time factor is
``env steps/s * ctrl_dt`` (simulated seconds per wall second, summed over the vector's copies). Worker
start-up, reset and a few warm-up steps are excluded, and a measurement stays within one episode (no
autoreset inside it); single and vector measurements alternate, and the median over repeats is reported
(DESIGN.md: about one run in ten lands in a slower mode).

Wall-clock figures need free cores. On a shared machine the CPU-time figures are the stable ones:
``single_cpu_realtime_factor`` (simulated seconds per CPU second of the process, all its threads) and, for
``async``, ``vector_cpu_realtime_factor`` (per CPU second of this process plus its workers, read from
``/proc``; absent where that is not available) and ``vector_cpu_overhead`` (CPU per env step in the vector
over the single env's: 1 means no cost of the workers' pipes and batching; on K idle cores the speedup is
at most about K / overhead).
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium
import numpy as np
import viotb.envs  # noqa: F401  (registers the ids)
from viotb.envs.gym.config import INFO_MODES
from viotb.envs.gym.vector import VECTOR_MODES, make_vector_env

SETUPS = {
    "ground-truth": {"estimator": "ground-truth", "frontend": "sim"},
    "msckf+sim": {"estimator": "msckf", "frontend": "sim"},
    "msckf+klt": {"estimator": "msckf", "frontend": "klt"},
}
"""Set-up name -> env keyword arguments."""

WARMUP_STEPS = 5
"""Untimed steps after the reset (a fresh worker's first steps pay one-off costs: lazy imports, caches)."""


def _worker_cpu_s(env) -> float | None:
    """User + system CPU seconds of an ``AsyncVectorEnv``'s worker processes, or None (no ``/proc``)."""
    processes = getattr(env, "processes", None)
    if not processes:
        return None
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for proc in processes:
        try:
            with open(f"/proc/{proc.pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            return None
        total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime (proc(5))
    return total


def _measure(env, n_steps: int, n_copies: int, seed: int) -> tuple[float, float | None]:
    """``(env steps per wall second, env steps per CPU second or None)`` over ``n_steps`` calls to ``step``.

    Reset and warm-up are not timed. CPU time is this process's (all threads) plus, for an async vector
    env, its workers'.
    """
    env.reset(seed=seed)
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    for _ in range(WARMUP_STEPS):
        env.step(action)
    workers0 = _worker_cpu_s(env)
    cpu0, t0 = time.process_time(), time.perf_counter()
    for _ in range(n_steps):
        env.step(action)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    workers1 = _worker_cpu_s(env)
    if workers0 is not None and workers1 is not None:
        cpu += workers1 - workers0
    elif getattr(env, "processes", None):
        cpu = None
    steps = n_copies * n_steps
    return steps / wall, (steps / cpu if cpu else None)


def bench(
    setup: str,
    n_steps: int,
    num_envs: int,
    repeats: int,
    seconds: float | None = None,
    vector: str = "async",
    info: str = "full",
) -> dict:
    """Median env steps/s and real-time factors of one set-up, single env and vector env (interleaved).

    Args:
        setup: A key of :data:`SETUPS`.
        n_steps: Env steps per measurement (ignored when ``seconds`` is given); at most one episode less the
            warm-up.
        num_envs: Copies in the vector env.
        repeats: Measurements of each (the median is reported).
        seconds: Simulated seconds per measurement instead of ``n_steps`` (``seconds / ctrl_dt`` steps).
        vector: A key of :data:`~viotb.envs.gym.vector.VECTOR_MODES`.
        info: The envs' ``info`` form (``VioEnvConfig.info``: ``full`` or ``flat``, the scalars only, which
            a vector env merges at less cost).

    Raises:
        ValueError: Unknown ``vector``.
    """
    if vector not in VECTOR_MODES:
        raise ValueError(f"unknown vector mode {vector!r}; allowed: {', '.join(map(repr, VECTOR_MODES))}")
    kwargs = {"action_type": "position", "info": info, **SETUPS[setup]}
    single = gymnasium.make("viotb/Hover-v0", **kwargs)
    ctrl_dt = single.unwrapped.dt
    if seconds is not None:
        n_steps = max(1, round(seconds / ctrl_dt))
    # Within one episode: a vector env would autoreset (a new rig) inside the timed loop at its end.
    n_steps = max(1, min(n_steps, (single.spec.max_episode_steps or 10**9) - WARMUP_STEPS))
    vec = make_vector_env("viotb/Hover-v0", num_envs, vector, **kwargs)
    single_runs, vec_runs = [], []
    for seed in range(repeats):
        single_runs.append(_measure(single, n_steps, 1, seed))
        vec_runs.append(_measure(vec, n_steps, num_envs, seed))
    single.close()
    vec.close()
    single_rate = float(np.median([r[0] for r in single_runs]))
    vec_rate = float(np.median([r[0] for r in vec_runs]))
    single_cpu = float(np.median([r[1] for r in single_runs]))
    out = {
        "ctrl_dt_s": ctrl_dt,
        "info": info,
        "steps_per_measurement": n_steps,
        "single_steps_per_s": single_rate,
        "single_realtime_factor": single_rate * ctrl_dt,
        "single_cpu_realtime_factor": single_cpu * ctrl_dt,
        "vector_mode": vector,
        "vector_num_envs": num_envs,
        "vector_steps_per_s": vec_rate,
        "vector_realtime_factor": vec_rate * ctrl_dt,
        "vector_speedup": vec_rate / single_rate,
    }
    if all(r[1] is not None for r in vec_runs):
        vec_cpu = float(np.median([r[1] for r in vec_runs]))
        out["vector_cpu_realtime_factor"] = vec_cpu * ctrl_dt
        out["vector_cpu_overhead"] = single_cpu / vec_cpu
    return out


def main(argv: list[str] | None = None) -> dict:
    """Parse arguments, run every set-up, print one JSON object (last line) and return it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="env steps per measurement")
    parser.add_argument("--num-envs", type=int, default=2, help="copies in the vector env")
    parser.add_argument("--vector", default="async", choices=VECTOR_MODES, help="vector env kind")
    parser.add_argument("--repeats", type=int, default=3, help="measurements per set-up (median reported)")
    parser.add_argument("--info", default="full", choices=INFO_MODES, help="the envs' info form")
    parser.add_argument(
        "--setups", nargs="+", default=list(SETUPS), choices=list(SETUPS), help="set-ups to measure"
    )
    args = parser.parse_args(argv)
    for name in ("steps", "num_envs", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    result = {
        setup: bench(setup, args.steps, args.num_envs, args.repeats, vector=args.vector, info=args.info)
        for setup in args.setups
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
