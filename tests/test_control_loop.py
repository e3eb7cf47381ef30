"""Closed-loop tests: the SE(3) controller flies the MJCF quadrotor in MuJoCo on ground truth.

Control at 250 Hz (``ctrl_dt``), physics at the model's timestep; ``ctrl`` = motor thrusts (N).
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np
import pytest
from viotb.controllers.se3 import SE3Controller, SE3Gains
from viotb.controllers.setpoints import FigureEight, HoverPoint, Sequence, Takeoff
from viotb.controllers.types import FlatOutput, NavState
from viotb.controllers.vehicle import VehicleParams
from viotb.envs.sim.vehicle import nav_state_from_data, vehicle_params_from_model
from viotb.models import load_model
from viotb.models.constants import HOVER_KEYFRAME
from viotb.vio.lie import yaw_from_rotmat

CTRL_DT_S = 1.0 / 250.0
"""Control period (s)."""

Disturb = Callable[[NavState], NavState]


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return load_model("quadrotor", "empty")


@pytest.fixture(scope="module")
def vehicle(model: mujoco.MjModel) -> VehicleParams:
    return vehicle_params_from_model(model)


def _fly(
    model: mujoco.MjModel,
    controller: SE3Controller,
    setpoint: Callable[[float], FlatOutput],
    seconds: float,
    keyframe: bool = True,
    measure: Disturb | None = None,
) -> tuple[np.ndarray, list[NavState]]:
    """Simulate; return the control times (s) and the true state after each control period."""
    data = mujoco.MjData(model)
    if keyframe:
        mujoco.mj_resetDataKeyframe(model, data, model.key(HOVER_KEYFRAME).id)
    else:
        mujoco.mj_forward(model, data)
    n_sub = round(CTRL_DT_S / model.opt.timestep)
    times, states = [], []
    for _ in range(round(seconds / CTRL_DT_S)):
        truth = nav_state_from_data(model, data)
        seen = measure(truth) if measure is not None else truth
        data.ctrl[:] = controller.update(data.time, seen, setpoint(data.time)).thrusts_N
        mujoco.mj_step(model, data, nstep=n_sub)
        times.append(data.time)
        states.append(nav_state_from_data(model, data))
    return np.array(times), states


def _positions(states: list[NavState]) -> np.ndarray:
    return np.array([s.p_WB for s in states])


def test_hover_keyframe_holds(model: mujoco.MjModel, vehicle: VehicleParams) -> None:
    hover = HoverPoint(p_W=[0.0, 0.0, 1.0])
    _, states = _fly(model, SE3Controller(vehicle), hover.sample, 2.0)
    err = np.linalg.norm(_positions(states) - [0.0, 0.0, 1.0], axis=1)
    assert np.max(err) < 1e-3


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_one_metre_step_settles(model: mujoco.MjModel, vehicle: VehicleParams, axis: int) -> None:
    target = np.array([0.0, 0.0, 1.0])
    target[axis] += 1.0
    times, states = _fly(model, SE3Controller(vehicle), HoverPoint(p_W=target).sample, 4.0)
    p = _positions(states)
    overshoot = np.max(p[:, axis]) - target[axis]
    assert overshoot < 0.2  # < 20 % of the 1 m step
    settled = times >= 3.0
    assert np.max(np.linalg.norm(p[settled] - target, axis=1)) < 0.02  # within 2 cm from 3 s on


def test_yaw_step_of_90_degrees_settles(model: mujoco.MjModel, vehicle: VehicleParams) -> None:
    target = HoverPoint(p_W=[0.0, 0.0, 1.0], yaw_rad=np.pi / 2)
    times, states = _fly(model, SE3Controller(vehicle), target.sample, 3.0)
    yaw = np.array([yaw_from_rotmat(s.R_WB) for s in states])
    assert np.max(yaw) - np.pi / 2 < np.deg2rad(9.0)  # < 10 % overshoot
    assert np.max(np.abs(yaw[times >= 2.0] - np.pi / 2)) < np.deg2rad(1.0)
    assert np.max(np.linalg.norm(_positions(states) - [0.0, 0.0, 1.0], axis=1)) < 0.01


def test_figure_eight_tracking(model: mujoco.MjModel, vehicle: VehicleParams) -> None:
    eight = FigureEight(center_xy_m=[0.0, 0.0], size_m=[1.0, 0.5], period_s=6.0, altitude_m=1.0, laps=1)
    times, states = _fly(model, SE3Controller(vehicle), eight.sample, eight.duration_s)
    desired = np.array([eight.sample(t).p_W for t in times])
    err = np.linalg.norm(_positions(states) - desired, axis=1)
    rms = float(np.sqrt(np.mean(err**2)))
    speed = max(np.linalg.norm(eight.sample(t).v_W) for t in times)
    assert speed > 1.0  # a real manoeuvre
    assert rms < 0.05


def test_takeoff_from_ground(model: mujoco.MjModel, vehicle: VehicleParams) -> None:
    start = np.array(model.body("quadrotor").pos)
    plan = Sequence(
        [Takeoff(start_W_m=start, altitude_m=1.0, duration_s=2.5), HoverPoint(p_W=[*start[:2], 1.0])]
    )
    times, states = _fly(model, SE3Controller(vehicle), plan.sample, 4.0, keyframe=False)
    desired = np.array([plan.sample(t).p_W for t in times])
    err = np.linalg.norm(_positions(states) - desired, axis=1)
    assert np.max(err[times > 3.5]) < 0.01
    assert np.max(err) < 0.1


def test_robust_to_estimate_noise(model: mujoco.MjModel, vehicle: VehicleParams) -> None:
    # The estimator feeds the controller: 3 cm position, 5 cm/s velocity and 5 mrad attitude noise (1 sigma).
    rng = np.random.default_rng(0)

    def noisy(truth: NavState) -> NavState:
        tilt = 0.005 * rng.normal(size=3)
        skew_tilt = np.array([[0, -tilt[2], tilt[1]], [tilt[2], 0, -tilt[0]], [-tilt[1], tilt[0], 0]])
        R = truth.R_WB @ (np.eye(3) + skew_tilt)
        u, _, vt = np.linalg.svd(R)
        return NavState(
            R_WB=u @ vt,
            p_WB=truth.p_WB + 0.03 * rng.normal(size=3),
            v_WB=truth.v_WB + 0.05 * rng.normal(size=3),
            omega_B=truth.omega_B + 0.01 * rng.normal(size=3),
        )

    hover = HoverPoint(p_W=[0.0, 0.0, 1.0])
    _, states = _fly(model, SE3Controller(vehicle), hover.sample, 3.0, measure=noisy)
    err = np.linalg.norm(_positions(states) - [0.0, 0.0, 1.0], axis=1)
    tilt = np.array([np.arccos(np.clip(s.R_WB[2, 2], -1, 1)) for s in states])
    assert float(np.sqrt(np.mean(err**2))) < 0.01  # 3 cm white noise is filtered to ~4 mm by the loop
    assert np.max(tilt) < np.deg2rad(5.0)


def test_integral_removes_mass_mismatch(model: mujoco.MjModel, vehicle: VehicleParams) -> None:
    # The controller believes the vehicle is 10 % lighter than the MJCF's 1.2 kg.
    light = VehicleParams(
        mass_kg=0.9 * vehicle.mass_kg,
        inertia_kg_m2=vehicle.inertia_kg_m2,
        rotor_positions_B_m=vehicle.rotor_positions_B_m,
        thrust_axes_B=vehicle.thrust_axes_B,
        yaw_moment_coeff_m=vehicle.yaw_moment_coeff_m,
        min_thrust_N=vehicle.min_thrust_N,
        max_thrust_N=vehicle.max_thrust_N,
        gravity_m_s2=vehicle.gravity_m_s2,
    )
    hover = HoverPoint(p_W=[0.0, 0.0, 1.0])
    _, no_int = _fly(model, SE3Controller(light), hover.sample, 6.0)
    gains = SE3Gains(ki_N_m_s=np.array([2.0, 2.0, 8.0]))
    _, with_int = _fly(model, SE3Controller(light, gains), hover.sample, 6.0)
    # Without the integral: steady sag of 0.1 m g / k_p,z.
    expected_sag = 0.1 * vehicle.hover_thrust_N / SE3Gains().kp_N_m[2]
    assert 1.0 - no_int[-1].p_WB[2] == pytest.approx(expected_sag, rel=0.05)
    assert abs(1.0 - with_int[-1].p_WB[2]) < 0.1 * expected_sag
