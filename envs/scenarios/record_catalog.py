"""The open-loop scenario library (``viotb record NAME``): quadrotor and headset motions, hard variants.

The variants put the motions in the lesson's hard conditions (blank wall, dark room, blackout, consumer IMU,
clock offset).
"""

from __future__ import annotations

from dataclasses import dataclass

from viotb.envs.scenarios.motions import TRAJECTORY_FACTORIES, MotionParams, Trajectory
from viotb.envs.scenarios.spec import Scenario
from viotb.envs.sim.camera_timing import CameraModelParams


@dataclass(frozen=True)
class _Motion:
    """Picklable factory ``duration_s -> Trajectory`` for a named motion of the trajectory library."""

    motion: str

    def __call__(self, duration_s: float) -> Trajectory:
        return TRAJECTORY_FACTORIES[self.motion](MotionParams(duration_s=duration_s))


_QUAD_CAMERA = CameraModelParams(rate_hz=20.0, width=320, height=240, pixel_noise_std=2.0)
_HEAD_CAMERA = CameraModelParams(rate_hz=30.0, width=320, height=240, pixel_noise_std=2.0)


def _record(
    name: str,
    description: str,
    seconds: float,
    motion: str | None = None,
    vehicle: str = "quadrotor",
    scene: str = "textured_room",
    imu: str = "adis16448",
    camera: CameraModelParams | None = None,
) -> Scenario:
    """One open-loop scenario (the head camera for the headset, else the quadrotor's)."""
    if camera is None:
        camera = _HEAD_CAMERA if vehicle == "headset" else _QUAD_CAMERA
    trajectory = _Motion(motion or name)
    return Scenario(name, description, "record", vehicle, scene, seconds, imu, camera, trajectory)


def record_scenarios() -> list[Scenario]:
    """Every open-loop scenario of the library, in listing order."""
    return [
        _record("hover", "Quadrotor hovers with a small 3-axis excitation (scale stays observable).", 30.0),
        _record("circle", "Quadrotor flies a 2 m-radius circle at 1.5 m/s, nose along the velocity.", 30.0),
        _record("figure8", "Quadrotor flies a 5 x 2.5 m figure-8 with a height wave.", 60.0),
        _record("line", "Quadrotor flies a straight line at constant velocity (weak excitation).", 8.0),
        _record("fast-rotation", "Quadrotor spins in yaw at 3 rad/s in place (rotation stress).", 20.0),
        _record(
            "fast-rotation-blur",
            "The 3 rad/s spin with a 45 ms exposure: motion blur (feature poverty).",
            20.0,
            motion="fast-rotation",
            camera=CameraModelParams(rate_hz=20.0, pixel_noise_std=2.0, exposure_s=0.045),
        ),
        _record("aggressive", "Fast 3-D figure-8: ~5 m/s, ~9 m/s^2, 40 deg tilt.", 20.0),
        _record(
            "long-loop", "Three laps of a 6 x 5 m ellipse returning to the start (drift / loop test).", 120.0
        ),
        _record(
            "head-walk", "Headset: walking a 2.2 m circle at 1.2 m/s with step bob.", 30.0, vehicle="headset"
        ),
        _record(
            "head-look-around",
            "Headset: standing, looking around (yaw +-60 deg, pitch +-25 deg).",
            30.0,
            vehicle="headset",
        ),
        _record("head-fast-turns", "Headset: fast head turns up to ~350 deg/s.", 20.0, vehicle="headset"),
        # The lesson's failure-mode variants (feature poverty, darkness, blackout, consumer IMU, time offset).
        _record(
            "hover-blank-wall",
            "Hover in front of a blank wall (feature poverty).",
            30.0,
            motion="hover",
            scene="blank_wall",
        ),
        _record(
            "circle-dark-room",
            "Circle in a dark room (low contrast).",
            30.0,
            motion="circle",
            scene="dark_room",
        ),
        _record(
            "circle-blackout",
            "Circle with the camera blacked out from 10 s to 14 s (IMU-only coasting).",
            30.0,
            motion="circle",
            camera=CameraModelParams(rate_hz=20.0, pixel_noise_std=2.0, blackout_intervals_s=((10.0, 14.0),)),
        ),
        _record(
            "circle-consumer-imu",
            "Circle with a consumer-grade (BMI088-like) IMU.",
            30.0,
            motion="circle",
            imu="bmi088",
        ),
        _record(
            "circle-time-offset",
            "Circle with a 15 ms camera-IMU clock offset (t_imu = t_cam + 0.015).",
            30.0,
            motion="circle",
            camera=CameraModelParams(rate_hz=20.0, pixel_noise_std=2.0, time_offset_s=0.015),
        ),
    ]
