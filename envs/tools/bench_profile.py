"""Where one simulated second of a closed-loop flight goes: a cProfile breakdown by component.

``python -m viotb.envs.tools.bench_profile [--frontend sim|klt] [--seconds S] [--json]`` flies
``fly-hover`` (MSCKF) under cProfile and prints, per component, the milliseconds of (profiled) wall time
per simulated second and the share of the flight. cProfile inflates small Python calls, so the absolute
figures overstate the real cost; the shares are what the README's profile table reports (measured on a
shared machine, where only ratios are stable). Components are the cumulative times of their entry points:

- render: ``OffscreenRenderer.render_gray`` (images) or ``project_landmarks`` (simulated features);
- physics: ``Simulation.step_checked`` (what ``Simulation.step`` and the scheduler call); IMU model:
  ``ImuModel.measure``;
- front end: the tracker's ``process``; update: ``MsckfEstimator._process`` less its propagation;
- propagation: ``Propagator.propagate`` (per frame) and ``MsckfEstimator.estimate`` (the per-tick
  prediction to the newest IMU sample);
- control: ``SE3Controller._thrusts_f`` (the SE(3) law and mixer behind ``update``, ``thrusts`` and
  ``thrusts_from_estimate``) and the mission's ``TakeoffSequence.update``;
- health monitor: ``HealthMonitor.observe_imu`` / ``observe_frame``; logging: ``fly._log_tick`` and
  ``FlightLog.resolve_deferred`` (which computes the per-tick covariances the log's sigmas read, once per
  frame: the estimate's covariance is lazy, :mod:`viotb.vio.imu_prediction`);
- other: the rest of the flight loop (scheduler, truth reads, crash test).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats

COMPONENTS: tuple[tuple[str, tuple[tuple[str, str], ...], tuple[tuple[str, str], ...]], ...] = (
    ("render", (("sim/render.py", "render_gray"), ("sim/landmarks.py", "project_landmarks")), ()),
    ("physics", (("sim/simulation.py", "step_checked"),), ()),
    ("IMU model", (("sim/imu_model.py", "measure"),), ()),
    ("front end", (("vio/frontend.py", "process"),), ()),
    ("update", (("vio/msckf.py", "_process"),), (("vio/propagator.py", "propagate"),)),
    ("propagation", (("vio/propagator.py", "propagate"), ("vio/msckf.py", "estimate")), ()),
    ("control", (("controllers/se3.py", "_thrusts_f"), ("run/mission.py", "update")), ()),
    ("health monitor", (("vio/health.py", "observe_imu"), ("vio/health.py", "observe_frame")), ()),
    ("logging", (("run/fly.py", "_log_tick"), ("run/flight_log.py", "resolve_deferred")), ()),
)
"""(component, entry points added, entry points subtracted), each point ``(file suffix, function)``."""


def _cumulative(stats: dict, points: tuple[tuple[str, str], ...]) -> float:
    return sum(
        v[3] for k, v in stats.items() for suffix, name in points if k[0].endswith(suffix) and k[2] == name
    )


def profile_flight(frontend: str = "sim", seconds: float = 10.0, seed: int = 0) -> dict:
    """Fly ``fly-hover`` under cProfile and break the flight's time down by component.

    Returns:
        ``{"frontend", "seconds", "total_ms_per_sim_s", "ms_per_sim_s": {component: ms}, "share":
        {component: fraction}}``, with ``other`` the remainder of the flight loop.
    """
    from viotb.envs.run.fly import fly

    prof = cProfile.Profile()
    prof.enable()
    fly("fly-hover", "msckf", seconds, seed, frontend)
    prof.disable()
    stats = pstats.Stats(prof).stats
    total = _cumulative(stats, (("run/fly.py", "fly"),))
    parts = {name: _cumulative(stats, add) - _cumulative(stats, sub) for name, add, sub in COMPONENTS}
    parts["other"] = total - sum(parts.values())
    return {
        "frontend": frontend,
        "seconds": seconds,
        "total_ms_per_sim_s": 1e3 * total / seconds,
        "ms_per_sim_s": {k: 1e3 * v / seconds for k, v in parts.items()},
        "share": {k: v / total for k, v in parts.items()},
    }


def main(argv: list[str] | None = None) -> dict:
    """Print the breakdown (a table, or JSON with ``--json``) and return it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frontend", choices=("sim", "klt"), default="sim")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    if not args.seconds > 0.0:
        parser.error(f"--seconds must be positive, got {args.seconds}")
    result = profile_flight(args.frontend, args.seconds, args.seed)
    if args.json:
        print(json.dumps(result))
    else:
        for name, ms in result["ms_per_sim_s"].items():
            print(f"{name:16s} {ms:8.1f} ms/s {100.0 * result['share'][name]:5.1f} %")
        print(f"{'total':16s} {result['total_ms_per_sim_s']:8.1f} ms/s (profiled)")
    return result


if __name__ == "__main__":
    main()
