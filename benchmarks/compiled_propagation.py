"""CPU time of the compiled IMU propagation against its numpy reference, interleaved in one process.

Both paths live in the code base (``Propagator.compiled``; :mod:`viotb.vio.imu_kernels`), so before and
after run in the same process, taking turns, and see the same load. Parts:

- ``micro``: the propagation's calls one by one (the per-tick mean, the per-tick covariance read, a
  frame's ten batched covariances, a frame's span of ten intervals); ``time.thread_time`` per call, the
  minimum over repeats of a loop of calls;
- ``fly``: ``fly fly-hover`` MSCKF + simulated features, ``--seconds`` each, numpy and compiled flights
  alternating (``--pairs`` pairs): the flight's ``cpu_realtime_factor``, the ratio of each pair, the
  median, and the per-component thread time of one simulated second (entry points wrapped with
  ``time.thread_time``, about 1 us per call added);
- ``gym``: ``viotb/Hover-v0`` MSCKF + sim, ``--steps`` steps per burst, bursts alternating in two envs
  (numpy, compiled): process CPU per burst, the ratio per pair, the median.

Usage::

    python benchmarks/compiled_propagation.py [--part micro|fly|gym|all] [--pairs 5] [--seconds 10]

prints one JSON object. Every flight of a mode gives the same ATE (determinism); the two modes differ by
round-off.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from contextlib import contextmanager

import numpy as np
from viotb.vio.propagator import Propagator


@contextmanager
def _propagation(compiled: bool):
    """New propagators (the flights' and envs' estimators) take the compiled path or the numpy one."""
    init = Propagator.__init__

    def patched(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self.compiled = compiled

    Propagator.__init__ = patched
    try:
        yield
    finally:
        Propagator.__init__ = init


def _min_us(fn: Callable[[], object], loops: int, repeats: int) -> float:
    """Minimum over ``repeats`` of the thread time per call (us) of ``loops`` calls."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.thread_time()
        for _ in range(loops):
            fn()
        best = min(best, (time.thread_time() - t0) / loops)
    return 1e6 * best


def micro(repeats: int = 7) -> dict:
    """Per-call thread time (us) of the propagation's pieces, numpy against compiled."""
    from viotb.vio import imu_kernels_calls as kc
    from viotb.vio.imu_integration import (
        Integration,
        discrete_noise,
        discrete_noise_batch,
        integrate_mean,
        step_transition,
        step_transitions,
    )
    from viotb.vio.lie import exp_so3
    from viotb.vio.propagator import propagate_values
    from viotb.vio.state import ImuValues
    from viotb.vio.types import ImuNoise

    rng = np.random.default_rng(0)
    noise = ImuNoise()
    x = ImuValues(
        exp_so3(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=3), np.zeros(3), np.zeros(3)
    )
    n = 11  # a frame at 20 Hz of a 200 Hz IMU: ten intervals
    t = 0.005 * np.arange(n)
    gyro, accel = rng.normal(0, 1, (n, 3)), rng.normal(0, 1, (n, 3)) + [0, 0, 9.81]
    m = Integration.RK4
    steps, cur = [], x
    for k in range(n - 1):
        steps.append(integrate_mean(cur, gyro[k], gyro[k + 1], accel[k], accel[k + 1], 0.005, m))
        cur = steps[-1].new
    eye, zero = np.eye(15), np.zeros((15, 15))

    def read_numpy():  # the per-tick covariance read (PredictionChain._build_totals, one step)
        phi = step_transition(steps[0])
        q = discrete_noise(phi, noise, 0.005)
        return phi @ eye, phi @ zero @ phi.T + q

    def read_compiled():
        phis, qs = kc.step_links(steps[:1], noise)
        return kc.chain_links(phis, qs, eye, zero)

    def batch_numpy():  # a frame's ten deferred covariances at once
        phis = step_transitions(steps)
        qs = discrete_noise_batch(phis, noise, np.full(len(steps), 0.005))
        phi_tot, q_tot = eye, zero
        for phi, q in zip(phis, qs, strict=True):
            phi_tot, q_tot = phi @ phi_tot, phi @ q_tot @ phi.T + q
        return phi_tot, q_tot

    def batch_compiled():
        phis, qs = kc.step_links(steps, noise)
        return kc.chain_links(phis, qs, eye, zero)

    w0, w1, a0, a1 = gyro[0], gyro[1], accel[0], accel[1]
    cases = {
        "tick_mean": (
            lambda: integrate_mean(x, w0, w1, a0, a1, 0.005, m),
            lambda: kc.mean_record(x, w0, w1, a0, a1, 0.005, m),
        ),
        "tick_cov_read": (read_numpy, read_compiled),
        "frame_cov_batch_10": (batch_numpy, batch_compiled),
        "frame_span_10": (
            lambda: propagate_values(x, t, gyro, accel, m, noise, x, None, False),
            lambda: propagate_values(x, t, gyro, accel, m, noise, x, None, True),
        ),
    }
    out = {}
    for name, (ref, new) in cases.items():
        new()  # compile or load the kernels
        loops = 200
        us_ref, us_new = [], []
        for _ in range(3):  # interleaved
            us_ref.append(_min_us(ref, loops, repeats))
            us_new.append(_min_us(new, loops, repeats))
        out[name] = {"numpy_us": min(us_ref), "compiled_us": min(us_new), "ratio": min(us_ref) / min(us_new)}
    return out


PROFILE_POINTS = (
    ("estimator: feed_camera less propagate", "viotb.vio.msckf", "MsckfEstimator", "feed_camera"),
    ("estimator: per-frame propagate", "viotb.vio.propagator", "Propagator", "propagate"),
    ("estimator: per-tick estimate()", "viotb.vio.msckf", "MsckfEstimator", "estimate"),
    ("estimator: feed_imu", "viotb.vio.msckf", "MsckfEstimator", "feed_imu"),
    ("log covariances (resolve_deferred)", "viotb.envs.run.flight_log", "FlightLog", "resolve_deferred"),
    ("physics (step_checked)", "viotb.envs.sim.simulation", "Simulation", "step_checked"),
    ("IMU model (measure)", "viotb.envs.sim.imu_model", "ImuModel", "measure"),
    ("control (SE(3) + mixer)", "viotb.controllers.se3", "SE3Controller", "_thrusts_f"),
    ("mission (TakeoffSequence.update)", "viotb.envs.run.mission", "TakeoffSequence", "update"),
    ("health monitor: observe_imu", "viotb.vio.health", "HealthMonitor", "observe_imu"),
    ("health monitor: observe_frame", "viotb.vio.health", "HealthMonitor", "observe_frame"),
)
"""(component, module, class, method) wrapped with a thread-time accumulator in :func:`fly_pairs`."""


@contextmanager
def _timed(acc: dict[str, float]):
    """Wrap :data:`PROFILE_POINTS` so that each adds its thread time (s) to ``acc[component]``."""
    import importlib

    saved = []
    for name, module, cls_name, meth in PROFILE_POINTS:
        cls = getattr(importlib.import_module(module), cls_name)
        fn = getattr(cls, meth)
        depth = [0]

        def wrapped(*a, _fn=fn, _name=name, _depth=depth, **k):
            if _depth[0]:
                return _fn(*a, **k)
            _depth[0] += 1
            t0 = time.thread_time()
            try:
                return _fn(*a, **k)
            finally:
                acc[_name] = acc.get(_name, 0.0) + time.thread_time() - t0
                _depth[0] -= 1

        setattr(cls, meth, wrapped)
        saved.append((cls, meth, fn))
    try:
        yield
    finally:
        for cls, meth, fn in saved:
            setattr(cls, meth, fn)


def fly_pairs(pairs: int, seconds: float) -> dict:
    """Alternating numpy / compiled ``fly-hover`` MSCKF + sim flights: CPU real-time factors and profile."""
    from viotb.envs.run.fly import fly

    for compiled in (False, True):  # warm-up: imports, kernel cache, MuJoCo
        with _propagation(compiled):
            fly("fly-hover", "msckf", 1.0, 0, "sim")
    runs: dict[str, list[dict]] = {"numpy": [], "compiled": []}
    for _ in range(pairs):
        for label in runs:
            acc: dict[str, float] = {}
            with _propagation(label == "compiled"), _timed(acc):
                t0 = time.process_time()
                metrics, _ = fly("fly-hover", "msckf", seconds, 0, "sim")
                cpu = time.process_time() - t0
            acc["estimator: feed_camera less propagate"] -= acc.get("estimator: per-frame propagate", 0.0)
            runs[label].append(
                {
                    "cpu_realtime_factor": seconds / cpu,
                    "ate_posyaw_m": metrics["ate_posyaw_m"],
                    "ms_per_sim_s": {k: 1e3 * v / seconds for k, v in acc.items()}
                    | {"total": 1e3 * cpu / seconds},
                }
            )
    ratios = [
        c["cpu_realtime_factor"] / n["cpu_realtime_factor"] for n, c in zip(*runs.values(), strict=True)
    ]
    out = {"seconds": seconds, "pair_ratios": ratios, "ratio_median": float(np.median(ratios))}
    for label, rs in runs.items():
        out[label] = {
            "cpu_realtime_factor": [r["cpu_realtime_factor"] for r in rs],
            "ate_posyaw_m": sorted({r["ate_posyaw_m"] for r in rs}),
            "ms_per_sim_s_median": {
                k: float(np.median([r["ms_per_sim_s"][k] for r in rs])) for k in rs[0]["ms_per_sim_s"]
            },
        }
    return out


def gym_pairs(pairs: int, steps: int) -> dict:
    """Alternating bursts of two MSCKF + sim ``Hover-v0`` envs (numpy, compiled): CPU per burst."""
    import gymnasium
    import viotb.envs  # noqa: F401  (registers the ids)

    envs = {}
    for label in ("numpy", "compiled"):
        with _propagation(label == "compiled"):
            env = gymnasium.make("viotb/Hover-v0", estimator="msckf", frontend="sim", action_type="position")
            env.reset(seed=0)
            for _ in range(5):
                env.step(np.zeros(env.action_space.shape, dtype=np.float32))
            envs[label] = env
    cpu: dict[str, list[float]] = {k: [] for k in envs}
    left = {k: (envs[k].spec.max_episode_steps or 10**9) - 5 for k in envs}
    for _ in range(pairs):
        for label, env in envs.items():
            if left[label] < steps:
                env.reset(seed=0)
                left[label] = env.spec.max_episode_steps or 10**9
            a = np.zeros(env.action_space.shape, dtype=np.float32)
            t0 = time.process_time()
            for _ in range(steps):
                env.step(a)
            cpu[label].append(time.process_time() - t0)
            left[label] -= steps
    dt = envs["numpy"].unwrapped.dt
    ratios = [n / c for n, c in zip(cpu["numpy"], cpu["compiled"], strict=True)]
    return {
        "steps": steps,
        "pair_ratios": ratios,
        "ratio_median": float(np.median(ratios)),
        **{
            f"{k}_cpu_realtime_factor_median": float(np.median([steps * dt / c for c in v]))
            for k, v in cpu.items()
        },
    }


def main(argv: list[str] | None = None) -> dict:
    """Run the selected parts and print one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("micro", "fly", "gym", "all"), default="all")
    parser.add_argument("--pairs", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args(argv)
    out = {}
    if args.part in ("micro", "all"):
        out["micro"] = micro()
    if args.part in ("fly", "all"):
        out["fly"] = fly_pairs(args.pairs, args.seconds)
    if args.part in ("gym", "all"):
        out["gym"] = gym_pairs(args.pairs, args.steps)
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
