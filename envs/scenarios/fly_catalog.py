"""The closed-loop scenario library (``viotb fly NAME``): missions flown on the estimate in each rig."""

from __future__ import annotations

from viotb.envs.scenarios.spec import FlyScenario
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.sim.rig import RigConfig, WindParams


def fly_scenarios() -> dict[str, FlyScenario]:
    """The nominal closed-loop scenarios by name (failures: :mod:`~viotb.envs.scenarios.failures`)."""
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
            "fly-lights-out",
            "hover with the room lights off for 4 s at t = 13 s (coast on the IMU, re-initialize in the air)",
            rig=RigConfig(lights_off_intervals_s=((13.0, 17.0),)),
            default_seconds=22.0,
            loop_closure=True,  # relocalizes at the hold point when the light returns (vio.recovery)
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
