"""Tests for viotb.controllers.se3: hover equilibrium, attitude blocks, tilt limit, integral, feed-forward."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.controllers.se3 import SE3Controller, SE3Gains, attitude_error, desired_attitude, desired_body_rate
from viotb.controllers.setpoints import FigureEight
from viotb.controllers.types import FlatOutput, NavState, PositionController
from viotb.controllers.vehicle import VehicleParams
from viotb.envs.sim.vehicle import vehicle_params_from_model
from viotb.models import load_model


@pytest.fixture(scope="module")
def vehicle() -> VehicleParams:
    return vehicle_params_from_model(load_model("quadrotor", "empty"))


def _hover_state(p_W: np.ndarray, yaw_rad: float = 0.0) -> NavState:
    return NavState(R_WB=Rotation.from_euler("z", yaw_rad).as_matrix(), p_WB=p_W)


def test_hover_commands_mg_and_zero_moments(vehicle: VehicleParams) -> None:
    controller = SE3Controller(vehicle)
    assert isinstance(controller, PositionController)
    for yaw in (0.0, 0.7, -2.5):
        p = np.array([0.3, -1.0, 1.5])
        cmd = controller.update(0.0, _hover_state(p, yaw), FlatOutput(p_W=p, yaw_rad=yaw))
        assert cmd.collective_N == pytest.approx(1.2 * 9.81, abs=1e-12)
        np.testing.assert_allclose(cmd.moments_B_Nm, 0.0, atol=1e-12)
        np.testing.assert_allclose(cmd.thrusts_N, np.full(4, 1.2 * 9.81 / 4), atol=1e-12)
        np.testing.assert_allclose(cmd.R_WB_desired, Rotation.from_euler("z", yaw).as_matrix(), atol=1e-12)


def test_desired_attitude_matches_scipy_construction() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        force = rng.normal(size=3) + [0.0, 0.0, 4.0]
        yaw = rng.uniform(-np.pi, np.pi)
        R_d = desired_attitude(force, yaw)
        np.testing.assert_allclose(R_d.T @ R_d, np.eye(3), atol=1e-12)
        assert np.linalg.det(R_d) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(R_d[:, 2], force / np.linalg.norm(force), atol=1e-12)
        # b1 lies in the plane spanned by b3 and the heading vector (Lee 2010: b1 = proj of b1c).
        b1c = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        assert np.dot(R_d[:, 1], b1c) == pytest.approx(0.0, abs=1e-12)
        assert np.dot(R_d[:, 0], b1c) > 0.0
    # Level force: R_d is the pure yaw rotation.
    np.testing.assert_allclose(
        desired_attitude(np.array([0, 0, 5.0]), 0.4), Rotation.from_euler("z", 0.4).as_matrix(), atol=1e-12
    )


def test_attitude_error_is_sin_angle_times_axis() -> None:
    rng = np.random.default_rng(0)
    R_d = Rotation.random(random_state=3).as_matrix()
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0.0, 3.0)
        R = R_d @ Rotation.from_rotvec(angle * axis).as_matrix()  # body-frame error rotation
        np.testing.assert_allclose(attitude_error(R, R_d), np.sin(angle) * axis, atol=1e-12)


def test_moment_pushes_back_and_includes_gyroscopic_term(vehicle: VehicleParams) -> None:
    gains = SE3Gains()
    controller = SE3Controller(vehicle, gains)
    p = np.array([0.0, 0.0, 1.0])
    small_roll = NavState(R_WB=Rotation.from_euler("x", 0.01).as_matrix(), p_WB=p)
    cmd = controller.update(0.0, small_roll, FlatOutput(p_W=p))
    assert cmd.moments_B_Nm[0] < 0.0  # restoring roll moment
    assert cmd.moments_B_Nm[0] == pytest.approx(-gains.kR_Nm_rad[0] * np.sin(0.01), rel=1e-3)
    omega = np.array([0.5, -0.3, 0.2])
    spinning = NavState(R_WB=np.eye(3), p_WB=p, omega_B=omega)
    cmd = SE3Controller(vehicle, gains).update(0.0, spinning, FlatOutput(p_W=p))
    J = vehicle.inertia_kg_m2
    expected = -gains.kw_Nm_s_rad * omega + np.cross(omega, J @ omega)
    np.testing.assert_allclose(cmd.moments_B_Nm, expected, atol=1e-12)


def test_tilt_limit(vehicle: VehicleParams) -> None:
    gains = SE3Gains(max_tilt_rad=np.deg2rad(20.0))
    controller = SE3Controller(vehicle, gains)
    state = _hover_state(np.array([0.0, 0.0, 1.0]))
    cmd = controller.update(0.0, state, FlatOutput(p_W=[50.0, 20.0, 1.0]))
    tilt = np.arccos(cmd.R_WB_desired[2, 2])
    assert tilt == pytest.approx(np.deg2rad(20.0), abs=1e-12)
    # Tilt toward the target: desired b3 leans along +x, +y.
    assert cmd.R_WB_desired[0, 2] > 0.0 and cmd.R_WB_desired[1, 2] > 0.0


def test_integral_accumulates_and_is_clamped(vehicle: VehicleParams) -> None:
    gains = SE3Gains(
        kp_N_m=np.zeros(3), kv_N_s_m=np.zeros(3), ki_N_m_s=np.array([0.0, 0.0, 2.0]), integral_limit_N=1.0
    )
    controller = SE3Controller(vehicle, gains)
    state = _hover_state(np.array([0.0, 0.0, 0.9]))  # 0.1 m low
    setpoint = FlatOutput(p_W=[0.0, 0.0, 1.0])
    for t in (0.0, 0.05, 0.1, 0.15, 0.2):
        cmd = controller.update(t, state, setpoint)
    # int(e_p) = -0.1 m * 0.2 s -> integral force 2 * 0.02 N upward.
    assert cmd.collective_N == pytest.approx(1.2 * 9.81 + 2.0 * 0.02, abs=1e-9)
    # A gap longer than 0.1 s (a pause) is not integrated.
    assert controller.update(5.0, state, setpoint).collective_N == pytest.approx(cmd.collective_N, abs=1e-12)
    for k in range(1, 200):
        cmd = controller.update(5.0 + 0.05 * k, state, setpoint)
    assert cmd.collective_N == pytest.approx(1.2 * 9.81 + 1.0, abs=1e-9)  # anti-windup clamp
    controller.reset()
    assert controller.update(30.0, state, setpoint).collective_N == pytest.approx(1.2 * 9.81, abs=1e-9)


def test_desired_body_rate_matches_finite_difference_of_desired_attitude(vehicle: VehicleParams) -> None:
    # On the trajectory (zero errors), F = m (a - g): the roll/pitch feed-forward equals vee(R_d^T dR_d/dt).
    sp = FigureEight(center_xy_m=[0.0, 0.0], size_m=[1.5, 1.0], period_s=5.0, laps=1)
    m = vehicle.mass_kg
    h = 1e-5

    def r_d(t: float) -> tuple[np.ndarray, float]:
        out = sp.sample(t)
        force = m * (out.a_W - vehicle.gravity_W_m_s2)
        return desired_attitude(force, out.yaw_rad), float(np.linalg.norm(force))

    for t in (1.0, 2.2, 3.7, 5.1):
        R_mid, thrust = r_d(t)
        R_lo, _ = r_d(t - h)
        R_hi, _ = r_d(t + h)
        omega_fd = Rotation.from_matrix(R_lo.T @ R_hi).as_rotvec() / (2 * h)
        omega = desired_body_rate(R_mid, thrust, m, sp.sample(t))
        np.testing.assert_allclose(omega[:2], omega_fd[:2], atol=1e-6)
        assert np.max(np.abs(omega_fd[:2])) > 0.05  # the check is not vacuous


def test_gains_validation() -> None:
    with pytest.raises(ValueError, match="kp_N_m"):
        SE3Gains(kp_N_m=np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="max_tilt_rad"):
        SE3Gains(max_tilt_rad=2.0)
    with pytest.raises(ValueError, match="kR_Nm_rad"):
        SE3Gains(kR_Nm_rad=np.array([1.0, -1.0, 1.0]))
