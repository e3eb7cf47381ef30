"""The plain-float SE(3) controller and mixer against the numpy formulation they replaced.

The reference below is the numpy controller as it was before the per-tick arithmetic moved to Python floats
(matrix products, ``np.linalg.norm``, the mixer's ``A^-1 @ w``), an independent implementation of the same
equations. Only the summation order differs (BLAS fused multiply-adds against left-to-right float sums), so
commands must agree to round-off over a sequence of updates (the integral state carries over), in the
unsaturated, tilt-limited and saturated regimes.
"""

from __future__ import annotations

import numpy as np
import pytest
from viotb.controllers.mixer import Mixer
from viotb.controllers.se3 import SE3Controller, SE3Gains, attitude_error, desired_attitude
from viotb.controllers.types import FlatOutput, NavState
from viotb.envs.sim.vehicle import vehicle_params_from_model
from viotb.models import load_model
from viotb.vio.lie import exp_so3


def _ref_desired_attitude(force_W, yaw_rad):
    b3 = force_W / np.linalg.norm(force_W)
    b2 = np.cross(b3, np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0]))
    b2 /= np.linalg.norm(b2)
    return np.column_stack([np.cross(b2, b3), b2, b3])


def _ref_vee(m):
    return np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) * 0.5


class _RefController:
    """The numpy SE(3) controller (Lee et al. 2010; Mellinger & Kumar 2011), as before the float path."""

    def __init__(self, vehicle, gains, mixer):
        self.v, self.g, self.mixer = vehicle, gains, mixer
        self.integral = np.zeros(3)
        self.last_t = None

    def thrusts_and_attitude(self, t_s, state, sp):
        g, m, R = self.g, self.v.mass_kg, state.R_WB
        e_p, e_v = state.p_WB - sp.p_W, state.v_WB - sp.v_W
        if self.last_t is not None and 0.0 < t_s - self.last_t <= 0.1:
            self.integral = self.integral + e_p * (t_s - self.last_t)
        self.last_t = t_s
        limit = np.full(3, np.inf)
        np.divide(g.integral_limit_N, g.ki_N_m_s, out=limit, where=g.ki_N_m_s > 0.0)
        self.integral = np.clip(self.integral, -limit, limit)
        force = (
            -g.kp_N_m * e_p
            - g.kv_N_s_m * e_v
            - g.ki_N_m_s * self.integral
            + m * (sp.a_W - self.v.gravity_W_m_s2)
        )
        force[2] = max(force[2], g.min_thrust_fraction * self.v.hover_thrust_N)
        horizontal, max_h = np.linalg.norm(force[:2]), force[2] * np.tan(g.max_tilt_rad)
        if horizontal > max_h:
            force[:2] *= max_h / horizontal
        collective = float(force @ (R @ np.array([0.0, 0.0, 1.0])))
        R_d = _ref_desired_attitude(force, sp.yaw_rad)
        b1, b2, b3 = R_d[:, 0], R_d[:, 1], R_d[:, 2]
        h = (m / np.linalg.norm(force)) * (sp.j_W - (b3 @ sp.j_W) * b3)
        omega_d = np.array([-h @ b2, h @ b1, sp.yaw_rate_rad_s * b3[2]])
        omega_d_B = R.T @ R_d @ omega_d
        e_R = 0.5 * _ref_vee(R_d.T @ R - R.T @ R_d)
        J, w = self.v.inertia_kg_m2, state.omega_B
        moments = (
            -g.kR_Nm_rad * e_R
            - g.kw_Nm_s_rad * (w - omega_d_B)
            + np.cross(w, J @ w)
            - J @ np.cross(w, omega_d_B)
        )
        exact = np.linalg.inv(self.mixer.allocation) @ np.concatenate([[collective], moments])
        return exact, R_d


@pytest.fixture(scope="module")
def vehicle():
    return vehicle_params_from_model(load_model("quadrotor", "empty"))


def _random_state(rng, scale):
    R = exp_so3(rng.normal(0.0, 0.05 * scale, 3))
    return NavState(
        R_WB=R,
        p_WB=rng.normal(0.0, 0.1 * scale, 3),
        v_WB=rng.normal(0.0, 0.1 * scale, 3),
        omega_B=rng.normal(0.0, 0.2 * scale, 3),
    )


def _random_setpoint(rng, scale):
    return FlatOutput(
        p_W=rng.normal(0.0, 0.1 * scale, 3),
        v_W=rng.normal(0.0, 0.1 * scale, 3),
        a_W=rng.normal(0.0, 0.5 * scale, 3),
        j_W=rng.normal(0.0, 1.0 * scale, 3),
        yaw_rad=float(rng.normal(0.0, 0.05 * scale)),
        yaw_rate_rad_s=float(rng.normal(0.0, 0.2 * scale)),
    )


@pytest.mark.parametrize("scale", [0.3, 1.0, 4.0])
def test_float_controller_matches_numpy_reference(vehicle, scale):
    """Thrusts and desired attitude agree to round-off over 400 updates (integral on), every regime."""
    rng = np.random.default_rng(11)
    gains = SE3Gains(ki_N_m_s=np.array([0.8, 0.8, 1.5]), integral_limit_N=0.5)
    mixer = Mixer(vehicle)
    ctrl, ref = SE3Controller(vehicle, gains), _RefController(vehicle, gains, mixer)
    lo, hi = vehicle.min_thrust_N, vehicle.max_thrust_N
    n_exact = n_sat = 0
    for k in range(400):
        t = 0.004 * k
        state, sp = _random_state(rng, scale), _random_setpoint(rng, scale)
        cmd = ctrl.update(t, state, sp)
        exact, R_d = ref.thrusts_and_attitude(t, state, sp)
        np.testing.assert_allclose(cmd.R_WB_desired, R_d, rtol=0, atol=1e-13)
        np.testing.assert_allclose(ctrl.integral_m_s, ref.integral, rtol=1e-12, atol=1e-15)
        if np.all(exact >= lo + 1e-9) and np.all(exact <= hi - 1e-9):
            n_exact += 1
            np.testing.assert_allclose(cmd.thrusts_N, exact, rtol=1e-12, atol=1e-12)
        else:  # saturated: the policy's result for the reference wrench (continuous in it)
            n_sat += 1
            wrench = mixer.allocation @ exact
            expected = mixer.motor_thrusts(float(wrench[0]), wrench[1:])
            np.testing.assert_allclose(cmd.thrusts_N, expected, rtol=0, atol=1e-9)
    assert (n_sat if scale > 1.0 else n_exact) > 100, (n_exact, n_sat)


def test_public_helpers_match_numpy_reference():
    """``desired_attitude`` and ``attitude_error`` (float kernels underneath) against numpy."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        force = rng.normal(0.0, 3.0, 3) + np.array([0.0, 0.0, 12.0])
        yaw = float(rng.uniform(-np.pi, np.pi))
        R_d = desired_attitude(force, yaw)
        np.testing.assert_allclose(R_d, _ref_desired_attitude(force, yaw), rtol=0, atol=1e-14)
        R = exp_so3(rng.normal(0.0, 0.5, 3))
        np.testing.assert_allclose(
            attitude_error(R, R_d), 0.5 * _ref_vee(R_d.T @ R - R.T @ R_d), rtol=0, atol=1e-14
        )


def test_mixer_float_path_matches_matrix_inverse(vehicle):
    """``motor_thrusts_f`` inverts like ``A^-1 @ w`` within limits and raises on a non-finite request."""
    mixer = Mixer(vehicle)
    inv = np.linalg.inv(mixer.allocation)
    rng = np.random.default_rng(2)
    for _ in range(300):
        f_true = rng.uniform(vehicle.min_thrust_N + 0.05, vehicle.max_thrust_N - 0.05)
        w = mixer.allocation @ f_true
        np.testing.assert_allclose(mixer.motor_thrusts_f(*w.tolist()), inv @ w, rtol=1e-13, atol=1e-13)
    with pytest.raises(ValueError, match="finite"):
        mixer.motor_thrusts_f(float("nan"), 0.0, 0.0, 0.0)


def test_records_check_all_fields_in_one_buffer_and_name_the_bad_one():
    """NavState / FlatOutput (one shared buffer) still reject a bad field by name and stay read-only."""
    R = np.eye(3)
    with pytest.raises(ValueError, match=r"NavState\.omega_B: non-finite"):
        NavState(R_WB=R, p_WB=np.zeros(3), v_WB=np.zeros(3), omega_B=np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match=r"FlatOutput\.a_W: expected shape \(3,\)"):
        FlatOutput(p_W=np.zeros(3), a_W=np.zeros(4))
    state = NavState(R_WB=R, p_WB=[1, 2, 3])
    np.testing.assert_array_equal(state.p_WB, [1.0, 2.0, 3.0])
    assert state.p_WB.dtype == np.float64 and state.R_WB.shape == (3, 3)
    with pytest.raises(ValueError):
        state.R_WB[0, 0] = 2.0
    source = np.array([0.5, 0.0, 0.0])
    sp = FlatOutput(p_W=source)
    source[0] = 9.0  # a copy: the record does not follow its input
    assert sp.p_W[0] == 0.5


def test_thrusts_from_estimate_equals_thrusts_on_the_record(vehicle):
    """No navigation record on the per-tick path: the same thrusts bit for bit, the same errors."""
    from viotb.vio.types import StateEstimate

    rng = np.random.default_rng(11)
    a, b = SE3Controller(vehicle, SE3Gains()), SE3Controller(vehicle, SE3Gains())
    for k in range(200):
        x, sp = _random_state(rng, 1.0), _random_setpoint(rng, 1.0)
        est = StateEstimate(t_s=0.004 * k, R_WB=x.R_WB, p_WB=x.p_WB, v_WB=x.v_WB, omega_B_rad_s=x.omega_B)
        t = 0.004 * k
        np.testing.assert_array_equal(
            a.thrusts_from_estimate(t, est, sp), b.thrusts(t, NavState.from_estimate(est), sp)
        )
    np.testing.assert_array_equal(a.integral_m_s, b.integral_m_s)
    bad = StateEstimate(t_s=1.0, R_WB=np.eye(3), p_WB=np.array([0.0, np.nan, 0.0]), v_WB=np.zeros(3))
    with pytest.raises(ValueError, match=r"NavState\.p_WB: non-finite"):
        a.thrusts_from_estimate(1.0, bad, sp)
    wrong = StateEstimate(t_s=1.0, R_WB=np.eye(3), p_WB=np.zeros(2), v_WB=np.zeros(3))
    with pytest.raises(ValueError, match=r"NavState\.p_WB: expected shape"):
        a.thrusts_from_estimate(1.0, wrong, sp)
