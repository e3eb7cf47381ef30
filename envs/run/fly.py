"""Closed-loop flights: a quadrotor that initializes on the ground, takes off and flies on its own VIO.

The runner (``viotb fly``) is a small phase machine on top of :class:`~viotb.envs.run.closed_loop.ClosedLoopSim`:

1. ``ground``: motors off; the estimator initializes statically from the IMU (and sees the camera) while the
   drone sits still. No truth is read by the control path after t = 0.
2. ``takeoff``: a smooth climb from the estimated start to ``takeoff_altitude_m`` above it.
3. ``excite``: a short excitation manoeuvre, flown only if the estimator asks for one
   (``estimator.wants_excitation()``), as a real VIO drone must.
4. ``mission``: the scenario's setpoints, expressed relative to the hover point, in the estimator's frame.

If the estimator reports divergence, the runner stops the motors, records ``diverged`` with the reason and
ends the flight instead of crashing the process. Metrics compare truth with the setpoints mapped into the
truth frame by the 4-DOF (yaw + translation) gauge fixed at initialization, which is used for evaluation only.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from viotb.controllers import SE3Controller, SE3Gains
from viotb.controllers.setpoints import (
    ExcitationManeuver,
    FigureEight,
    HoverPoint,
    Sequence,
    StraightLine,
    Takeoff,
    Waypoints,
)
from viotb.controllers.types import FlatOutput, NavState
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.run.closed_loop import ClosedLoopSim, RigConfig, WindParams
from viotb.envs.sim.vehicle import vehicle_params_from_model
from viotb.vio.health import HealthMonitor
from viotb.vio.lie import rotz, yaw_from_rotmat

ProgressFn = Callable[[float, float], None]

CONTROL_RATE_HZ = 250.0
"""Position/attitude controller rate (Hz): a whole multiple of the 1 kHz physics."""


@dataclass(frozen=True)
class FlyScenario:
    """A closed-loop scenario.

    Attributes:
        name: Registry name.
        description: One line.
        rig: Scene, sensors, wind (the estimator and front end are chosen per run).
        mission: ``"hover"``, ``"waypoints"``, ``"figure8"``, ``"aggressive"``, ``"line"`` (4.5 m along the
            heading at a constant 0.8 m/s, then hover) or ``"loops"`` (three laps of the waypoint square).
        default_seconds: Default flight duration (s), ground phase included.
        takeoff_altitude_m: Climb above the start (m).
    """

    name: str
    description: str
    rig: RigConfig = field(default_factory=RigConfig)
    mission: str = "hover"
    default_seconds: float = 20.0
    takeoff_altitude_m: float = 1.0


def _fly_scenarios() -> dict[str, FlyScenario]:
    """The closed-loop scenario registry."""
    blackout = CameraModelParams(blackout_intervals_s=((12.0, 14.0),))
    items = [
        FlyScenario("fly-hover", "take off and hold a point in the textured room", default_seconds=30.0),
        FlyScenario(
            "fly-waypoints", "fly a square of waypoints at 1.5 m", mission="waypoints", default_seconds=30.0
        ),
        FlyScenario("fly-figure8", "track a 3 x 1.5 m figure-8", mission="figure8", default_seconds=40.0),
        FlyScenario(
            "fly-blackout",
            "hover with a 2 s camera blackout at t = 12 s (coast on the IMU)",
            rig=RigConfig(camera=blackout),
            default_seconds=20.0,
        ),
        FlyScenario(
            "fly-imu-failure",
            "hover until the IMU fails at t = 12 s: the estimator must report it and the runner stop safely",
            rig=RigConfig(imu_fault_at_s=12.0),
            default_seconds=16.0,
        ),
        FlyScenario(
            "fly-blank-wall",
            "hover facing a blank wall (feature poverty)",
            rig=RigConfig(scene="blank_wall", start_p_W_m=(3.0, 0.0, 0.06)),
            default_seconds=20.0,
        ),
        FlyScenario(
            "fly-dark-room", "hover in a dark room", rig=RigConfig(scene="dark_room"), default_seconds=20.0
        ),
        FlyScenario(
            "fly-wind",
            "hold a point against wind gusts (2 N sigma, 1 s correlation)",
            rig=RigConfig(wind=WindParams(mean_force_W_N=(0.5, 0.0, 0.0), gust_sigma_N=2.0)),
            default_seconds=20.0,
        ),
        FlyScenario(
            "fly-gyro-saturation",
            "an aggressive roll manoeuvre with a +-125 deg/s gyro that saturates",
            rig=RigConfig(imu_preset="bmi088-125dps"),
            mission="aggressive",
            default_seconds=20.0,
        ),
    ]
    return {s.name: s for s in items}


FLY_SCENARIOS = _fly_scenarios()


def _register_fly_scenarios() -> None:
    """List the closed-loop scenarios in the shared registry (``viotb scenarios``) as kind ``fly``."""
    from viotb.envs.scenarios.registry import Scenario, is_registered, register

    for sc in list(FLY_SCENARIOS.values()):
        if not is_registered(sc.name):
            register(
                Scenario(
                    name=sc.name,
                    description=sc.description,
                    kind="fly",
                    vehicle="quadrotor",
                    scene=sc.rig.scene,
                    default_seconds=sc.default_seconds,
                    imu_preset=sc.rig.imu_preset,
                    camera=sc.rig.camera,
                )
            )


_register_fly_scenarios()


def get_fly_scenario(name: str) -> FlyScenario:
    """Look up a closed-loop scenario.

    Raises:
        ValueError: Unknown name (lists the known ones).
    """
    if name not in FLY_SCENARIOS:
        import viotb.envs.scenarios.failures  # noqa: F401, PLC0415 (registers the fly-fail-* scenarios)
    if name not in FLY_SCENARIOS:
        raise ValueError(f"unknown closed-loop scenario {name!r}; known: {sorted(FLY_SCENARIOS)}")
    return FLY_SCENARIOS[name]


def _mission(kind: str, hover_W: np.ndarray, yaw: float) -> object:
    """Mission setpoints starting at rest at ``hover_W`` (estimator frame)."""
    if kind == "hover":
        return HoverPoint(hover_W, yaw)
    if kind in ("waypoints", "loops"):
        R = rotz(yaw)
        lap = [[1.5, 0, 0.5], [1.5, 1.5, 0.5], [0, 1.5, 0.5], [0, 0, 0]]
        corners = [[0, 0, 0]] + lap * (3 if kind == "loops" else 1)
        square = [hover_W + R @ np.array(d) for d in corners]
        yaws = np.full(len(square), yaw)
        return Sequence([Waypoints(np.array(square), yaws_rad=yaws, speed_m_s=0.6), HoverPoint(hover_W, yaw)])
    if kind == "line":
        line = StraightLine(hover_W, rotz(yaw) @ np.array([1.0, 0.0, 0.0]), length_m=4.5, speed_m_s=0.8,
                            yaw_rad=yaw)
        return Sequence([line, HoverPoint(line.sample(line.duration_s).p_W, yaw)])
    if kind == "figure8":
        return FigureEight(
            center_xy_m=hover_W[:2],
            size_m=np.array([1.5, 0.75]),
            period_s=12.0,
            altitude_m=float(hover_W[2]),
            yaw_rad=yaw,
        )
    if kind == "aggressive":
        return Sequence(
            [
                ExcitationManeuver(
                    hover_W,
                    amplitude_m=np.array([0.6, 0.6, 0.1]),
                    frequency_hz=np.array([1.2, 1.4, 0.5]),
                    yaw_center_rad=yaw,
                    yaw_amplitude_rad=0.0,
                    duration_s=4.0,
                ),
                HoverPoint(hover_W, yaw),
            ]
        )
    raise ValueError(f"unknown mission {kind!r}")


@dataclass
class FlightLog:
    """Per control tick and per frame records of one flight (lists, converted to arrays at the end)."""

    t_s: list = field(default_factory=list)
    phase: list = field(default_factory=list)
    p_true_W: list = field(default_factory=list)
    p_est_W: list = field(default_factory=list)
    p_sigma_W: list = field(default_factory=list)
    p_set_W: list = field(default_factory=list)
    yaw_true: list = field(default_factory=list)
    yaw_est: list = field(default_factory=list)
    thrusts_N: list = field(default_factory=list)
    gyro_B: list = field(default_factory=list)
    accel_B: list = field(default_factory=list)
    frame_t_s: list = field(default_factory=list)
    frame_features: list = field(default_factory=list)
    frame_conditions: list = field(default_factory=list)


def _gauge(est_R: np.ndarray, est_p: np.ndarray, true_R: np.ndarray, true_p: np.ndarray):
    """4-DOF transform (yaw, translation) mapping estimator-frame points to the truth frame."""
    dyaw = yaw_from_rotmat(true_R) - yaw_from_rotmat(est_R)
    R = rotz(dyaw)
    return R, true_p - R @ est_p


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
) -> tuple[dict, FlightLog]:
    """Fly a closed-loop scenario.

    Args:
        scenario: Name from :data:`FLY_SCENARIOS`.
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

    Returns:
        ``(metrics, log)``; metrics has ``hover_rms_m``, ``max_err_m``, ``ate_posyaw_m``, ``crashed``,
        ``diverged``, ``realtime_factor`` and more.

    Raises:
        ValueError: Unknown scenario/estimator/front end, non-positive ``seconds``.
    """
    if severity is None:
        sc = get_fly_scenario(scenario)
    else:
        from viotb.envs.scenarios.failures import failure_fly_scenario  # noqa: PLC0415

        sc = failure_fly_scenario(scenario, severity)
    total_s = sc.default_seconds if seconds is None else float(seconds)
    if not (total_s > 0.0 and np.isfinite(total_s)):
        raise ValueError(f"seconds must be positive and finite, got {seconds}")
    rig = replace(sc.rig, estimator=estimator, frontend=frontend)
    if online_calibration is not None:
        rig = replace(rig, online_calibration=bool(online_calibration))
    loop = ClosedLoopSim(rig, seed=seed)
    controller = SE3Controller(vehicle_params_from_model(loop.sim.model), gains or SE3Gains())
    log = FlightLog()
    ctrl_dt = 1.0 / CONTROL_RATE_HZ
    phase = "ground"
    plan = None
    plan_t0 = 0.0
    gauge = None
    hover_W = None
    mission_t0 = None
    crashed = diverged = False
    reason = ""
    excited = False
    init_time = None
    thrusts = np.zeros(4)
    n_frames_seen = 0
    monitor = HealthMonitor()
    last_imu_seen = None
    wall0 = time.perf_counter()
    while loop.t_s < total_s - 1e-9:
        est = loop.estimate()
        health = loop.health()
        if health.diverged or loop.estimator_failure:
            # Stop safely: motors off, flight ended, the reason reported (no exception escapes).
            diverged, reason = True, health.reason or f"estimator failed: {loop.estimator_failure}"
            break
        if phase == "ground" and est is not None:
            init_time = loop.t_s
            tr = loop.truth()
            gauge = _gauge(est.R_WB, est.p_WB, tr.R_WB, tr.p_WB)
            yaw0 = yaw_from_rotmat(est.R_WB)
            hover_W = est.p_WB + np.array([0.0, 0.0, sc.takeoff_altitude_m])
            plan = Takeoff(est.p_WB, float(hover_W[2]), duration_s=3.0, yaw_rad=yaw0)
            plan_t0, phase = loop.t_s, "takeoff"
        elif phase in ("takeoff", "excite") and loop.t_s - plan_t0 >= plan.duration_s:
            yaw0 = plan.sample(plan.duration_s).yaw_rad
            wants = getattr(loop.estimator, "wants_excitation", None)
            if phase == "takeoff" and wants is not None and wants():
                plan, plan_t0, phase, excited = (
                    ExcitationManeuver(hover_W, yaw_center_rad=yaw0),
                    loop.t_s,
                    "excite",
                    True,
                )
            else:
                plan, plan_t0, phase = _mission(sc.mission, hover_W, yaw0), loop.t_s, "mission"
                mission_t0 = loop.t_s
        setpoint: FlatOutput | None = plan.sample(loop.t_s - plan_t0) if plan is not None else None
        if phase == "ground" or est is None or setpoint is None:
            thrusts = np.zeros(4)
        else:
            cmd = controller.update(loop.t_s, NavState.from_estimate(est), setpoint)
            thrusts = cmd.thrusts_N
        loop.advance(thrusts, ctrl_dt)
        tr = loop.truth()
        airborne = phase != "ground" and (loop.t_s - plan_t0 > 1.0 or phase != "takeoff")
        if loop.crashed(airborne):
            crashed = True
        _log_tick(log, loop, phase, est, setpoint, gauge, tr, thrusts)
        if loop.last_imu is not None and loop.last_imu is not last_imu_seen:
            last_imu_seen = loop.last_imu
            monitor.observe_imu(last_imu_seen)
        if loop.frames_delivered != n_frames_seen:
            n_frames_seen = loop.frames_delivered
            h = loop.health()
            monitor.observe_frame(loop.t_s, h, loop.estimate())
            if "divergence" in monitor.active() and not h.diverged:
                # The monitor's bound is tighter than the filter's own (a drone flying blind on the IMU alone
                # is lost long before its covariance explodes): stop the flight the same way.
                cond = next(c for c in monitor.report() if c.name == "divergence")
                diverged, reason = True, f"health monitor: {cond.evidence}"
            log.frame_t_s.append(loop.t_s)
            log.frame_features.append(h.tracked_features)
            log.frame_conditions.append(h.conditions)
        if on_tick is not None:
            on_tick(loop, log)
        if progress is not None:
            progress(loop.t_s, total_s)
        if crashed or diverged:
            break
    wall = time.perf_counter() - wall0
    loop.close()
    metrics = _metrics(log, mission_t0, init_time)
    metrics.update(_blackout_metrics(log, rig.camera.blackout_intervals_s))
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
            "excitation_flown": excited,
            "init_time_s": init_time,
            "realtime_factor": float(loop.t_s / wall) if wall > 0 else float("inf"),
            "frames_delivered": loop.frames_delivered,
            "frames_dropped": loop.frames_dropped,
            "conditions": [
                {"name": c.name, "t_s_first": c.t_s_first, "evidence": c.evidence} for c in monitor.report()
            ],
        }
    )
    return metrics, log


def _log_tick(log: FlightLog, loop: ClosedLoopSim, phase, est, setpoint, gauge, tr, thrusts) -> None:
    """Append one control tick to the log (setpoint and estimate mapped to the truth frame by the gauge)."""
    nan3 = np.full(3, np.nan)
    log.t_s.append(loop.t_s)
    log.phase.append(phase)
    log.p_true_W.append(tr.p_WB)
    log.yaw_true.append(yaw_from_rotmat(tr.R_WB))
    log.thrusts_N.append(np.array(thrusts, dtype=float))
    imu = loop.last_imu
    log.gyro_B.append(imu.gyro_B_rad_s if imu is not None else nan3)
    log.accel_B.append(imu.accel_B_m_s2 if imu is not None else nan3)
    if est is None or gauge is None:
        log.p_est_W.append(nan3)
        log.p_sigma_W.append(nan3)
        log.yaw_est.append(np.nan)
    else:
        R_g, t_g = gauge
        log.p_est_W.append(R_g @ est.p_WB + t_g)
        cov_p = R_g @ est.cov[3:6, 3:6] @ R_g.T
        log.p_sigma_W.append(np.sqrt(np.clip(np.diag(cov_p), 0.0, None)))
        log.yaw_est.append(yaw_from_rotmat(R_g @ est.R_WB))
    if setpoint is None or gauge is None:
        log.p_set_W.append(nan3)
    else:
        log.p_set_W.append(gauge[0] @ setpoint.p_W + gauge[1])


def _blackout_metrics(log: FlightLog, blackouts: tuple) -> dict:
    """Excursion during each camera blackout (+1 s) and whether tracking came back after it.

    Returns ``{}`` without blackouts, else ``blackout_excursion_m`` (largest truth-to-setpoint distance
    from the start of a blackout to 1 s after its end), ``blackout_est_err_m`` (largest estimate error in
    that span) and ``blackout_recovered`` (every blackout is followed, within 1 s, by a frame with >= 20
    tracked features).
    """
    if not blackouts:
        return {}
    t = np.asarray(log.t_s)
    err_set = np.linalg.norm(np.asarray(log.p_true_W) - np.asarray(log.p_set_W), axis=1)
    err_est = np.linalg.norm(np.asarray(log.p_est_W) - np.asarray(log.p_true_W), axis=1)
    ft, nf = np.asarray(log.frame_t_s), np.asarray(log.frame_features)
    excursion, est_err, recovered = 0.0, 0.0, True
    for a, b in blackouts:
        m = (t >= a) & (t <= b + 1.0)
        if not np.any(m):
            recovered = False
            continue
        excursion = max(excursion, float(np.nanmax(err_set[m])))
        est_err = max(est_err, float(np.nanmax(err_est[m])))
        after = (ft > b) & (ft <= b + 1.0)
        recovered = recovered and bool(np.any(nf[after] >= 20))
    return {"blackout_excursion_m": excursion, "blackout_est_err_m": est_err, "blackout_recovered": recovered}


def _metrics(log: FlightLog, mission_t0: float | None, init_time: float | None) -> dict:
    """Tracking and estimation metrics of a flight log."""
    t = np.asarray(log.t_s)
    p_true = np.asarray(log.p_true_W)
    p_est = np.asarray(log.p_est_W)
    p_set = np.asarray(log.p_set_W)
    out: dict = {"hover_rms_m": None, "max_err_m": None, "ate_posyaw_m": None, "est_rms_m": None}
    if mission_t0 is not None:
        m = t >= mission_t0
        err = np.linalg.norm(p_true[m] - p_set[m], axis=1)
        if err.size:
            out["hover_rms_m"] = float(np.sqrt(np.mean(err**2)))
            out["max_err_m"] = float(np.max(err))
    ok = np.all(np.isfinite(p_est), axis=1)
    if init_time is not None and ok.sum() >= 3:
        from viotb.vio.metrics import align_umeyama

        est_err = np.linalg.norm(p_est[ok] - p_true[ok], axis=1)
        out["est_rms_m"] = float(np.sqrt(np.mean(est_err**2)))
        al = align_umeyama(p_est[ok], p_true[ok], "posyaw")
        aligned = (al.s * (al.R @ p_est[ok].T)).T + al.t
        out["ate_posyaw_m"] = float(np.sqrt(np.mean(np.sum((aligned - p_true[ok]) ** 2, axis=1))))
    return out
