"""The lesson's failure modes as a catalog: each :class:`FailureSpec` at a severity, and its fix.

Each failure is offered three ways, all built here and registered by :mod:`~viotb.envs.scenarios.registry`:

* an open-loop ``record`` scenario (``viotb record fail-...``: :func:`failure_record_scenario`),
* a closed-loop :class:`~viotb.envs.scenarios.spec.FlyScenario` where the rig can express it
  (:func:`failure_fly_scenarios`),
* a fast in-memory stream (:meth:`FailureSpec.config`, a
  :class:`~viotb.envs.scenarios.streams.StreamConfig`) that ``viotb failures`` runs with a health monitor
  (:mod:`viotb.envs.run.failure_runner`, :mod:`viotb.envs.tools.failure_report`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from viotb.envs.scenarios.motions import TRAJECTORY_FACTORIES, MotionParams, Trajectory
from viotb.envs.scenarios.spec import FlyScenario, Scenario
from viotb.envs.scenarios.streams import NO_EXCITATION_START_S, StreamConfig
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.sim.faults import SensorFaults
from viotb.envs.sim.rig import RigConfig
from viotb.vio.msckf import MsckfParams


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
            return StreamConfig(
                motion="line",
                seconds=8.0,
                speed_scale=1.0 + 0.5 * s,
                start_in_flight_s=NO_EXCITATION_START_S,
                initial_scale_error=0.1 * s,
            )
        if n == "fail-time-offset":
            return StreamConfig(
                motion="figure8",
                seconds=12.0,
                time_offset_s=0.01 * s,
                speed_scale=1.0 + s,
                faults=SensorFaults(assumed_time_offset_s=0.0),
            )
        if n == "fail-extrinsic":
            return StreamConfig(
                motion="figure8",
                seconds=12.0,
                faults=SensorFaults(extrinsic_error_rad=float(np.deg2rad(2.0)) * s),
                speed_scale=1.0 + s,
            )
        if n == "fail-feature-poverty":
            return StreamConfig(
                motion="hover",
                landmark_count=max(int(1500 * (1.0 - 0.98 * min(s, 1.0))), 8),
                blackout_s=(6.0, 6.0 + 2.0 * s),
            )
        if n == "fail-gyro-saturation":
            return StreamConfig(
                motion="aggressive", seconds=12.0, imu_preset="bmi088-125dps", speed_scale=0.5 + 0.5 * s
            )
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
        FailureSpec(
            "fail-bad-init",
            "initialization_failure",
            "turn-on gyro bias 0.3 rad/s and 5 % accelerometer scale: wrong gravity / bias at init",
            "calibrated IMU (re-initialize after calibration)",
        ),
        FailureSpec(
            "fail-no-excitation",
            "insufficient_excitation",
            "started in flight with a 10 % scale error, then a constant-velocity line: scale "
            "unobservable, the error stays and the position error grows with distance",
            "excitation manoeuvre (the same start on a figure-8)",
        ),
        FailureSpec(
            "fail-time-offset",
            "time_sync_or_extrinsic_suspected",
            "10 ms camera-IMU clock offset on a fast figure-8: error grows with speed",
            "online time-offset and extrinsic calibration",
            "time_offset_miscalibrated",
        ),
        FailureSpec(
            "fail-extrinsic",
            "time_sync_or_extrinsic_suspected",
            "2 deg camera-IMU rotation error on a fast figure-8",
            "online time-offset and extrinsic calibration",
            "extrinsic_miscalibrated",
        ),
        FailureSpec(
            "fail-feature-poverty",
            "feature_poverty",
            "30 landmarks and a 2 s blackout (blank wall / dark room)",
            "coast on the IMU (propagate only)",
        ),
        FailureSpec(
            "fail-gyro-saturation",
            "imu_saturation",
            "aggressive manoeuvre past a +-125 deg/s gyro",
            "an IMU rated for the motion (+-2000 deg/s)",
        ),
        FailureSpec(
            "fail-long-loop",
            "",
            "long loop back to the start: odometry drift (loop closure is out of scope)",
            "none in odometry (needs loop closure)",
        ),
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
    cam = CameraModelParams(
        rate_hz=cfg.camera_rate_hz,
        pixel_noise_std=2.0,
        time_offset_s=cfg.time_offset_s,
        blackout_intervals_s=(cfg.blackout_s,) if cfg.blackout_s else (),
    )
    scene = "blank_wall" if spec.name == "fail-feature-poverty" else cfg.scene
    return Scenario(
        spec.name,
        spec.description,
        "record",
        "quadrotor",
        scene,
        cfg.seconds,
        cfg.imu_preset,
        cam,
        _MotionFactory(cfg.motion, cfg.speed_scale),
        still_start_s=cfg.still_s,
        faults=cfg.faults,
    )


@dataclass(frozen=True)
class _MotionFactory:
    """Picklable ``duration_s -> Trajectory`` with a speed scale."""

    motion: str
    speed_scale: float = 1.0

    def __call__(self, duration_s: float) -> Trajectory:
        return TRAJECTORY_FACTORIES[self.motion](MotionParams(duration_s, speed_scale=self.speed_scale))


FLY_SEVERITY_KNOBS = (
    "fly-fail-bad-init",
    "fly-fail-time-offset",
    "fly-fail-extrinsic",
    "fly-fail-feature-poverty",
)
"""Closed-loop failures whose rig follows the severity (the stream's faults, offset or blackout length)."""


def failure_fly_scenarios(severity: float = 1.0) -> dict:
    """Closed-loop versions of the failures that the rig can express, as ``FlyScenario`` objects.

    ``severity`` scales the rigs of :data:`FLY_SEVERITY_KNOBS` as :meth:`FailureSpec.config` scales the
    streams (the IMU faults, the clock offset, the extrinsic error; the blackout lasts ``3 x severity`` s);
    the others do not depend on it.
    """
    sev = float(severity)
    offset = FAILURES["fail-time-offset"].config(sev)
    blackout = ((10.0, 10.0 + 3.0 * sev),) if sev > 0.0 else ()
    items = [
        FlyScenario(
            "fly-fail-bad-init",
            "hover with an out-of-spec IMU: +0.3 rad/s gyro bias on every axis, 5 % accel scale",
            rig=RigConfig(faults=FAILURES["fail-bad-init"].config(sev).faults),
            default_seconds=20.0,
        ),
        FlyScenario(
            "fly-fail-time-offset",
            "figure-8 with a 10 ms camera clock offset the estimator is not told (fix: --calibrate)",
            rig=RigConfig(camera=CameraModelParams(time_offset_s=offset.time_offset_s), faults=offset.faults),
            mission="figure8",
            default_seconds=25.0,
        ),
        FlyScenario(
            "fly-fail-extrinsic",
            "figure-8 with a 2 deg error in the camera-IMU rotation given to the estimator (fix: "
            "--calibrate)",
            rig=RigConfig(faults=FAILURES["fail-extrinsic"].config(sev).faults),
            mission="figure8",
            default_seconds=25.0,
        ),
        FlyScenario(
            "fly-fail-no-excitation",
            "4.5 m straight line at a constant 0.8 m/s: no acceleration while cruising",
            rig=RigConfig(start_p_W_m=(-2.5, 0.0, 0.06)),
            mission="line",
            default_seconds=20.0,
        ),
        FlyScenario(
            "fly-fail-feature-poverty",
            "hover in front of a blank wall with a 3 s blackout",
            rig=RigConfig(
                scene="blank_wall",
                start_p_W_m=(3.0, 0.0, 0.06),
                camera=CameraModelParams(blackout_intervals_s=blackout),
            ),
            default_seconds=20.0,
        ),
        FlyScenario(
            "fly-fail-gyro-saturation",
            "aggressive flight with a +-125 deg/s gyro",
            rig=RigConfig(imu_preset="bmi088-125dps"),
            mission="aggressive",
            default_seconds=20.0,
        ),
        FlyScenario(
            "fly-fail-long-loop",
            "three laps of a 1.5 m square back to the start: odometry drift",
            mission="loops",
            default_seconds=50.0,
        ),
    ]
    return {s.name: s for s in items}


def failure_fly_scenario(name: str, severity: float = 1.0) -> FlyScenario:
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
