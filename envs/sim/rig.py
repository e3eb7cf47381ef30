"""The closed-loop rig's configuration: scene, sensors, estimator choice, start pose, wind and faults."""

from __future__ import annotations

from dataclasses import dataclass, field

from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.sim.faults import SensorFaults
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.window import WindowParams


@dataclass(frozen=True)
class WindParams:
    """Wind gusts as a horizontal force on the body: a seeded Ornstein-Uhlenbeck process plus a mean.

    Attributes:
        mean_force_W_N: Constant force (N), shape (3,).
        gust_sigma_N: Stationary standard deviation of the gust force per horizontal axis (N).
        gust_time_constant_s: Correlation time of the gusts (s).
    """

    mean_force_W_N: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_sigma_N: float = 0.0
    gust_time_constant_s: float = 1.0


@dataclass(frozen=True)
class RigConfig:
    """Everything that defines the simulated rig of a closed-loop run.

    Attributes:
        scene: Scene name (``viotb.models.constants.SCENE_XMLS``).
        estimator: ``msckf``, ``imu-only`` or ``ground-truth``.
        frontend: ``klt`` (OpenCV on rendered images) or ``sim`` (projected landmarks, fast mode).
        imu_preset: IMU model preset name (``viotb.envs.sim.imu_model``).
        camera: Camera model (rate, resolution, clock offset, latency, drops, blackouts, pixel noise).
        start_p_W_m: Start position of the body on the ground (m), shape (3,).
        start_yaw_rad: Start heading (rad).
        wind: Wind gusts.
        sim_pixel_sigma_px: Pixel noise of the ``sim`` front end (px).
        render_images: Render the onboard camera even in ``sim`` mode (for image observations / recordings).
        imu_fault_at_s: From this time on (s) the IMU outputs NaN on every axis: a failed sensor, used to test
            how an estimator and the runner behave when the estimate becomes unusable; None = healthy.
        faults: Calibration / IMU errors (:class:`~viotb.envs.sim.faults.SensorFaults`): what the estimator is
            told and fed, not the truth.
        online_calibration: Estimate the time offset and the extrinsics online (MSCKF:
            :meth:`~viotb.vio.msckf.MsckfParams.with_online_calibration`; window:
            :meth:`~viotb.vio.window_params.WindowParams.with_online_calibration`).
        msckf: MSCKF settings (None: the defaults); the ``sim`` front end still sets its pixel noise.
        window: Window-optimizer settings (None: the defaults); likewise.
        lights_off_intervals_s: ``((start, end), ...)`` on the IMU clock (s) in which every light of the
            scene is off: frames still arrive, black (``klt``) or without features (``sim``).
        recovery: Wrap the feature-based estimators in :class:`~viotb.vio.recovery.RecoveringEstimator`
            (coast on the IMU through a loss of tracking, re-initialize in the air when features return)
            instead of letting a diverged estimator end the flight. ``viotb fly`` turns it on; off here, so
            the Gymnasium envs still end an episode on divergence.
    """

    scene: str = "textured_room"
    estimator: str = "msckf"
    frontend: str = "klt"
    imu_preset: str = "adis16448"
    camera: CameraModelParams = field(default_factory=CameraModelParams)
    start_p_W_m: tuple[float, float, float] = (0.0, 0.0, 0.06)
    start_yaw_rad: float = 0.0
    wind: WindParams = field(default_factory=WindParams)
    sim_pixel_sigma_px: float = 0.5
    render_images: bool = False
    imu_fault_at_s: float | None = None
    faults: SensorFaults = field(default_factory=SensorFaults)
    online_calibration: bool = False
    msckf: MsckfParams | None = None
    window: WindowParams | None = None
    lights_off_intervals_s: tuple[tuple[float, float], ...] = ()
    recovery: bool = False

    def __post_init__(self) -> None:
        """Validate the lights-out intervals (message names the field and value)."""
        for i, interval in enumerate(self.lights_off_intervals_s):
            if len(interval) != 2 or not interval[0] < interval[1]:
                raise ValueError(
                    f"RigConfig.lights_off_intervals_s[{i}] must be (start, end) with start < end, "
                    f"got {interval!r}"
                )
