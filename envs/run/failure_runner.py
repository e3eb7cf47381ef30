"""Runs an estimator with the health monitor over an in-memory stream and measures its error against truth."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from viotb.envs.run.replay import MonitoredRun, monitor_run
from viotb.envs.scenarios.streams import Stream, StreamConfig, synthesize_stream
from viotb.vio.health import HealthMonitor, HealthParams
from viotb.vio.lie import rotmat_to_quat_wxyz
from viotb.vio.metrics import align_umeyama, evaluate_trajectory, positions_at, scale_error_pct
from viotb.vio.msckf import MsckfEstimator, MsckfParams
from viotb.vio.types import CameraFrame, ImuSeries, TrajectoryArrays
from viotb.vio.window import WindowEstimator, WindowParams


@dataclass
class RunResult:
    """One monitored MSCKF run over a stream."""

    t_s: np.ndarray
    err_m: np.ndarray
    run: MonitoredRun
    stream: Stream
    metrics: dict = field(default_factory=dict)


def run_stream(
    stream: Stream,
    params: MsckfParams | None = None,
    health: HealthParams | None = None,
    estimator: str = "msckf",
) -> RunResult:
    """Run an estimator (sim front end) with a monitor over a stream and measure position error vs time.

    The error is taken after a 4-DOF (yaw + translation) alignment of the whole estimated trajectory;
    ``metrics`` holds ``ate_m``, ``final_err_m``, ``scale_error_pct`` (sim(3) fit on the positions),
    ``init_time_s``, ``diverged``, ``time_offset_est_s``.

    Args:
        stream: A :func:`synthesize_stream` output.
        params: MSCKF settings (``estimator="msckf"``); by default the stream's pixel noise.
        health: Monitor thresholds.
        estimator: ``"msckf"`` or ``"window"`` (the sliding-window optimizer, told the stream's pixel noise).
    """
    prm = params if params is not None else MsckfParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px)
    if estimator == "msckf":
        est = MsckfEstimator(stream.calib_given, stream.noise, replace(prm, frontend="sim"))
    elif estimator == "window":
        est = WindowEstimator(
            stream.calib_given,
            stream.noise,
            WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px),
        )
    else:
        raise ValueError(f"run_stream: estimator must be 'msckf' or 'window', got {estimator!r}")
    monitor = HealthMonitor(health)
    imu, frames = stream.imu, stream.frames
    if stream.external_init is not None:
        imu, frames = _start_in_flight(est, monitor, stream)
    run = monitor_run(est, imu, frames, stream.time_offset_s, monitor)
    ok = [i for i, e in enumerate(run.estimates) if e is not None and np.all(np.isfinite(e.p_WB))]
    out = RunResult(np.zeros(0), np.zeros(0), run, stream)
    m: dict = {
        "init_time_s": None,
        "ate_m": float("nan"),
        "final_err_m": float("nan"),
        "scale_error_pct": float("nan"),
        "diverged": any(h.diverged for h in run.health),
        "time_offset_est_s": None,
    }
    if len(ok) >= 3:
        t = np.array([run.estimates[i].t_s for i in ok])
        p_est = np.array([run.estimates[i].p_WB for i in ok])
        gt = stream.truth
        p_gt = positions_at(gt, t)
        al = align_umeyama(p_est, p_gt, "posyaw")
        err = np.linalg.norm(al.apply(p_est) - p_gt, axis=1)
        out.t_s, out.err_m = t, err
        m.update(
            init_time_s=float(t[0]),
            ate_m=float(np.sqrt(np.mean(err**2))),
            final_err_m=float(err[-1]),
            scale_error_pct=float(scale_error_pct(p_est, p_gt)),
        )
        if isinstance(est, MsckfEstimator) and est.state is not None and prm.estimate_time_offset:
            m["time_offset_est_s"] = float(est.state.time_offset_s)
    out.metrics = m
    return out


def _start_in_flight(
    est: MsckfEstimator | WindowEstimator, monitor: HealthMonitor, stream: Stream
) -> tuple[ImuSeries, list[CameraFrame]]:
    """Show the monitor the IMU up to ``stream.external_init``, start ``est`` there; return the rest."""
    init = stream.external_init
    k = int(np.searchsorted(stream.imu.t_s, init.t_s, side="right"))
    for i in range(k):
        monitor.observe_imu(stream.imu.sample(i))
    est.initialize(init)
    imu = stream.imu
    rest = ImuSeries(imu.t_s[k:], imu.gyro_B_rad_s[k:], imu.accel_B_m_s2[k:], imu.saturated[k:])
    frames = [f for f in stream.frames if f.t_s + stream.time_offset_s > init.t_s]
    return rest, frames


def along_track_velocity_stats(
    result: RunResult, t_from_s: float, t_to_s: float, relative: bool = False
) -> tuple[float, float]:
    """Error and filter sigma of the velocity along the direction of travel over a time window.

    With a monocular camera the metric scale lives in the velocity (the images fix only its direction), so
    ``e = d . v_est - |v_true|`` with ``d = v_true / |v_true|`` is the scale error times the speed, and
    ``sigma = sqrt(d^T P_vv d)`` (``P_vv`` the velocity block, rows 6:9, of the 15x15 covariance) is the
    filter's own uncertainty of it.

    Args:
        result: A :func:`run_stream` result.
        t_from_s: Window start (s, IMU clock), inclusive.
        t_to_s: Window end (s), exclusive.
        relative: Divide each error and sigma by the true speed: the scale error (fraction).

    Returns:
        ``(rms_error, mean_sigma)`` (m/s, or fractions when ``relative``) over the estimates in the window
        moving faster than 0.2 m/s.

    Raises:
        ValueError: No such estimate in the window.
    """
    gt = result.stream.truth
    err, sig = [], []
    for est in result.run.estimates:
        if est is None or not t_from_s <= est.t_s < t_to_s:
            continue
        v = np.array([np.interp(est.t_s, gt.t_s, gt.v_WB[:, j]) for j in range(3)])
        speed = float(np.linalg.norm(v))
        if speed < 0.2:
            continue
        d = v / speed
        unit = speed if relative else 1.0
        err.append((float(d @ est.v_WB) - speed) / unit)
        sig.append(float(np.sqrt(max(d @ est.cov_velocity_W_m2_s2 @ d, 0.0))) / unit)
    if not err:
        raise ValueError(f"along_track_velocity_stats: no moving estimate in [{t_from_s}, {t_to_s}) s")
    return float(np.sqrt(np.mean(np.square(err)))), float(np.mean(sig))


def anchored_position_error_m(result: RunResult) -> tuple[np.ndarray, np.ndarray]:
    """Odometry error without any trajectory alignment: displacement from the first estimate vs truth.

    The estimator's world frame has its origin and yaw at the first (static) pose, as does a trajectory
    that starts at rest facing +x, so ``|(p_k - p_0) - (p_gt,k - p_gt,0)|`` is the drift accumulated since
    initialization (an alignment over the whole run would spread it over the trajectory and hide it).

    Returns:
        ``(path_length_m, error_m)``, shapes (N,) each: true distance travelled and error at each estimate.

    Raises:
        ValueError: Fewer than two estimates.
    """
    ests = [e for e in result.run.estimates if e is not None]
    if len(ests) < 2:
        raise ValueError(f"anchored_position_error_m: {len(ests)} estimates, need at least 2")
    gt = result.stream.truth
    t = np.array([e.t_s for e in ests])
    p = np.array([e.p_WB for e in ests])
    g = positions_at(gt, t)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(g, axis=0), axis=1))])
    return s, np.linalg.norm((p - p[0]) - (g - g[0]), axis=1)


def stream_metrics(
    cfg: StreamConfig, seed: int, params: MsckfParams | None = None, estimator: str = "msckf"
) -> dict:
    """Synthesize ``cfg``'s stream, run the estimator on it with a monitor, and measure it (regress, sweeps).

    Args:
        cfg: The stream.
        seed: Its seed.
        params: MSCKF settings (the stream's pixel noise and the ``sim`` front end by default).
        estimator: ``"msckf"`` or ``"window"``.

    Returns:
        ``ate_m``, ``final_err_m``, ``drift_pct`` (final error over path length), ``scale_error_pct``
        (absolute), ``nees_pos`` (``nees_pos_mean`` of :func:`viotb.vio.metrics.evaluate_trajectory`: the
        position NEES in the frame anchored at the first estimate, where the estimator fixes its gauge),
        ``ms_per_frame`` (wall time of the run per frame), ``diverged``, ``init_time_s`` and ``conditions``
        (the names the health monitor raised).
    """
    stream = synthesize_stream(cfg, seed)
    prm = replace(params, frontend="sim") if params is not None else None
    t0 = time.perf_counter()
    res = run_stream(stream, prm, estimator=estimator)
    ms = (time.perf_counter() - t0) * 1e3 / max(len(res.run.health), 1)
    m = res.metrics
    path = float(np.sum(np.linalg.norm(np.diff(stream.truth.p_WB, axis=0), axis=1)))
    nees_pos = float("nan")
    ests = [e for e in res.run.estimates if e is not None and np.all(np.isfinite(e.p_WB))]
    if len(ests) >= 3:
        traj = TrajectoryArrays(
            np.array([e.t_s for e in ests]),
            np.array([e.p_WB for e in ests]),
            np.array([rotmat_to_quat_wxyz(e.R_WB) for e in ests]),
        )
        covs = np.array([e.cov_position_W_m2 for e in ests])
        nees_pos = float(evaluate_trajectory(traj, stream.truth, pos_covs=covs)["nees_pos_mean"])
    return {
        "ate_m": m["ate_m"],
        "final_err_m": m["final_err_m"],
        "drift_pct": 100.0 * m["final_err_m"] / path if path > 0 else float("nan"),
        "scale_error_pct": abs(m["scale_error_pct"]),
        "nees_pos": nees_pos,
        "ms_per_frame": ms,
        "diverged": bool(m["diverged"]),
        "init_time_s": m["init_time_s"],
        "conditions": [c.name for c in res.run.monitor.report()],
    }
