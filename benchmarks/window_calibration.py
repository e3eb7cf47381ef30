"""Online calibration of the ``window`` optimizer on simulated-feature failure streams: accuracy and cost.

Cases (sim front end, 0.5 px, 13.5 s fast figure-8s of :data:`viotb.envs.scenarios.failures.FAILURES`):
``time-offset`` (the file's offset 10 ms off), ``extrinsic`` (``R_BC`` 2 deg off), ``right-file`` (the
extrinsic stream with the true file), ``translation+offset`` (5 ms and ``p_BC`` 2 cm off, a 5 cm translation
prior). Each is run with the file's calibration fixed and with ``WindowParams.with_online_calibration()``,
interleaved, ``--repeats`` times; the CPU time of every ``feed_camera`` call is ``time.thread_time()`` and
each frame keeps its minimum over the repeats (the machine is shared). Prints one JSON object: per case and
mode the ATE (yaw + translation alignment), the estimated minus true calibration with its sigmas, the
conditions the health monitor named, and the per-frame CPU ms (median, p99).

Usage::

    python benchmarks/window_calibration.py --seed 0 --repeats 2
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np
from viotb.envs.run.replay import monitor_run
from viotb.envs.scenarios.failures import FAILURES
from viotb.envs.scenarios.streams import synthesize_stream
from viotb.vio.health import HealthMonitor
from viotb.vio.lie import log_so3
from viotb.vio.metrics import align_umeyama, positions_at
from viotb.vio.window import WindowEstimator, WindowParams


class _Timed:
    """The estimator with the CPU time (ms) of each ``feed_camera`` call recorded in ``cpu_ms``."""

    def __init__(self, est: WindowEstimator) -> None:
        self._est = est
        self.cpu_ms: list[float] = []

    def feed_camera(self, frame) -> None:
        t0 = time.thread_time()
        self._est.feed_camera(frame)
        self.cpu_ms.append((time.thread_time() - t0) * 1e3)

    def __getattr__(self, name: str):
        return getattr(self._est, name)


def _streams(seed: int) -> dict:
    to = synthesize_stream(FAILURES["fail-time-offset"].config(1.0), seed=seed)
    ex = synthesize_stream(FAILURES["fail-extrinsic"].config(1.0), seed=seed)
    half = synthesize_stream(FAILURES["fail-time-offset"].config(0.5), seed=seed)
    moved = replace(half.calib_given, p_BC=half.calib_given.p_BC + np.array([0.02, 0.0, 0.0]))
    return {
        "time-offset": (to, None),
        "extrinsic": (ex, None),
        "right-file": (replace(ex, calib_given=ex.calib_true), None),
        "translation+offset": (replace(half, calib_given=moved), 0.05),
    }


def _run(stream, params: WindowParams) -> dict:
    est = _Timed(WindowEstimator(stream.calib_given, stream.noise, params))
    monitor = HealthMonitor()
    run = monitor_run(est, stream.imu, stream.frames, stream.time_offset_s, monitor)
    ok = [e for e in run.estimates if e is not None]
    t = np.array([e.t_s for e in ok])
    p = np.array([e.p_WB for e in ok])
    gt = stream.truth
    p_gt = positions_at(gt, t)
    al = align_umeyama(p, p_gt, "posyaw")
    out = {
        "ate_cm": 100.0 * float(np.sqrt(np.mean(np.linalg.norm(al.apply(p) - p_gt, axis=1) ** 2))),
        "named": sorted({c.name for c in monitor.report()}),
        "cpu_ms": est.cpu_ms,
    }
    c = run.health[-1].calibration
    if c is not None:
        g, tr = stream.calib_given, stream.calib_true
        out["time_offset_error_ms"] = 1e3 * (c.time_offset_s - (stream.time_offset_s - g.time_offset_s))
        out["time_offset_sigma_ms"] = 1e3 * c.time_offset_sigma_s
        rot_true = log_so3(g.R_BC.T @ tr.R_BC)
        out["rotation_error_deg"] = np.rad2deg(c.rotation_BC_rad - rot_true).round(4).tolist()
        out["rotation_sigma_deg"] = np.rad2deg(c.rotation_sigma_rad).round(4).tolist()
        out["translation_error_cm"] = (100 * (c.translation_BC_m - (tr.p_BC - g.p_BC))).round(3).tolist()
        out["translation_sigma_cm"] = (100 * c.translation_sigma_m).round(3).tolist()
    return out


def main() -> None:
    """Run every case fixed and calibrated; print the JSON summary."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    result: dict = {"seed": args.seed, "repeats": args.repeats, "cases": {}}
    for name, (stream, sigma_m) in _streams(args.seed).items():
        base = WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px)
        modes = {"fixed": base, "calibrated": base.with_online_calibration(extrinsic_sigma_m=sigma_m)}
        runs: dict = {m: [] for m in modes}
        for _ in range(args.repeats):  # interleaved A/B
            for m, prm in modes.items():
                runs[m].append(_run(stream, prm))
        case = {}
        for m, rs in runs.items():
            row = {k: v for k, v in rs[0].items() if k != "cpu_ms"}
            cpu = np.min(np.array([r["cpu_ms"] for r in rs]), axis=0)  # per frame, over the repeats
            row["cpu_ms_median"], row["cpu_ms_p99"] = float(np.median(cpu)), float(np.percentile(cpu, 99))
            case[m] = row
        result["cases"][name] = case
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
