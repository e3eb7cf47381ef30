"""The lesson's failure modes as scenarios with a severity knob, and a report that names and fixes each.

Each :class:`FailureSpec` is registered three ways:

* as an open-loop ``record`` scenario (``viotb record fail-...``) in :mod:`viotb.envs.scenarios.registry`,
* as a closed-loop :class:`~viotb.envs.run.fly.FlyScenario` in ``FLY_SCENARIOS`` where the rig can express it
  (:func:`failure_fly_scenarios`),
* and as a fast in-memory stream (:func:`synthesize_stream`: scripted truth -> IMU model -> projected scene
  landmarks, no rendering) that :func:`failure_report` runs through the MSCKF with a
  :class:`~viotb.vio.health.HealthMonitor`.

Streams start with ``still_s`` seconds at rest (the trajectories start with zero derivatives, so holding the
first sample is smooth) so that the estimator's static initializer can start it.

:func:`failure_report` runs the failure at a severity, runs the *fix* of the lesson's catalog (online
time-offset / extrinsic calibration, an excitation manoeuvre, coasting on the IMU, a calibrated IMU or a
sensor rated for the motion), writes an error-vs-time PNG and returns the monitor's conditions and the
numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.sim.faults import SensorFaults
from viotb.envs.sim.imu_model import ImuModel, imu_preset
from viotb.envs.scenarios.registry import Scenario, is_registered, register
from viotb.envs.scenarios.motions import TRAJECTORY_FACTORIES, MotionParams, Trajectory
from viotb.vio.camera import CameraCalibration
from viotb.vio.health import HealthMonitor, HealthParams, MonitoredRun, monitor_run
from viotb.vio.initialization import InitResult
from viotb.vio.lie import rotmat_to_quat_wxyz
from viotb.vio.metrics import align_umeyama, scale_error_pct
from viotb.vio.msckf import MsckfEstimator, MsckfParams
from viotb.vio.types import CameraFrame, ImuSeries, TrajectoryArrays
from viotb.vio.window import WindowEstimator, WindowParams

NO_EXCITATION_START_S = 3.5
"""Stream time (s) at which ``fail-no-excitation`` starts the estimator: the line's cruise begins (the
ramp runs from the end of the 1.5 s still start to 3.5 s)."""


@dataclass(frozen=True)
class StreamConfig:
    """One in-memory run (all physical knobs of a failure).

    Attributes:
        motion: Name in ``TRAJECTORY_FACTORIES``.
        seconds: Duration (s) of the motion (after the still start).
        speed_scale: Multiplies the motion's phase rate.
        imu_preset: IMU part.
        scene: Scene whose textured surfaces carry the landmarks.
        still_s: Seconds at rest before the motion (for static initialization).
        camera_rate_hz: Frame rate (Hz).
        time_offset_s: True clock offset, ``t_imu = t_cam + offset`` (s).
        faults: Calibration / IMU errors (:class:`~viotb.envs.sim.faults.SensorFaults`).
        landmark_count: Landmarks in the scene.
        blackout_s: Camera blackout interval (start, end) in seconds of stream time, or None.
        pixel_sigma_px: Pixel noise (px) of the projected features.
        start_in_flight_s: When set, the estimator is not initialized at rest: at this stream time (s) it is
            started in flight (as by a dynamic initializer) from the true pose, the true biases and the true
            velocity times ``1 + initial_scale_error`` (with a monocular camera the metric scale lives in the
            velocity), with an honest prior: velocity sigma ``initial_scale_error x speed`` (at least
            2 cm/s) per axis. The monitor still sees the IMU from the first sample.
        initial_scale_error: Relative scale (speed) error of that in-flight start.
    """

    motion: str = "hover"
    seconds: float = 12.0
    speed_scale: float = 1.0
    imu_preset: str = "adis16448"
    scene: str = "textured_room"
    still_s: float = 1.5
    camera_rate_hz: float = 20.0
    time_offset_s: float = 0.0
    faults: SensorFaults = field(default_factory=SensorFaults)
    landmark_count: int = 1500
    blackout_s: tuple[float, float] | None = None
    pixel_sigma_px: float = 0.5
    start_in_flight_s: float | None = None
    initial_scale_error: float = 0.0


@dataclass
class Stream:
    """A synthesized run: IMU readings, frames, truth, and the calibration the estimator is given.

    ``external_init`` (an :class:`~viotb.vio.initialization.InitResult`) is the in-flight start of
    ``StreamConfig.start_in_flight_s``, or None for the estimator's own initialization at rest.
    """

    imu: ImuSeries
    frames: list[CameraFrame]
    truth: TrajectoryArrays
    calib_true: CameraCalibration
    calib_given: CameraCalibration
    noise: object
    time_offset_s: float
    pixel_sigma_px: float = 0.5
    external_init: InitResult | None = None


@dataclass(frozen=True)
class _Delayed:
    """Trajectory held at its first sample for ``still_s`` seconds (picklable)."""

    base: Trajectory
    still_s: float

    def sample_many(self, t_s: np.ndarray):  # noqa: D102
        return self.base.sample_many(np.maximum(np.asarray(t_s, dtype=float) - self.still_s, 0.0))


def synthesize_stream(cfg: StreamConfig, seed: int = 0) -> Stream:
    """Build IMU readings and simulated-feature frames for ``cfg`` without rendering.

    Steps: sample the truth at the IMU rate, pass it through the IMU model (plus the injected bias/scale
    errors), project the scene landmarks at the exposure instants ``k / rate`` (IMU clock) and stamp the
    frames ``t_cam = t_imu - time_offset_s``.

    Raises:
        ValueError: Unknown motion or a non-positive duration.
    """
    if cfg.motion not in TRAJECTORY_FACTORIES:
        known = sorted(TRAJECTORY_FACTORIES)
        raise ValueError(f"StreamConfig.motion: unknown motion {cfg.motion!r}; known: {known}")
    if not cfg.seconds > 0.0:
        raise ValueError(f"StreamConfig.seconds must be > 0, got {cfg.seconds}")
    from viotb.envs.sim.landmarks import project_landmarks, scene_landmarks  # noqa: PLC0415 (imports mujoco)
    from viotb.envs.sim.render import camera_calibration  # noqa: PLC0415
    from viotb.models import load_model  # noqa: PLC0415
    from viotb.models.constants import ONBOARD_CAMERA, VEHICLE_BODIES  # noqa: PLC0415

    imu_seq, lm_seq, px_seq = np.random.SeedSequence(seed).spawn(3)
    traj = _Delayed(TRAJECTORY_FACTORIES[cfg.motion](MotionParams(cfg.seconds, speed_scale=cfg.speed_scale)),
                    cfg.still_s)
    total_s = cfg.seconds + cfg.still_s
    params = imu_preset(cfg.imu_preset)
    t_imu = np.arange(int(np.floor(total_s * params.rate_hz + 1e-9)) + 1) / params.rate_hz
    truth = traj.sample_many(t_imu)
    omega, f_B = cfg.faults.imu_input(truth.omega_B, truth.specific_force_B)
    imu, bias_g, bias_a = ImuModel(params, np.random.default_rng(imu_seq)).measure_series_with_biases(
        t_imu, omega, f_B
    )

    model = load_model("quadrotor", cfg.scene)
    calib = camera_calibration(model, ONBOARD_CAMERA, VEHICLE_BODIES["quadrotor"], 320, 240,
                               cfg.time_offset_s, cfg.camera_rate_hz)
    landmarks = scene_landmarks(model, np.random.default_rng(lm_seq), cfg.landmark_count)
    rng = np.random.default_rng(px_seq)
    t_exp = np.arange(1, int(np.floor(total_s * cfg.camera_rate_hz))) / cfg.camera_rate_hz
    t_exp = t_exp[t_exp > cfg.time_offset_s + 1e-6]
    cams = traj.sample_many(t_exp)
    frames = []
    for k, t in enumerate(t_exp):
        R_WB, p_WB = cams.R_WB[k], cams.p_WB[k]
        blank = cfg.blackout_s is not None and cfg.blackout_s[0] <= t < cfg.blackout_s[1]
        obs = project_landmarks(
            landmarks[:0] if blank else landmarks, R_WB @ calib.R_BC, p_WB + R_WB @ calib.p_BC, calib.camera,
            rng, cfg.pixel_sigma_px,
        )
        frames.append(CameraFrame(t_s=float(t - cfg.time_offset_s), features=obs))
    given = cfg.faults.told_calibration(calib)
    gt = TrajectoryArrays(t_imu, truth.p_WB, np.array([rotmat_to_quat_wxyz(R) for R in truth.R_WB]),
                          truth.v_WB)
    init = None
    if cfg.start_in_flight_s is not None:
        k = int(np.searchsorted(t_imu, cfg.start_in_flight_s))
        if k >= len(t_imu) - 1:
            raise ValueError(f"StreamConfig.start_in_flight_s={cfg.start_in_flight_s} is beyond the stream "
                             f"({total_s} s)")
        sigma_v = max(abs(cfg.initial_scale_error) * float(np.linalg.norm(truth.v_WB[k])), 0.02)
        init = InitResult(
            t_s=float(t_imu[k]), R_WB=truth.R_WB[k], p_WB=truth.p_WB[k],
            v_WB=truth.v_WB[k] * (1.0 + cfg.initial_scale_error),
            gyro_bias_rad_s=bias_g[k] + cfg.faults.extra_gyro_bias_rad_s, accel_bias_m_s2=bias_a[k],
            method="in-flight",
            cov_diag=np.repeat([1e-4**2, 1e-3**2, sigma_v**2, 1e-3**2, 0.02**2], 3),
        )
    return Stream(imu, frames, gt, calib, given, params.noise, cfg.time_offset_s, cfg.pixel_sigma_px, init)


# ----------------------------------------------------------------------------------------------- specs


@dataclass(frozen=True)
class FailureSpec:
    """A failure mode of the lesson's catalog.

    Attributes:
        name: Scenario name (``fail-...``).
        condition: Monitor condition that should name it (or "" when none is expected).
        description: Symptom / cause, one line.
        fix: The fix of the catalog that :func:`failure_report` applies.
        diagnosis: Condition the monitor should name on the *fixed* run ("" when none): with both online
            calibrations on, the calibration that moves tells a time offset from an extrinsic error.
    """

    name: str
    condition: str
    description: str
    fix: str
    diagnosis: str = ""

    def config(self, severity: float = 1.0) -> StreamConfig:
        """The failing run at ``severity`` (0 = nominal, 1 = default, larger = worse)."""
        s = float(severity)
        if not (np.isfinite(s) and s >= 0.0):
            raise ValueError(f"severity must be finite and >= 0, got {severity}")
        n = self.name
        if n == "fail-bad-init":
            return StreamConfig(
                faults=SensorFaults(extra_gyro_bias_rad_s=0.3 * s, accel_scale_error=0.05 * s)
            )
        if n == "fail-no-excitation":
            return StreamConfig(motion="line", seconds=8.0, speed_scale=1.0 + 0.5 * s,
                                start_in_flight_s=NO_EXCITATION_START_S, initial_scale_error=0.1 * s)
        if n == "fail-time-offset":
            return StreamConfig(motion="figure8", seconds=12.0, time_offset_s=0.01 * s, speed_scale=1.0 + s,
                                faults=SensorFaults(assumed_time_offset_s=0.0))
        if n == "fail-extrinsic":
            return StreamConfig(motion="figure8", seconds=12.0,
                                faults=SensorFaults(extrinsic_error_rad=float(np.deg2rad(2.0)) * s),
                                speed_scale=1.0 + s)
        if n == "fail-feature-poverty":
            return StreamConfig(motion="hover", landmark_count=max(int(1500 * (1.0 - 0.98 * min(s, 1.0))), 8),
                                blackout_s=(6.0, 6.0 + 2.0 * s))
        if n == "fail-gyro-saturation":
            return StreamConfig(motion="aggressive", seconds=12.0, imu_preset="bmi088-125dps",
                                speed_scale=0.5 + 0.5 * s)
        if n == "fail-long-loop":
            return StreamConfig(motion="long-loop", seconds=40.0 + 40.0 * s)
        raise ValueError(f"unknown failure {n!r}")

    def fixed(self, severity: float = 1.0) -> tuple[StreamConfig, MsckfParams]:
        """The run with the catalog's fix applied, and the MSCKF settings of the fix."""
        cfg = self.config(severity)
        prm = MsckfParams(frontend="sim", pixel_sigma_px=cfg.pixel_sigma_px)
        n = self.name
        if n == "fail-bad-init":
            cfg = replace(cfg, faults=SensorFaults())
        elif n == "fail-no-excitation":
            cfg = replace(cfg, motion="figure8", speed_scale=1.0)
        elif n in ("fail-time-offset", "fail-extrinsic"):
            prm = prm.with_online_calibration()
        elif n == "fail-gyro-saturation":
            cfg = replace(cfg, imu_preset="bmi088")
        elif n == "fail-feature-poverty":
            cfg = replace(cfg, landmark_count=1500)  # texture back: coast through the gap
        return cfg, prm


FAILURES: dict[str, FailureSpec] = {
    f.name: f
    for f in (
        FailureSpec("fail-bad-init", "initialization_failure",
                    "turn-on gyro bias 0.3 rad/s and 5 % accelerometer scale: wrong gravity / bias at init",
                    "calibrated IMU (re-initialize after calibration)"),
        FailureSpec("fail-no-excitation", "insufficient_excitation",
                    "started in flight with a 10 % scale error, then a constant-velocity line: scale "
                    "unobservable, the error stays and the position error grows with distance",
                    "excitation manoeuvre (the same start on a figure-8)"),
        FailureSpec("fail-time-offset", "time_sync_or_extrinsic_suspected",
                    "10 ms camera-IMU clock offset on a fast figure-8: error grows with speed",
                    "online time-offset and extrinsic calibration", "time_offset_miscalibrated"),
        FailureSpec("fail-extrinsic", "time_sync_or_extrinsic_suspected",
                    "2 deg camera-IMU rotation error on a fast figure-8",
                    "online time-offset and extrinsic calibration", "extrinsic_miscalibrated"),
        FailureSpec("fail-feature-poverty", "feature_poverty",
                    "30 landmarks and a 2 s blackout (blank wall / dark room)",
                    "coast on the IMU (propagate only)"),
        FailureSpec("fail-gyro-saturation", "imu_saturation",
                    "aggressive manoeuvre past a +-125 deg/s gyro",
                    "an IMU rated for the motion (+-2000 deg/s)"),
        FailureSpec("fail-long-loop", "",
                    "long loop back to the start: odometry drift (loop closure is out of scope)",
                    "none in odometry (needs loop closure)"),
    )
}
"""The failure scenarios by name."""


def failure_record_scenario(name: str, severity: float = 1.0) -> Scenario:
    """Open-loop ``record`` scenario of failure ``name`` at ``severity``.

    The recording holds the motion, the camera timing and the sensor faults (wrong calibration file, faulty
    IMU); an in-flight start (``fail-no-excitation``) is the stream runner's and not part of a dataset.

    Raises:
        ValueError: Unknown failure or a bad severity.
    """
    if name not in FAILURES:
        raise ValueError(f"unknown failure scenario {name!r}; known: {sorted(FAILURES)}")
    spec = FAILURES[name]
    cfg = spec.config(severity)
    cam = CameraModelParams(rate_hz=cfg.camera_rate_hz, pixel_noise_std=2.0, time_offset_s=cfg.time_offset_s,
                            blackout_intervals_s=(cfg.blackout_s,) if cfg.blackout_s else ())
    scene = "blank_wall" if spec.name == "fail-feature-poverty" else cfg.scene
    return Scenario(spec.name, spec.description, "record", "quadrotor", scene, cfg.seconds, cfg.imu_preset,
                    cam, _MotionFactory(cfg.motion, cfg.speed_scale), still_start_s=cfg.still_s,
                    faults=cfg.faults)


def _register_record_scenarios() -> None:
    """Register each failure (default severity) as an open-loop ``record`` scenario."""
    for spec in FAILURES.values():
        if not is_registered(spec.name):
            register(failure_record_scenario(spec.name, 1.0))


@dataclass(frozen=True)
class _MotionFactory:
    """Picklable ``duration_s -> Trajectory`` with a speed scale."""

    motion: str
    speed_scale: float = 1.0

    def __call__(self, duration_s: float) -> Trajectory:
        return TRAJECTORY_FACTORIES[self.motion](MotionParams(duration_s, speed_scale=self.speed_scale))


FLY_SEVERITY_KNOBS = ("fly-fail-bad-init", "fly-fail-time-offset", "fly-fail-extrinsic",
                      "fly-fail-feature-poverty")
"""Closed-loop failures whose rig follows the severity (the stream's faults, offset or blackout length)."""


def failure_fly_scenarios(severity: float = 1.0) -> dict:
    """Closed-loop versions of the failures that the rig can express, as ``FlyScenario`` objects.

    ``severity`` scales the rigs of :data:`FLY_SEVERITY_KNOBS` as :meth:`FailureSpec.config` scales the
    streams (the IMU faults, the clock offset, the extrinsic error; the blackout lasts ``3 x severity`` s);
    the others do not depend on it.
    """
    from viotb.envs.run.closed_loop import RigConfig  # noqa: PLC0415
    from viotb.envs.run.fly import FlyScenario  # noqa: PLC0415

    sev = float(severity)
    offset = FAILURES["fail-time-offset"].config(sev)
    blackout = ((10.0, 10.0 + 3.0 * sev),) if sev > 0.0 else ()
    items = [
        FlyScenario("fly-fail-bad-init",
                    "hover with an out-of-spec IMU: +0.3 rad/s gyro bias on every axis, 5 % accel scale",
                    rig=RigConfig(faults=FAILURES["fail-bad-init"].config(sev).faults), default_seconds=20.0),
        FlyScenario("fly-fail-time-offset",
                    "figure-8 with a 10 ms camera clock offset the estimator is not told (fix: --calibrate)",
                    rig=RigConfig(camera=CameraModelParams(time_offset_s=offset.time_offset_s),
                                  faults=offset.faults),
                    mission="figure8", default_seconds=25.0),
        FlyScenario("fly-fail-extrinsic",
                    "figure-8 with a 2 deg error in the camera-IMU rotation given to the estimator (fix: "
                    "--calibrate)",
                    rig=RigConfig(faults=FAILURES["fail-extrinsic"].config(sev).faults),
                    mission="figure8",
                    default_seconds=25.0),
        FlyScenario("fly-fail-no-excitation",
                    "4.5 m straight line at a constant 0.8 m/s: no acceleration while cruising",
                    rig=RigConfig(start_p_W_m=(-2.5, 0.0, 0.06)), mission="line", default_seconds=20.0),
        FlyScenario("fly-fail-feature-poverty", "hover in front of a blank wall with a 3 s blackout",
                    rig=RigConfig(scene="blank_wall", start_p_W_m=(3.0, 0.0, 0.06),
                                  camera=CameraModelParams(blackout_intervals_s=blackout)),
                    default_seconds=20.0),
        FlyScenario("fly-fail-gyro-saturation", "aggressive flight with a +-125 deg/s gyro",
                    rig=RigConfig(imu_preset="bmi088-125dps"), mission="aggressive", default_seconds=20.0),
        FlyScenario("fly-fail-long-loop", "three laps of a 1.5 m square back to the start: odometry drift",
                    mission="loops", default_seconds=50.0),
    ]
    return {s.name: s for s in items}


def failure_fly_scenario(name: str, severity: float = 1.0) -> object:
    """The ``FlyScenario`` of closed-loop failure ``name`` at ``severity``.

    Raises:
        ValueError: Unknown name, or a severity other than 1 for a scenario without a knob.
    """
    scenarios = failure_fly_scenarios(severity)
    if name not in scenarios:
        raise ValueError(f"unknown closed-loop failure {name!r}; known: {sorted(scenarios)}")
    if name not in FLY_SEVERITY_KNOBS and float(severity) != 1.0:
        raise ValueError(
            f"{name} has no severity knob in closed loop; the ones that do: {FLY_SEVERITY_KNOBS}"
        )
    return scenarios[name]


def register_fly_failures() -> None:
    """Add :func:`failure_fly_scenarios` to ``viotb.envs.run.fly.FLY_SCENARIOS`` and the shared registry."""
    from viotb.envs.run import fly  # noqa: PLC0415

    for name, sc in failure_fly_scenarios().items():
        fly.FLY_SCENARIOS.setdefault(name, sc)
    fly._register_fly_scenarios()  # noqa: SLF001 (idempotent: skips registered names)


_register_record_scenarios()
register_fly_failures()


# ----------------------------------------------------------------------------------------------- running


@dataclass
class RunResult:
    """One monitored MSCKF run over a stream."""

    t_s: np.ndarray
    err_m: np.ndarray
    run: MonitoredRun
    stream: Stream
    metrics: dict = field(default_factory=dict)


def run_stream(
    stream: Stream, params: MsckfParams | None = None, health: HealthParams | None = None,
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
        est = WindowEstimator(stream.calib_given, stream.noise,
                              WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px))
    else:
        raise ValueError(f"run_stream: estimator must be 'msckf' or 'window', got {estimator!r}")
    monitor = HealthMonitor(health)
    imu, frames = stream.imu, stream.frames
    if stream.external_init is not None:
        imu, frames = _start_in_flight(est, monitor, stream)
    run = monitor_run(est, imu, frames, stream.time_offset_s, monitor)
    ok = [i for i, e in enumerate(run.estimates) if e is not None and np.all(np.isfinite(e.p_WB))]
    out = RunResult(np.zeros(0), np.zeros(0), run, stream)
    m: dict = {"init_time_s": None, "ate_m": float("nan"), "final_err_m": float("nan"),
               "scale_error_pct": float("nan"), "diverged": any(h.diverged for h in run.health),
               "time_offset_est_s": None}
    if len(ok) >= 3:
        t = np.array([run.estimates[i].t_s for i in ok])
        p_est = np.array([run.estimates[i].p_WB for i in ok])
        gt = stream.truth
        p_gt = np.stack([np.interp(t, gt.t_s, gt.p_WB[:, j]) for j in range(3)], axis=1)
        al = align_umeyama(p_est, p_gt, "posyaw")
        err = np.linalg.norm(al.apply(p_est) - p_gt, axis=1)
        out.t_s, out.err_m = t, err
        m.update(init_time_s=float(t[0]), ate_m=float(np.sqrt(np.mean(err**2))), final_err_m=float(err[-1]),
                 scale_error_pct=float(scale_error_pct(p_est, p_gt)))
        st = getattr(est, "state", None)
        if st is not None and prm.estimate_time_offset:
            m["time_offset_est_s"] = float(st.time_offset_s)
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
        sig.append(float(np.sqrt(max(d @ est.cov[6:9, 6:9] @ d, 0.0))) / unit)
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
    g = np.stack([np.interp(t, gt.t_s, gt.p_WB[:, j]) for j in range(3)], axis=1)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(g, axis=0), axis=1))])
    return s, np.linalg.norm((p - p[0]) - (g - g[0]), axis=1)


def _plot(path: Path, title: str, runs: dict[str, RunResult]) -> None:
    """Position error vs time of each run (PNG)."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for label, r in runs.items():
        ax.plot(r.t_s, r.err_m, label=label)
        for c in r.run.monitor.report():
            ax.axvline(c.t_s_first, ls=":", lw=0.8, color="gray")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("position error (m, 4-DOF aligned)")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def failure_report(name: str, out_dir: Path | str, seed: int = 0, severity: float = 1.0) -> dict:
    """Run failure ``name`` and its fix, plot error vs time and report what the monitor said.

    Args:
        name: A key of :data:`FAILURES`.
        out_dir: Folder for ``<name>_error.png`` (created).
        seed: Seed of the stream.
        severity: Failure severity (0 = nominal).

    Returns:
        ``{"name", "severity", "seed", "expected_condition", "conditions": [{name, t_s_first, evidence}],
        "detected", "detection_time_s", "fix", "failing": metrics, "fixed": metrics, "fixed_conditions",
        "diagnosis", "diagnosis_time_s", "plot"}`` (``diagnosis``: the condition the fixed run should name).
    """
    if name not in FAILURES:
        raise ValueError(f"unknown failure {name!r}; known: {sorted(FAILURES)}")
    spec = FAILURES[name]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bad = run_stream(synthesize_stream(spec.config(severity), seed))
    cfg_fix, prm_fix = spec.fixed(severity)
    good = run_stream(synthesize_stream(cfg_fix, seed), prm_fix)
    plot = out / f"{name}_error.png"
    _plot(plot, f"{name} (severity {severity})", {"failing": bad, f"fix: {spec.fix}": good})
    conds = bad.run.monitor.report()
    return {
        "name": name,
        "severity": float(severity),
        "seed": int(seed),
        "expected_condition": spec.condition,
        "conditions": [{"name": c.name, "t_s_first": c.t_s_first, "evidence": c.evidence} for c in conds],
        "detected": spec.condition in {c.name for c in conds} if spec.condition else None,
        "detection_time_s": bad.run.monitor.first_time(spec.condition) if spec.condition else None,
        "fix": spec.fix,
        "failing": bad.metrics,
        "fixed": good.metrics,
        "fixed_conditions": [c.name for c in good.run.monitor.report()],
        "diagnosis": spec.diagnosis or None,
        "diagnosis_time_s": good.run.monitor.first_time(spec.diagnosis) if spec.diagnosis else None,
        "plot": str(plot),
    }
