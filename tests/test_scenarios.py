"""Tests of the scenario registry (envs/scenarios.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from viotb.envs.scenarios import Scenario, get_scenario, list_scenarios, register
from viotb.envs.trajectories import Trajectory

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
