"""Tests of the scripted trajectories (envs/trajectories.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.envs.scenarios.motions import (
    TRAJECTORY_FACTORIES,
    MotionParams,
    ScriptedTrajectory,
    Sinusoids,
    SmoothWarp,
    Trajectory,
)
from viotb.vio.types import GRAVITY_M_S2

NAMES = sorted(TRAJECTORY_FACTORIES)


def _rotvec_between(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Body-frame rotation vector of ``R_a^T R_b`` via scipy (independent of vio.lie)."""
    return Rotation.from_matrix(R_a.T @ R_b).as_rotvec()


@pytest.mark.parametrize("name", NAMES)
def test_finite_differences_match_analytic_derivatives(name):
    traj = TRAJECTORY_FACTORIES[name]()
    assert isinstance(traj, Trajectory)
    rng = np.random.default_rng(0)
    T = traj.duration_s
    # Inside the ramps and on the plateau (away from the clamped ends).
    times = np.concatenate(
        [rng.uniform(0.05, 1.9, 3), rng.uniform(2.1, T - 2.1, 4), rng.uniform(T - 1.9, T - 0.05, 3)]
    )
    h = 1e-4
    for t in times:
        s0, sp, sm = traj.sample(t), traj.sample(t + h), traj.sample(t - h)
        np.testing.assert_allclose((sp.p_WB - sm.p_WB) / (2 * h), s0.v_WB, atol=1e-6, rtol=0)
        np.testing.assert_allclose((sp.v_WB - sm.v_WB) / (2 * h), s0.a_WB, atol=2e-6, rtol=0)
        omega_fd = _rotvec_between(sm.R_WB, sp.R_WB) / (2 * h)
        np.testing.assert_allclose(omega_fd, s0.omega_B, atol=2e-6, rtol=0)
        np.testing.assert_allclose((sp.omega_B - sm.omega_B) / (2 * h), s0.alpha_B, atol=2e-5, rtol=0)
        np.testing.assert_allclose(s0.R_WB.T @ s0.R_WB, np.eye(3), atol=1e-12)
        assert np.linalg.det(s0.R_WB) > 0.0


def _state_derivative(x: np.ndarray, omega_B: np.ndarray, f_B: np.ndarray) -> np.ndarray:
    """Derivative of ``x = (q_xyzw, v_W, p_W)``: ``q' = q (0, omega) / 2``, ``v' = R f + g``, ``p' = v``."""
    qx, qy, qz, qw = x[:4]
    wx, wy, wz = omega_B
    q_dot = 0.5 * np.array(
        [
            qw * wx + qy * wz - qz * wy,
            qw * wy + qz * wx - qx * wz,
            qw * wz + qx * wy - qy * wx,
            -qx * wx - qy * wy - qz * wz,
        ]
    )
    R = Rotation.from_quat(x[:4]).as_matrix()
    a_W = R @ f_B + np.array([0.0, 0.0, -GRAVITY_M_S2])
    return np.concatenate([q_dot, a_W, x[4:7]])


def _integrate_imu(
    traj: Trajectory, duration_s: float, rate_hz: float = 200.0
) -> tuple[np.ndarray, np.ndarray]:
    """Dead-reckon noise-free 200 Hz IMU samples with classical RK4 on (quaternion, v, p).

    Each RK4 step spans two sample periods so that its midpoint evaluations use a real sample.
    """
    t = np.arange(int(duration_s * rate_hz) + 1) / rate_hz
    truth = traj.sample_many(t)
    gyro, f_B = truth.omega_B, truth.specific_force_B
    h = 2.0 / rate_hz
    x = np.concatenate([Rotation.from_matrix(truth.R_WB[0]).as_quat(), truth.v_WB[0], truth.p_WB[0]])
    for k in range(0, len(t) - 2, 2):
        k1 = _state_derivative(x, gyro[k], f_B[k])
        k2 = _state_derivative(x + 0.5 * h * k1, gyro[k + 1], f_B[k + 1])
        k3 = _state_derivative(x + 0.5 * h * k2, gyro[k + 1], f_B[k + 1])
        k4 = _state_derivative(x + h * k3, gyro[k + 2], f_B[k + 2])
        x = x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        x[:4] /= np.linalg.norm(x[:4])
    return x[7:10], truth.p_WB[-1]


@pytest.mark.parametrize("name", NAMES)
def test_noise_free_imu_integration_reproduces_position(name):
    """Requirement: within 1 cm over 10 s; RK4 on exact derivatives gives < 1 um, so assert 0.1 mm."""
    traj = TRAJECTORY_FACTORIES[name]()
    p_est, p_true = _integrate_imu(traj, 10.0)
    assert np.linalg.norm(p_est - p_true) < 1e-4


@pytest.mark.parametrize("name", NAMES)
def test_starts_and_ends_at_rest_inside_the_room(name):
    traj = TRAJECTORY_FACTORIES[name]()
    t = np.linspace(0.0, traj.duration_s, 801)
    s = traj.sample_many(t)
    for k in (0, -1):
        np.testing.assert_allclose(s.v_WB[k], 0.0, atol=1e-12)
        np.testing.assert_allclose(s.a_WB[k], 0.0, atol=1e-12)
        np.testing.assert_allclose(s.omega_B[k], 0.0, atol=1e-12)
    assert np.all(np.abs(s.p_WB[:, :2]) < 3.5)
    assert np.all((s.p_WB[:, 2] > 0.5) & (s.p_WB[:, 2] < 3.0))
    # Upright enough that the forward camera sees the walls (tilt < 60 deg).
    assert np.all(s.R_WB[:, 2, 2] > math.cos(math.radians(60.0)))


def test_hover_excites_acceleration_and_level_start_reads_gravity():
    s = TRAJECTORY_FACTORIES["hover"]().sample_many(np.linspace(0.0, 30.0, 601))
    np.testing.assert_allclose(s.specific_force_B[0], [0.0, 0.0, 9.81], atol=1e-12)
    acc = np.linalg.norm(s.a_WB, axis=1)
    assert 0.2 < acc.max() < 2.0


def test_flat_attitude_thrust_axis_and_yaw():
    """Differential flatness: body z along a - g; body x projects onto the yaw direction."""
    traj = TRAJECTORY_FACTORIES["aggressive"]()
    for t in np.random.default_rng(0).uniform(0.0, traj.duration_s, 20):
        s = traj.sample(t)
        thrust = s.a_WB + np.array([0.0, 0.0, GRAVITY_M_S2])
        np.testing.assert_allclose(s.R_WB[:, 2], thrust / np.linalg.norm(thrust), atol=1e-12)
        # The accelerometer of a quadrotor reads thrust only: no x/y specific force.
        np.testing.assert_allclose(s.specific_force_B[:2], 0.0, atol=1e-12)
        yaw = traj.attitude.derivatives(traj.warp.derivatives(t)[0], 0)[0, 0]
        x_c = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        assert abs(np.dot(s.R_WB[:, 1], x_c)) < 1e-12


def test_euler_attitude_matches_scipy():
    traj = TRAJECTORY_FACTORIES["head-look-around"]()
    for t in np.random.default_rng(0).uniform(0.0, traj.duration_s, 20):
        yaw, pitch, roll = traj.attitude.derivatives(traj.warp.derivatives(t)[0], 0)[0]
        R_ref = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
        np.testing.assert_allclose(traj.sample(t).R_WB, R_ref, atol=1e-12)


def test_circle_closed_form_on_plateau():
    """Circle of radius r at speed v: |v| = v, |a| = v^2 / r, yaw rate = v / r (plateau)."""
    traj = TRAJECTORY_FACTORIES["circle"](MotionParams(duration_s=20.0), radius_m=2.0, speed_m_s=1.5)
    s = traj.sample(10.0)
    np.testing.assert_allclose(np.linalg.norm(s.v_WB), 1.5, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(s.a_WB), 1.5**2 / 2.0, rtol=1e-12)
    # World-frame angular velocity is (0, 0, v / r) for a coordinated turn at constant speed.
    np.testing.assert_allclose(s.R_WB @ s.omega_B, [0.0, 0.0, 0.75], atol=1e-12)


def test_long_loop_returns_to_start_and_line_is_constant_velocity():
    loop = TRAJECTORY_FACTORIES["long-loop"]()
    a, b = loop.sample(0.0), loop.sample(loop.duration_s)
    np.testing.assert_allclose(b.p_WB, a.p_WB, atol=1e-9)
    np.testing.assert_allclose(b.R_WB, a.R_WB, atol=1e-9)
    line = TRAJECTORY_FACTORIES["line"]()
    mid = line.sample_many(np.linspace(2.5, line.duration_s - 2.5, 50))
    np.testing.assert_allclose(mid.v_WB, np.tile(mid.v_WB[0], (50, 1)), atol=1e-12)
    assert np.linalg.norm(mid.v_WB[0]) > 0.5


def test_warp_total_phase_and_bad_inputs():
    warp = SmoothWarp(10.0, 2.0, 1.5)
    np.testing.assert_allclose(warp.derivatives(10.0)[0], 2.0 * (10.0 - 1.5), rtol=1e-14)
    np.testing.assert_allclose(warp.derivatives(5.0)[1], 2.0, rtol=1e-14)
    with pytest.raises(ValueError, match="ramp_s"):
        SmoothWarp(2.0, 1.0, 1.5)
    with pytest.raises(ValueError, match="attitude_mode"):
        ScriptedTrajectory(Sinusoids((0.0, 0.0, 1.0)), Sinusoids((0.0,)), "spin", warp)
