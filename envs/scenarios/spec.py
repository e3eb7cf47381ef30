"""What a scenario is: the open-loop :class:`Scenario` and the closed-loop :class:`FlyScenario`.

``kind`` is ``"record"`` for open-loop scenarios (the vehicle is driven kinematically along its trajectory)
and ``"fly"`` for closed-loop ones; every closed-loop scenario is listed in the registry as a ``fly``
:class:`Scenario` too (:func:`listing`), so that ``viotb scenarios`` shows one table.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from viotb.envs.scenarios.motions import StillStart, Trajectory
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.sim.faults import SensorFaults
from viotb.envs.sim.imu_model import imu_preset
from viotb.envs.sim.rig import RigConfig
from viotb.models.constants import ONBOARD_CAMERA, SCENE_XMLS, VEHICLE_XMLS

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
        camera_names: The rig's MuJoCo cameras, left (``cam0``) first; empty = the vehicle's single
            ``onboard`` camera. Two names make a stereo rig (``cam0`` and ``cam1`` in recordings).
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
    camera_names: tuple[str, ...] = ()

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
        if len(self.camera_names) > 2:
            raise ValueError(f"scenario {self.name!r}: at most 2 cameras, got {self.camera_names}")

    @property
    def rig_cameras(self) -> tuple[str, ...]:
        """MuJoCo camera names of the rig, left first (at least one)."""
        return self.camera_names if self.camera_names else (ONBOARD_CAMERA,)

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
        loop_closure: Flown with loop closure unless the run says otherwise (``viotb fly
            --no-loop-closure``), its keyframes from the excitation manoeuvre on
            (``LoopOptions.from_excitation``).
    """

    name: str
    description: str
    rig: RigConfig = field(default_factory=RigConfig)
    mission: str = "hover"
    default_seconds: float = 20.0
    takeoff_altitude_m: float = 1.0
    loop_closure: bool = False


def listing(sc: FlyScenario) -> Scenario:
    """The registry entry (kind ``fly``) of a closed-loop scenario, for ``viotb scenarios``."""
    return Scenario(
        name=sc.name,
        description=sc.description,
        kind="fly",
        vehicle="quadrotor",
        scene=sc.rig.scene,
        default_seconds=sc.default_seconds,
        imu_preset=sc.rig.imu_preset,
        camera=sc.rig.camera,
    )
