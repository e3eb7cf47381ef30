"""Scenarios as fast in-memory sensor streams: scripted truth -> IMU model -> projected scene landmarks.

No rendering: :func:`synthesize_stream` samples a motion of the library at the IMU rate, passes it through the
IMU model (with the configured faults), projects the scene's landmarks at each exposure and stamps the frames
on the camera clock. The failure catalog and the Monte Carlos run estimators on these streams
(``run.failure_runner``). Streams start with ``still_s`` seconds at rest so that a static initializer can
start them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from viotb.envs.scenarios.motions import TRAJECTORY_FACTORIES, MotionParams, Trajectory
from viotb.envs.sim.faults import SensorFaults
from viotb.envs.sim.imu_model import ImuModel, imu_preset
from viotb.vio.camera import CameraCalibration
from viotb.vio.initialization import InitResult
from viotb.vio.lie import rotmat_to_quat_wxyz
from viotb.vio.types import CameraFrame, ImuSeries, TrajectoryArrays

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
        start_at_s: Drop the first ``start_at_s`` seconds of the run (its still start included): the
            stream begins there, moving, and lasts ``still_s + seconds - start_at_s``; the motion itself is
            the one of ``start_at_s = 0`` (a moving start for the estimator's own initializer).
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
    start_at_s: float = 0.0


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
    """Trajectory held at its first sample for ``still_s`` seconds, entered at ``start_s`` (picklable)."""

    base: Trajectory
    still_s: float
    start_s: float = 0.0

    def sample_many(self, t_s: np.ndarray):  # noqa: D102
        t = np.asarray(t_s, dtype=float) + self.start_s
        return self.base.sample_many(np.maximum(t - self.still_s, 0.0))


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
    if not 0.0 <= cfg.start_at_s < cfg.seconds + cfg.still_s:
        raise ValueError(
            f"StreamConfig.start_at_s must lie in [0, still_s + seconds = {cfg.seconds + cfg.still_s}) s, "
            f"got {cfg.start_at_s}"
        )
    from viotb.envs.sim.landmarks import project_landmarks, scene_landmarks  # (imports mujoco)
    from viotb.envs.sim.render import camera_calibration
    from viotb.models import load_model
    from viotb.models.constants import ONBOARD_CAMERA, VEHICLE_BODIES

    imu_seq, lm_seq, px_seq = np.random.SeedSequence(seed).spawn(3)
    traj = _Delayed(
        TRAJECTORY_FACTORIES[cfg.motion](MotionParams(cfg.seconds, speed_scale=cfg.speed_scale)),
        cfg.still_s,
        cfg.start_at_s,
    )
    total_s = cfg.seconds + cfg.still_s - cfg.start_at_s
    params = imu_preset(cfg.imu_preset)
    t_imu = np.arange(int(np.floor(total_s * params.rate_hz + 1e-9)) + 1) / params.rate_hz
    truth = traj.sample_many(t_imu)
    omega, f_B = cfg.faults.imu_input(truth.omega_B, truth.specific_force_B)
    imu, bias_g, bias_a = ImuModel(params, np.random.default_rng(imu_seq)).measure_series_with_biases(
        t_imu, omega, f_B
    )

    model = load_model("quadrotor", cfg.scene)
    calib = camera_calibration(
        model, ONBOARD_CAMERA, VEHICLE_BODIES["quadrotor"], 320, 240, cfg.time_offset_s, cfg.camera_rate_hz
    )
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
            landmarks[:0] if blank else landmarks,
            R_WB @ calib.R_BC,
            p_WB + R_WB @ calib.p_BC,
            calib.camera,
            rng,
            cfg.pixel_sigma_px,
        )
        frames.append(CameraFrame(t_s=float(t - cfg.time_offset_s), features=obs))
    given = cfg.faults.told_calibration(calib)
    gt = TrajectoryArrays(
        t_imu, truth.p_WB, np.array([rotmat_to_quat_wxyz(R) for R in truth.R_WB]), truth.v_WB
    )
    init = None
    if cfg.start_in_flight_s is not None:
        k = int(np.searchsorted(t_imu, cfg.start_in_flight_s))
        if k >= len(t_imu) - 1:
            raise ValueError(
                f"StreamConfig.start_in_flight_s={cfg.start_in_flight_s} is beyond the stream ({total_s} s)"
            )
        sigma_v = max(abs(cfg.initial_scale_error) * float(np.linalg.norm(truth.v_WB[k])), 0.02)
        init = InitResult(
            t_s=float(t_imu[k]),
            R_WB=truth.R_WB[k],
            p_WB=truth.p_WB[k],
            v_WB=truth.v_WB[k] * (1.0 + cfg.initial_scale_error),
            gyro_bias_rad_s=bias_g[k] + cfg.faults.extra_gyro_bias_rad_s,
            accel_bias_m_s2=bias_a[k],
            method="in-flight",
            cov_diag=np.repeat([1e-4**2, 1e-3**2, sigma_v**2, 1e-3**2, 0.02**2], 3),
        )
    return Stream(imu, frames, gt, calib, given, params.noise, cfg.time_offset_s, cfg.pixel_sigma_px, init)
