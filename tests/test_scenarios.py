"""Tests of the scenario registry (envs/scenarios.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from viotb.envs.scenarios.motions import Trajectory
from viotb.envs.scenarios.registry import Scenario, get_scenario, list_scenarios, register

REQUIRED = (
    "hover",
    "circle",
    "figure8",
    "line",
    "fast-rotation",
    "aggressive",
    "long-loop",
    "head-walk",
    "head-look-around",
    "head-fast-turns",
)


def test_required_scenarios_listed_with_keys():
    items = {item["name"]: item for item in list_scenarios()}
    for name in REQUIRED:
        assert name in items
        assert set(items[name]) >= {"name", "kind", "description", "vehicle", "scene"}
        assert items[name]["kind"] == "record"
        assert items[name]["description"]
    assert items["figure8"]["default_seconds"] == 60.0
    assert items["head-walk"]["vehicle"] == "headset" and items["circle"]["vehicle"] == "quadrotor"


@pytest.mark.parametrize("name", REQUIRED)
def test_trajectory_factory_honours_duration(name):
    scenario = get_scenario(name)
    traj = scenario.make_trajectory(5.0)
    assert isinstance(traj, Trajectory)
    assert traj.duration_s == 5.0
    assert scenario.make_trajectory().duration_s == scenario.default_seconds
    s = traj.sample_many(np.linspace(0.0, 5.0, 11))
    assert np.all(np.isfinite(s.p_WB))


def test_unknown_name_lists_known_names():
    with pytest.raises(ValueError, match="hover.*long-loop|circle"):
        get_scenario("does-not-exist")


def test_register_fly_scenario_and_duplicates():
    base = get_scenario("hover")
    fly = dataclasses.replace(base, name="test-fly-hover", kind="fly", trajectory=None)
    register(fly)
    assert get_scenario("test-fly-hover") is fly
    assert any(item["name"] == "test-fly-hover" and item["kind"] == "fly" for item in list_scenarios())
    with pytest.raises(ValueError, match="already registered"):
        register(fly)
    register(fly, replace=True)
    with pytest.raises(ValueError, match="no scripted trajectory"):
        fly.make_trajectory()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"kind": "race"}, "kind"),
        ({"vehicle": "blimp"}, "vehicle"),
        ({"scene": "moon"}, "scene"),
        ({"imu_preset": "nope"}, "preset"),
        ({"default_seconds": 0.0}, "default_seconds"),
    ],
)
def test_bad_scenarios_rejected(change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(get_scenario("hover"), **change)


def test_scenario_is_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        get_scenario("hover").name = "x"  # type: ignore[misc]
    assert isinstance(get_scenario("circle"), Scenario)


def test_sensor_faults_told_calibration_and_imu_input():
    from viotb.envs.sim.faults import SensorFaults
    from viotb.vio.camera import CameraCalibration, PinholeCamera
    from viotb.vio.lie import log_so3

    cam = PinholeCamera(320, 240, 250.0, 250.0, 160.0, 120.0)
    true = CameraCalibration(cam, np.eye(3), np.zeros(3), time_offset_s=0.01)
    told = SensorFaults(assumed_time_offset_s=0.0, extrinsic_error_rad=0.02).told_calibration(true)
    # The rotation error is 0.02 rad about (1, 0, 1) / sqrt(2); the offset is replaced, the rest kept.
    axis = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    np.testing.assert_allclose(log_so3(told.R_BC), 0.02 * axis, atol=1e-12)
    assert told.time_offset_s == 0.0 and told.camera == cam
    same = SensorFaults().told_calibration(true)  # no fault: the truth
    np.testing.assert_array_equal(same.R_BC, true.R_BC)
    assert same.time_offset_s == 0.01
    omega, f = SensorFaults(extra_gyro_bias_rad_s=0.1, accel_scale_error=0.05).imu_input(
        np.zeros((2, 3)), np.tile([0.0, 0.0, 9.81], (2, 1))
    )
    np.testing.assert_allclose(omega, 0.1)
    np.testing.assert_allclose(f[:, 2], 1.05 * 9.81)
    with pytest.raises(ValueError, match="extrinsic_error_rad"):
        SensorFaults(extrinsic_error_rad=float("nan"))
