"""The headset rig's scenarios (``viotb record`` and ``viotb headset``): the rig as headsets are built.

The rig: two global-shutter tracking cameras (``head_cam0`` left, ``head_cam1`` right, 10 cm baseline,
fovy 100 deg, 30 Hz, 2 ms exposure integrated over three renders and written to ``sensor.yaml``) and a
consumer IMU at 1 kHz (``icm42688-1khz``). Every scenario is stereo; ``--cameras 1`` uses ``head_cam0`` alone.
The older ``head-*`` recordings of :mod:`~viotb.envs.scenarios.record_catalog` keep their single centre camera
and 200 Hz IMU, so their numbers do not move.
"""

from __future__ import annotations

from dataclasses import dataclass

from viotb.envs.scenarios.head_motions import HEAD_TRAJECTORY_FACTORIES
from viotb.envs.scenarios.motions import TRAJECTORY_FACTORIES, MotionParams, Trajectory
from viotb.envs.scenarios.spec import Scenario
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.models.constants import HEADSET_CAMERAS

HEADSET_IMU_PRESET = "icm42688-1khz"
"""IMU preset of the headset rig."""
HEADSET_RIG_CAMERA = CameraModelParams(
    rate_hz=30.0, width=320, height=240, pixel_noise_std=2.0, exposure_s=0.002, blur_samples=3
)
"""Timing and noise of each of the rig's tracking cameras."""


@dataclass(frozen=True)
class _HeadMotion:
    """Picklable factory ``duration_s -> Trajectory`` for a named head motion."""

    motion: str

    def __call__(self, duration_s: float) -> Trajectory:
        factory = HEAD_TRAJECTORY_FACTORIES.get(self.motion) or TRAJECTORY_FACTORIES[self.motion]
        return factory(MotionParams(duration_s=duration_s))


def _rig(name: str, description: str, seconds: float, motion: str, scene: str = "textured_room") -> Scenario:
    return Scenario(
        name,
        description,
        "record",
        "headset",
        scene,
        seconds,
        HEADSET_IMU_PRESET,
        HEADSET_RIG_CAMERA,
        _HeadMotion(motion),
        camera_names=HEADSET_CAMERAS,
    )


def head_scenarios() -> list[Scenario]:
    """Every scenario of the stereo headset rig, in listing order."""
    return [
        _rig("headset-still", "Stereo headset, seated still: breathing sway (sub-mm).", 15.0, "head-still"),
        _rig(
            "headset-look-around",
            "Stereo headset, standing, looking around: yaw +-60 deg up to 200 deg/s, pitch +-15 deg.",
            20.0,
            "head-look-around-fast",
        ),
        _rig(
            "headset-fast-turns",
            "Stereo headset, fast head turns: yaw +-70 deg up to ~350 deg/s.",
            15.0,
            "head-fast-turns",
        ),
        _rig("headset-walk", "Stereo headset, walking a 2.2 m circle at 1.2 m/s.", 30.0, "head-walk"),
        _rig("headset-crouch", "Stereo headset, crouching and standing (1.65-1.05 m).", 20.0, "head-crouch"),
        _rig(
            "headset-blank-wall",
            "Stereo headset, 1 m from a blank wall, facing it (feature poverty).",
            15.0,
            "head-face-wall",
            scene="blank_wall",
        ),
        _rig(
            "headset-dark-room",
            "Stereo headset, looking around in a dark room (low contrast).",
            15.0,
            "head-look-around-fast",
            scene="dark_room",
        ),
    ]
