"""Registry of named scenarios: vehicle + scene + scripted motion + sensor set-up.

``kind`` is ``"record"`` for open-loop scenarios (``viotb record``: the vehicle is driven kinematically along
its trajectory) and ``"fly"`` for closed-loop ones, which other modules add through :func:`register`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.sim.faults import SensorFaults
from viotb.envs.sim.imu_model import imu_preset
from viotb.envs.scenarios.motions import TRAJECTORY_FACTORIES, MotionParams, StillStart, Trajectory
from viotb.models.constants import SCENE_XMLS, VEHICLE_XMLS

SCENARIO_KINDS = ("record", "fly")
"""Allowed values of :attr:`Scenario.kind`."""


@dataclass(frozen=True)
class Scenario:
    """One runnable scenario.

    Attributes:
        name: Unique id used on the command line (``viotb record NAME``).
        description: One line for ``viotb scenarios``.
        kind: ``"record"`` (open loop) or ``"fly"`` (closed loop).
        vehicle: ``"quadrotor"`` or ``"headset"`` (a key of ``models.constants.VEHICLE_XMLS``).
        scene: Scene name (a key of ``models.constants.SCENE_XMLS``).
        default_seconds: Duration (s) when the user gives none.
        imu_preset: Name for :func:`viotb.envs.sim.imu_model.imu_preset`.
        camera: Camera timing/noise parameters.
        trajectory: Factory ``duration_s -> Trajectory`` (None for scenarios without a scripted motion).
        still_start_s: Rest at the first pose before the motion (s), inside the duration, so that a static
            initializer can start as on real sequences; 0 disables it.
        faults: Calibration / IMU errors written into a recording: the IMU readings carry the IMU faults and
            the dataset's calibration files hold the wrong calibration (as a bad calibration file would).
    """

    name: str
    description: str
    kind: str
    vehicle: str
    scene: str
    default_seconds: float
    imu_preset: str = "adis16448"
    camera: CameraModelParams = field(default_factory=CameraModelParams)
    trajectory: Callable[[float], Trajectory] | None = None
    still_start_s: float = 1.5
    faults: SensorFaults = field(default_factory=SensorFaults)

    def __post_init__(self) -> None:
        """Validate names against the models and presets."""
        if self.kind not in SCENARIO_KINDS:
            raise ValueError(f"scenario {self.name!r}: kind must be in {SCENARIO_KINDS}, got {self.kind!r}")
        if self.vehicle not in VEHICLE_XMLS:
            raise ValueError(
                f"scenario {self.name!r}: unknown vehicle {self.vehicle!r}; known: {sorted(VEHICLE_XMLS)}"
            )
        if self.scene not in SCENE_XMLS:
            known = sorted(SCENE_XMLS)
            raise ValueError(f"scenario {self.name!r}: unknown scene {self.scene!r}; known: {known}")
        if not self.default_seconds > 0.0:
            raise ValueError(
                f"scenario {self.name!r}: default_seconds must be > 0, got {self.default_seconds}"
            )
        imu_preset(self.imu_preset)  # raises ValueError listing the presets

    def make_trajectory(self, seconds: float | None = None) -> Trajectory:
        """The scripted motion for ``seconds`` (default: ``default_seconds``)."""
        if self.trajectory is None:
            raise ValueError(f"scenario {self.name!r} has no scripted trajectory")
        duration = self.default_seconds if seconds is None else float(seconds)
        if not duration > 0.0:
            raise ValueError(f"scenario {self.name!r}: seconds must be > 0, got {seconds}")
        if self.still_start_s <= 0.0:
            return self.trajectory(duration)
        # The motion fills what the rest leaves (a scenario shorter than its rest is all rest).
        motion = self.trajectory(max(duration - self.still_start_s, 1e-3))
        return StillStart(motion, min(self.still_start_s, duration))


_REGISTRY: dict[str, Scenario] = {}


def register(scenario: Scenario, replace: bool = False) -> Scenario:
    """Add a scenario to the registry (ValueError on a duplicate name unless ``replace``)."""
    if scenario.name in _REGISTRY and not replace:
        raise ValueError(f"scenario {scenario.name!r} is already registered")
    _REGISTRY[scenario.name] = scenario
    return scenario


def is_registered(name: str) -> bool:
    """Whether ``name`` is registered already (without importing the registering modules)."""
    return name in _REGISTRY


def _load_registrants() -> None:
    """Import the modules that register more scenarios: closed-loop (``fly-*``) and failure (``fail-*``)."""
    import viotb.envs.scenarios.failures  # noqa: F401, PLC0415
    import viotb.envs.run.fly  # noqa: F401, PLC0415


def get_scenario(name: str) -> Scenario:
    """The scenario called ``name`` (ValueError listing the known names)."""
    if name not in _REGISTRY:
        _load_registrants()
    try:
        return _REGISTRY[name]
    except KeyError:
        known = ", ".join(sorted(_REGISTRY))
        raise ValueError(f"unknown scenario {name!r}; known scenarios: {known}") from None


def list_scenarios() -> list[dict]:
    """All scenarios as dicts with keys name, kind, description, vehicle, scene, default_seconds."""
    _load_registrants()
    return [
        {
            "name": s.name,
            "kind": s.kind,
            "description": s.description,
            "vehicle": s.vehicle,
            "scene": s.scene,
            "default_seconds": s.default_seconds,
        }
        for s in sorted(_REGISTRY.values(), key=lambda s: (s.kind, s.name))
    ]


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
) -> None:
    if camera is None:
        camera = _HEAD_CAMERA if vehicle == "headset" else _QUAD_CAMERA
    trajectory = _Motion(motion or name)
    register(Scenario(name, description, "record", vehicle, scene, seconds, imu, camera, trajectory))


_record("hover", "Quadrotor hovers with a small 3-axis excitation (scale stays observable).", 30.0)
_record("circle", "Quadrotor flies a 2 m-radius circle at 1.5 m/s, nose along the velocity.", 30.0)
_record("figure8", "Quadrotor flies a 5 x 2.5 m figure-8 with a height wave.", 60.0)
_record("line", "Quadrotor flies a straight line at constant velocity (weak excitation).", 8.0)
_record("fast-rotation", "Quadrotor spins in yaw at 3 rad/s in place (rotation stress).", 20.0)
_record("fast-rotation-blur", "The 3 rad/s spin with a 45 ms exposure: motion blur (feature poverty).", 20.0,
        motion="fast-rotation", camera=CameraModelParams(rate_hz=20.0, pixel_noise_std=2.0, exposure_s=0.045))
_record("aggressive", "Fast 3-D figure-8: ~5 m/s, ~9 m/s^2, 40 deg tilt.", 20.0)
_record("long-loop", "Three laps of a 6 x 5 m ellipse returning to the start (drift / loop test).", 120.0)
_record("head-walk", "Headset: walking a 2.2 m circle at 1.2 m/s with step bob.", 30.0, vehicle="headset")
_record("head-look-around", "Headset: standing, looking around (yaw +-60 deg, pitch +-25 deg).", 30.0,
        vehicle="headset")
_record("head-fast-turns", "Headset: fast head turns up to ~350 deg/s.", 20.0, vehicle="headset")
# Failure-mode variants of the lesson (feature poverty, darkness, camera blackout, consumer IMU, time offset).
_record("hover-blank-wall", "Hover in front of a blank wall (feature poverty).", 30.0, motion="hover",
        scene="blank_wall")
_record("circle-dark-room", "Circle in a dark room (low contrast).", 30.0, motion="circle", scene="dark_room")
_record(
    "circle-blackout",
    "Circle with the camera blacked out from 10 s to 14 s (IMU-only coasting).",
    30.0,
    motion="circle",
    camera=CameraModelParams(rate_hz=20.0, pixel_noise_std=2.0, blackout_intervals_s=((10.0, 14.0),)),
)
_record("circle-consumer-imu", "Circle with a consumer-grade (BMI088-like) IMU.", 30.0, motion="circle",
        imu="bmi088")
_record(
    "circle-time-offset",
    "Circle with a 15 ms camera-IMU clock offset (t_imu = t_cam + 0.015).",
    30.0,
    motion="circle",
    camera=CameraModelParams(rate_hz=20.0, pixel_noise_std=2.0, time_offset_s=0.015),
)
