"""Closed-loop flights: a quadrotor that initializes on the ground, takes off and flies on its own VIO.

The runner (``viotb fly``) drives :class:`~viotb.envs.run.closed_loop.ClosedLoopSim` (the scheduler) with the
phase machine of :class:`~viotb.envs.run.mission.TakeoffSequence`: on the ground until the estimator
initializes from the IMU at rest, a climb to ``takeoff_altitude_m`` above the estimated start, an excitation
manoeuvre when the estimator asks for one, then the scenario's mission relative to the hover point, in the
estimator's frame. No truth is read by the control path after t = 0.

A feature-based estimator runs inside :class:`~viotb.vio.recovery.RecoveringEstimator` (``recovery``,
the default): when it loses every feature or diverges, or the health monitor names ``divergence``, the drone
coasts on the IMU and the estimator re-initializes in the air once features return; ``recoveries`` lists each
episode. Only what cannot be recovered (a failed IMU, a divergence with no good state to coast from, or any
divergence with ``recovery`` off) stops the motors: the runner records ``diverged`` with the reason and ends
the flight instead of crashing the process. Metrics compare truth with the setpoints mapped into the
truth frame by the 4-DOF (yaw + translation) gauge fixed at initialization, which is used for evaluation only.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial

import numpy as np
from viotb.controllers import SE3Controller, SE3Gains
from viotb.envs.run.closed_loop import ClosedLoopSim
from viotb.envs.run.flight_log import FlightLog
from viotb.envs.run.flight_metrics import blackout_metrics, flight_metrics, lights_out_metrics
from viotb.envs.run.loop_glue import FlightLoopClosure, LoopOptions, require_images
from viotb.envs.run.mission import TakeoffSequence
from viotb.envs.scenarios.failures import failure_fly_scenario
from viotb.envs.scenarios.registry import get_fly_scenario
from viotb.envs.sim.rig import RigConfig
from viotb.envs.sim.vehicle import vehicle_params_from_model
from viotb.vio.health import HealthMonitor
from viotb.vio.imu_prediction import prefetch_covariances
from viotb.vio.lie import rotz, yaw_from_rotmat
from viotb.vio.model_options import model_settings
from viotb.vio.recovery import RecoveringEstimator
from viotb.vio.types import StateEstimate

ProgressFn = Callable[[float, float], None]

CONTROL_RATE_HZ = 250.0
"""Position/attitude controller rate (Hz): a whole multiple of the 1 kHz physics."""


def _gauge(est_R: np.ndarray, est_p: np.ndarray, true_R: np.ndarray, true_p: np.ndarray):
    """4-DOF transform (yaw, translation) mapping estimator-frame points to the truth frame."""
    dyaw = yaw_from_rotmat(true_R) - yaw_from_rotmat(est_R)
    R = rotz(dyaw)
    return R, true_p - R @ est_p


def _gauge_floats(R_g: np.ndarray, t_g: np.ndarray) -> tuple[float, float, float, float, float]:
    """``(cos, sin, t_x, t_y, t_z)`` of a gauge ``(R_g = rotz(yaw), t_g)`` from :func:`_gauge`."""
    return (float(R_g[0, 0]), float(R_g[1, 0]), *t_g.tolist())


def fly(
    scenario: str,
    estimator: str = "msckf",
    seconds: float | None = None,
    seed: int = 0,
    frontend: str = "klt",
    progress: ProgressFn | None = None,
    on_tick: Callable[[ClosedLoopSim, FlightLog], None] | None = None,
    gains: SE3Gains | None = None,
    online_calibration: bool | None = None,
    severity: float | None = None,
    edit_rig: Callable[[RigConfig], RigConfig] | None = None,
    loop_closure: bool | LoopOptions | None = None,
    recovery: bool = True,
    sensor_model: str = "default",
) -> tuple[dict, FlightLog]:
    """Fly a closed-loop scenario.

    Args:
        scenario: A closed-loop scenario name (:func:`~viotb.envs.scenarios.registry.fly_scenario_names`).
        estimator: ``msckf``, ``imu-only`` or ``ground-truth``.
        seconds: Flight duration (s), ground phase included; scenario default if None.
        seed: Seeds sensors, wind and drops.
        frontend: ``klt`` (rendered images) or ``sim`` (simulated features, fast mode).
        progress: Optional ``(done_s, total_s)`` callback.
        on_tick: Optional hook called every control tick (recorders use it).
        gains: Controller gains (defaults when None).
        online_calibration: Estimate the camera-IMU time offset and extrinsics online (overrides the
            scenario's rig when not None).
        severity: For a ``fly-fail-*`` scenario with a knob, its severity
            (``viotb.envs.scenarios.failures.failure_fly_scenario``); None = the registered default.
        edit_rig: Applied last to the run's rig (estimator settings, sensors, wind...; sweeps use it).
        loop_closure: Loop closure beside the filter (True: default options, keyframes from the excitation
            manoeuvre on where the scenario flies with loop closure by default); the controller then flies on
            the corrected pose (``viotb.envs.run.loop_glue.FlightLoopClosure``). None: the scenario's default
            (``FlyScenario.loop_closure``). With the ``sim`` front end the camera is rendered for the closer.
        recovery: Coast through a loss of tracking and re-initialize in the air (``RigConfig.recovery``)
            instead of stopping the flight on divergence; ``edit_rig`` may still turn it off.
        sensor_model: The estimator's sensor model (:func:`viotb.vio.model_options.model_settings`;
            ``"render"``: the one measured on these renders; ``msckf`` or ``window`` on ``klt`` only).

    Returns:
        ``(metrics, log)``; metrics has ``hover_rms_m``, ``max_err_m``, ``ate_posyaw_m``, ``crashed``,
        ``diverged``, ``realtime_factor`` and more.

    Raises:
        ValueError: Unknown scenario/estimator/front end, non-positive ``seconds``.
    """
    if severity is None:
        sc = get_fly_scenario(scenario)
    else:
        sc = failure_fly_scenario(scenario, severity)
    total_s = sc.default_seconds if seconds is None else float(seconds)
    if not (total_s > 0.0 and np.isfinite(total_s)):
        raise ValueError(f"seconds must be positive and finite, got {seconds}")
    rig = replace(sc.rig, estimator=estimator, frontend=frontend, recovery=bool(recovery))
    if online_calibration is not None:
        rig = replace(rig, online_calibration=bool(online_calibration))
    if sensor_model != "default":
        msckf, window = model_settings(estimator, frontend, sensor_model, msckf=rig.msckf, window=rig.window)
        rig = replace(rig, msckf=msckf, window=window)
    if edit_rig is not None:
        rig = edit_rig(rig)
    if loop_closure is None:
        loop_closure = sc.loop_closure
    lc_opts = LoopOptions(from_excitation=sc.loop_closure) if loop_closure is True else (loop_closure or None)
    if lc_opts is not None and frontend == "sim":
        rig = replace(rig, render_images=True)  # the estimator on simulated features, the closer on images
    if lc_opts is not None:
        require_images(frontend, rig.render_images)
    loop = ClosedLoopSim(rig, seed=seed)
    lc = None
    if lc_opts is not None:
        lc = FlightLoopClosure(lc_opts, loop.calib_given, frontend, rig.render_images)
        if isinstance(loop.estimator, RecoveringEstimator):
            lc.follow_odometry_resets(loop.estimator.odometry_resets)
            if lc_opts.velocity_fix_wait_s > 0.0:
                loop.estimator.expect_velocity_fixes(lc_opts.velocity_fix_wait_s)
    controller = SE3Controller(vehicle_params_from_model(loop.sim.model), gains or SE3Gains())
    log = FlightLog()
    ctrl_dt = 1.0 / CONTROL_RATE_HZ
    alt = np.array([0.0, 0.0, sc.takeoff_altitude_m])
    seq = TakeoffSequence(lambda e: e.p_WB + alt, takeoff_s=3.0, mission=sc.mission, allow_excitation=True)
    gauge = None
    crashed = diverged = False
    reason = ""
    thrusts = np.zeros(4)
    n_frames_seen = 0
    monitor = HealthMonitor()
    last_imu_seen = None
    lazy: list[StateEstimate] = []  # the estimates whose sigmas the log fills in at the next frame
    wall0, cpu0 = time.perf_counter(), time.process_time()
    while loop.t_s < total_s - 1e-9:
        est = loop.estimate() if lc is None else lc.correct(loop.t_s, loop.estimate())
        health = loop.health()
        if health.diverged or loop.estimator_failure:
            # Stop safely: motors off, flight ended, the reason reported (no exception escapes).
            diverged, reason = True, health.reason or f"estimator failed: {loop.estimator_failure}"
            break
        on_ground = seq.phase == "ground"
        setpoint = seq.update(loop.t_s, est, loop.estimator)
        if on_ground and seq.phase != "ground":
            tr = loop.truth()
            gauge = _gauge_floats(*_gauge(est.R_WB, est.p_WB, tr.R_WB, tr.p_WB))
        phase = seq.phase
        if phase == "ground" or est is None or setpoint is None:
            thrusts = np.zeros(4)
        else:
            thrusts = controller.thrusts_from_estimate(loop.t_s, est, setpoint)
        loop.advance(thrusts, ctrl_dt)
        tr = loop.truth()
        airborne = phase != "ground" and (loop.t_s - seq.plan_t0_s > 1.0 or phase != "takeoff")
        if loop.crashed(airborne):
            crashed = True
        _log_tick(log, loop, phase, est, setpoint, gauge, tr, thrusts, lazy)
        if loop.last_imu is not None and loop.last_imu is not last_imu_seen:
            last_imu_seen = loop.last_imu
            monitor.observe_imu(last_imu_seen)
        if loop.frames_delivered != n_frames_seen:
            n_frames_seen = loop.frames_delivered
            h = loop.health()
            monitor.observe_frame(loop.t_s, h, loop.estimate())
            if "divergence" in monitor.active() and not h.diverged:
                # The monitor's bound is tighter than the filter's own (a drone flying blind on the IMU alone
                # is lost long before its covariance explodes): coast and re-initialize, or stop the flight.
                cond = next(c for c in monitor.report() if c.name == "divergence")
                if isinstance(loop.estimator, RecoveringEstimator):
                    loop.estimator.declare_lost(loop.t_s, f"health monitor: {cond.evidence}")
                else:
                    diverged, reason = True, f"health monitor: {cond.evidence}"
            log.append_frame(loop.t_s, h.tracked_features, h.conditions)
            prefetch_covariances(lazy)  # the covariances since the last frame, in one batch
            lazy.clear()
            log.resolve_deferred()
            if lc is not None and loop.last_frame is not None and _loop_phase(lc, seq):
                frame_image = loop.last_frame.image
                lc.on_frame(loop.t_s, frame_image, loop.estimate(), h.tracked_features, loop.truth())
                rec = loop.estimator
                if isinstance(rec, RecoveringEstimator) and rec.wants_velocity_fix:
                    fix = lc.drift_velocity()  # the relocalized coast's drift rate (vio.recovery)
                    if fix is not None:
                        rec.velocity_fix(*fix)
        if on_tick is not None:
            on_tick(loop, log)
        if progress is not None:
            progress(loop.t_s, total_s)
        if crashed or diverged:
            break
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    loop.close()
    metrics = flight_metrics(log, seq.mission_t0_s, seq.init_t_s)
    metrics["notes"] = _null_notes(
        metrics, seq.init_t_s, seq.mission_t0_s, float(loop.t_s), crashed or diverged
    )
    metrics.update(blackout_metrics(log, rig.camera.blackout_intervals_s))
    metrics.update(lights_out_metrics(log, rig.lights_off_intervals_s))
    events = loop.estimator.events if isinstance(loop.estimator, RecoveringEstimator) else []
    metrics.update(
        {
            "scenario": scenario,
            "estimator": estimator,
            "frontend": frontend,
            "seed": seed,
            "seconds": float(loop.t_s),
            "crashed": bool(crashed),
            "diverged": bool(diverged),
            "reason": reason,
            "excitation_flown": seq.excitation_flown,
            "init_time_s": seq.init_t_s,
            "realtime_factor": float(loop.t_s / wall) if wall > 0 else float("inf"),
            "cpu_realtime_factor": float(loop.t_s / cpu) if cpu > 0 else float("inf"),
            "frames_delivered": loop.frames_delivered,
            "frames_dropped": loop.frames_dropped,
            "conditions": [
                {"name": c.name, "t_s_first": c.t_s_first, "evidence": c.evidence} for c in monitor.report()
            ],
            "recoveries": [
                {
                    "t_lost_s": e.t_lost_s,
                    "reason": e.reason,
                    "t_reinit_s": e.t_reinit_s,
                    "coast_position_sigma_m": e.coast_position_sigma_m,
                }
                for e in events
            ],
        }
    )
    if lc is not None:
        metrics.update(lc.finish())
    return metrics, log


def _loop_phase(lc: FlightLoopClosure, seq: TakeoffSequence) -> bool:
    """Whether the closer gets frames now.

    From the mission on (keyframes of the climb carry the filter's unconverged scale), or from the excitation
    manoeuvre on with ``LoopOptions.from_excitation``.
    """
    return seq.phase == "mission" or (lc.opts.from_excitation and seq.phase == "excite")


def _null_notes(
    metrics: dict, init_t_s: float | None, mission_t0_s: float | None, end_s: float, stopped: bool
) -> list[str]:
    """Why a tracking or estimation metric is None (``hover_rms_m``, ``max_err_m``, ``ate_posyaw_m``...)."""
    if mission_t0_s is not None and metrics["hover_rms_m"] is not None:
        return []
    if stopped:
        why = f"the flight stopped at {end_s:.2f} s (crash or divergence) before the mission started"
    elif init_t_s is None:
        why = f"the estimator did not initialize on the ground within the {end_s:.2f} s flown"
    else:
        why = (
            f"the mission had not started when the flight ended at {end_s:.2f} s (initialized on the ground "
            f"at {init_t_s:.2f} s, then a 3 s takeoff: fly longer, about 10.5 s plus the mission)"
        )
    keys = [k for k in ("hover_rms_m", "max_err_m", "ate_posyaw_m", "est_rms_m") if metrics.get(k) is None]
    return [f"{', '.join(keys)}: null ({why})"] if keys else []


def _sigma_in_gauge(est: StateEstimate, gauge: tuple[float, float, float, float, float]) -> tuple:
    """Position sigmas (m) along the truth frame's axes: ``sqrt(diag(R_g C R_g^T))`` in floats."""
    c, s = gauge[0], gauge[1]
    (cxx, cxy, _), (cyx, cyy, _), (_, _, czz) = est.cov_position_W_m2.tolist()
    vxx = c * c * cxx - c * s * (cxy + cyx) + s * s * cyy
    vyy = s * s * cxx + c * s * (cxy + cyx) + c * c * cyy
    return (math.sqrt(max(vxx, 0.0)), math.sqrt(max(vyy, 0.0)), math.sqrt(max(czz, 0.0)))


def _log_tick(
    log: FlightLog, loop: ClosedLoopSim, phase, est, setpoint, gauge, tr, thrusts, lazy: list | None = None
) -> None:
    """Append one control tick to the log (setpoint and estimate mapped to the truth frame by the gauge).

    The gauge is a yaw about z and a translation, applied in floats (:func:`_gauge_floats`): the values
    equal the matrix form ``R_g @ p + t_g``, ``sqrt(diag(R_g C R_g^T))``, ``yaw(R_g R_WB)`` to round-off.
    An estimate whose covariance is not computed yet (``LazyCovarianceEstimate`` of
    :mod:`viotb.vio.imu_prediction`) has its sigmas filled in later by the log
    (:meth:`FlightLog.resolve_deferred`, once per frame), so that the covariances between two frames are
    computed in one batch: such an estimate is appended to ``lazy``, which the flight hands to
    :func:`~viotb.vio.imu_prediction.prefetch_covariances` before the log resolves its cells.
    """
    imu = loop.last_imu
    nan3 = (math.nan, math.nan, math.nan)
    p_est = p_sigma = p_set = nan3
    yaw_est = math.nan
    deferred = None
    if gauge is not None:
        c, s, t0, t1, t2 = gauge
        if est is not None:
            x, y, z = est.p_WB.tolist()
            p_est = (c * x - s * y + t0, s * x + c * y + t1, z + t2)
            if getattr(est, "cov_ready", True):
                p_sigma = _sigma_in_gauge(est, gauge)
            else:
                deferred = ("p_sigma_W", partial(_sigma_in_gauge, est, gauge))
                if lazy is not None:
                    lazy.append(est)
            (r00, _, _), (r10, _, _), _ = est.R_WB.tolist()
            yaw_est = math.atan2(s * r00 + c * r10, c * r00 - s * r10)
        if setpoint is not None:
            x, y, z = setpoint.p_W.tolist()
            p_set = (c * x - s * y + t0, s * x + c * y + t1, z + t2)
    gyro, accel = (nan3, nan3) if imu is None else (imu.gyro_B_rad_s.tolist(), imu.accel_B_m_s2.tolist())
    # The row in FlightLog's column order: t_s, p_true_W, p_est_W, p_sigma_W, p_set_W, yaw_true, yaw_est,
    # thrusts_N, gyro_B, accel_B.
    log.append_row(
        phase,
        [loop.t_s, *tr.p_WB.tolist(), *p_est, *p_sigma, *p_set, yaw_from_rotmat(tr.R_WB), yaw_est,
         *np.asarray(thrusts, dtype=float).tolist(), *gyro, *accel],
        deferred,
    )  # fmt: skip
