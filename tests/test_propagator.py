"""Tests of vio/propagator.py: interpolation, transition matrix vs finite differences, FEJ, noise."""

import numpy as np
import pytest
from random_states import random_imu_values
from viotb.vio.lie import exp_so3, log_so3, skew
from viotb.vio.propagator import (
    ImuBuffer,
    Integration,
    Propagator,
    discrete_noise,
    integrate_step,
    propagate_values,
    select_imu_readings,
)
from viotb.vio.state import IMU_BLOCK, ImuValues, State, is_psd, marginal_covariance
from viotb.vio.types import GRAVITY_M_S2, ImuNoise, ImuSample, gravity_W
from viotb.vio.window_factors import boxminus as _boxminus
from viotb.vio.window_factors import retract as _boxplus


def test_select_imu_readings_interpolates_the_ends():
    t = np.array([0.0, 0.1, 0.2, 0.3])
    g = np.stack([t, 2 * t, -t], axis=1)
    ts, gs, _ = select_imu_readings(t, g, g, 0.05, 0.25)
    np.testing.assert_allclose(ts, [0.05, 0.1, 0.2, 0.25])
    np.testing.assert_allclose(gs[:, 0], ts, atol=1e-15)
    np.testing.assert_allclose(gs[:, 1], 2 * ts, atol=1e-15)
    with pytest.raises(ValueError, match="must be after"):
        select_imu_readings(t, g, g, 0.2, 0.1)


@pytest.mark.parametrize("method", [Integration.DISCRETE, Integration.RK4])
def test_transition_matrix_matches_central_differences(method):
    rng = np.random.default_rng(0)
    x0 = random_imu_values(rng)
    t = np.linspace(0.0, 0.05, 6)
    gyro = rng.normal(0, 1.0, (6, 3))
    accel = rng.normal(0, 3.0, (6, 3)) + np.array([0, 0, 9.81])
    noise = ImuNoise()
    x1, phi, _ = propagate_values(x0, t, gyro, accel, method, noise)
    eps = 1e-6
    num = np.zeros((15, 15))
    for i in range(15):
        d = np.zeros(15)
        d[i] = eps
        xp, _, _ = propagate_values(_boxplus(x0, d), t, gyro, accel, method, noise)
        xm, _, _ = propagate_values(_boxplus(x0, -d), t, gyro, accel, method, noise)
        num[:, i] = (_boxminus(xp, x1) - _boxminus(xm, x1)) / (2 * eps)
    np.testing.assert_allclose(phi, num, atol=2e-7)


def test_constant_rate_and_stationary_closed_forms():
    noise = ImuNoise()
    x0 = ImuValues(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    w = np.array([0.1, -0.2, 0.3])
    t = np.linspace(0, 1.0, 201)
    still = np.tile([0.0, 0.0, GRAVITY_M_S2], (201, 1))
    for method in Integration:
        x1, _, _ = propagate_values(x0, t, np.tile(w, (201, 1)), np.zeros((201, 3)), method, noise)
        np.testing.assert_allclose(x1.R_WB, exp_so3(w * 1.0), atol=1e-12)
        # Free fall: zero specific force.
        np.testing.assert_allclose(x1.v_WB, gravity_W() * 1.0, atol=1e-12)
        np.testing.assert_allclose(x1.p_WB, 0.5 * gravity_W(), atol=1e-12)
        x2, _, _ = propagate_values(x0, t, np.zeros((201, 3)), still, method, noise)
        np.testing.assert_allclose(x2.p_WB, 0.0, atol=1e-12)
        np.testing.assert_allclose(x2.v_WB, 0.0, atol=1e-12)


def test_discrete_noise_closed_form_for_a_level_still_step():
    noise = ImuNoise()
    x0 = ImuValues(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    dt = 0.005
    _, phi = integrate_step(x0, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), dt, Integration.DISCRETE)
    Q = discrete_noise(phi, noise, dt)
    sa2, sg2 = noise.accel_noise_density_m_s2_sqrthz**2, noise.gyro_noise_density_rad_s_sqrthz**2
    np.testing.assert_allclose(Q[6:9, 6:9], sa2 * dt * np.eye(3), rtol=1e-12)
    np.testing.assert_allclose(Q[3:6, 3:6], sa2 * dt**3 / 4 * np.eye(3), rtol=1e-12)
    np.testing.assert_allclose(Q[0:3, 0:3], sg2 * dt * np.eye(3), rtol=1e-12)
    np.testing.assert_allclose(Q[9:12, 9:12], noise.gyro_random_walk_rad_s2_sqrthz**2 * dt * np.eye(3))
    assert np.linalg.eigvalsh(Q).min() > -1e-20


def _yaw_position_nullspace(x: ImuValues) -> np.ndarray:
    """Columns: global translation (3) and yaw (1) in the right-perturbation error state (15, 4)."""
    N = np.zeros((15, 4))
    N[3:6, 0:3] = np.eye(3)
    ez = np.array([0.0, 0.0, 1.0])
    N[0:3, 3] = x.R_WB.T @ ez
    N[3:6, 3] = skew(ez) @ x.p_WB
    N[6:9, 3] = skew(ez) @ x.v_WB
    return N


@pytest.mark.parametrize("method", [Integration.DISCRETE, Integration.RK4])
def test_fej_transition_maps_the_unobservable_directions(method):
    rng = np.random.default_rng(1)
    x0 = random_imu_values(rng)
    fej = _boxplus(x0, rng.normal(0, 0.05, 15))  # first estimates differ from the current (updated) values
    t = np.linspace(0.0, 0.05, 6)
    gyro = rng.normal(0, 1.0, (6, 3))
    accel = rng.normal(0, 3.0, (6, 3))
    x1, phi, _ = propagate_values(x0, t, gyro, accel, method, ImuNoise(), imu_fej=fej)
    np.testing.assert_allclose(phi @ _yaw_position_nullspace(fej), _yaw_position_nullspace(x1), atol=1e-9)
    _, phi_plain, _ = propagate_values(x0, t, gyro, accel, method, ImuNoise())
    assert np.abs(phi_plain @ _yaw_position_nullspace(fej) - _yaw_position_nullspace(x1)).max() > 1e-4


def test_buffer_rejects_nan_and_out_of_order_with_clear_messages():
    buf = ImuBuffer(capacity=2)
    for k in range(5):  # grows past the initial capacity
        buf.feed(ImuSample(0.01 * k, np.zeros(3), np.array([0, 0, 9.81])))
    assert len(buf) == 5
    with pytest.raises(ValueError, match=r"t=0\.050000 s: gyro_B_rad_s=\[nan"):
        buf.feed(ImuSample(0.05, np.array([np.nan, 0, 0]), np.zeros(3)))
    with pytest.raises(ValueError, match=r"t=0\.030000000 s after t=0\.040000000 s"):
        buf.feed(ImuSample(0.03, np.zeros(3), np.zeros(3)))
    buf.clean_older_than(0.025)
    np.testing.assert_allclose(buf.arrays()[0], [0.02, 0.03, 0.04])


def test_propagate_and_clone_keeps_covariance_psd_and_time_offset_jacobian():
    rng = np.random.default_rng(0)
    noise = ImuNoise()
    x0 = random_imu_values(rng)
    x0.v_WB = np.array([1.0, 0.5, -0.2])

    def run(offset_s: float) -> State:
        st = State(0.0, x0, np.eye(15) * 1e-4, np.eye(3), np.zeros(3), offset_s, time_offset_var_s2=1e-6)
        prop = Propagator(noise, Integration.RK4)
        for k in range(41):
            prop.feed_imu(ImuSample(0.005 * k, np.array([0.3, -0.2, 0.5]), np.array([0.5, 0.1, 9.9])))
        prop.propagate_and_clone(st, 0.1)
        prop.propagate_and_clone(st, 0.15)
        return st

    st = run(0.002)
    assert is_psd(st)
    np.testing.assert_allclose(st.cov, st.cov.T, atol=1e-15)
    imu_var = np.diag(marginal_covariance(st, [st.block(IMU_BLOCK)]))
    assert np.all(imu_var > 1e-4 - 1e-12)
    # The clone at camera time 0.1 depends on the offset through [omega; v] (checked by central differences).
    eps = 1e-5
    cp, cm = run(0.002 + eps).clones[0.1], run(0.002 - eps).clones[0.1]
    c = st.clones[0.1]
    dtheta = log_so3(c.R_WB.T @ cp.R_WB) - log_so3(c.R_WB.T @ cm.R_WB)
    num = np.concatenate([dtheta, cp.p_WB - cm.p_WB]) / (2 * eps)
    blk = st.clone_block(0.1)
    td = st.block("time_offset").offset
    # cross-covariance / var(td) = Jacobian of the clone w.r.t. td at cloning time (time offset is static)
    jac = st.cov[blk.indices, td] / st.cov[td, td]
    np.testing.assert_allclose(jac, num, rtol=1e-3, atol=1e-6)


def test_imu_sample_validation_fast_path_agrees_with_the_checks():
    """The plain-float pass of valid samples accepts exactly what the array checks accept."""
    from viotb.vio.propagator import validate_imu_sample

    def checks(sample, last):  # the array checks alone (a list is never on the fast path)
        validate_imu_sample(ImuSample(sample.t_s, list(sample.gyro_B_rad_s), list(sample.accel_B_m_s2)), last)

    big = np.finfo(float).max
    cases = [
        (0.1, np.zeros(3), np.array([0.0, 0.0, 9.81]), None),
        (0.1, np.zeros(3), np.array([0.0, 0.0, 9.81]), 0.1),  # not after the last
        (0.1, np.array([big, big, 0.0]), np.zeros(3), 0.0),  # finite, but the sum overflows
        (0.1, np.array([np.inf, 0.0, 0.0]), np.zeros(3), 0.0),
        (0.1, np.zeros(3), np.array([0.0, np.nan, 0.0]), 0.0),
        (np.inf, np.zeros(3), np.zeros(3), None),
        (0.2, np.arange(3), np.ones(3, dtype=np.float32), 0.1),
    ]
    for t, g, a, last in cases:
        sample = ImuSample(t, g, a)
        outcomes = []
        for fn in (validate_imu_sample, checks):
            try:
                fn(sample, last)
                outcomes.append(None)
            except ValueError as exc:
                outcomes.append(str(exc))
        assert outcomes[0] == outcomes[1], (t, g, a, last)
