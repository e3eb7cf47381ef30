"""Online IMU intrinsics (vio/imu_intrinsics.py, the propagation): Jacobians, prediction, identifiability."""

import numpy as np
import pytest
from random_states import random_imu_values
from viotb.vio.imu_intrinsics import ImuIntrinsics, correct_readings
from viotb.vio.imu_prediction import PredictionChain
from viotb.vio.lie import exp_so3, log_so3
from viotb.vio.propagator import Integration, Propagator, propagate_values
from viotb.vio.state import IMU_DIM, ImuValues, State, ekf_update
from viotb.vio.types import ImuNoise, ImuSample
from viotb.vio.window_factors import boxminus as _boxminus
from viotb.vio.window_factors import retract as _boxplus


def _random_intrinsics(rng: np.random.Generator) -> ImuIntrinsics:
    return ImuIntrinsics(
        np.eye(3) + rng.normal(0, 0.02, (3, 3)), np.eye(3) + rng.normal(0, 0.02, (3, 3)), True, True
    )


@pytest.mark.parametrize("method", [Integration.DISCRETE, Integration.RK4])
def test_transition_with_intrinsics_matches_central_differences(method):
    """Every column of the extended Phi (IMU and both 3x3 corrections) against central differences."""
    rng = np.random.default_rng(3)
    x0 = random_imu_values(rng)
    intr = _random_intrinsics(rng)
    t = np.linspace(0.0, 0.05, 6)
    gyro = rng.normal(0, 1.0, (6, 3))
    accel = rng.normal(0, 3.0, (6, 3)) + np.array([0, 0, 9.81])
    noise = ImuNoise()
    x1, phi, q = propagate_values(x0, t, gyro, accel, method, noise, intrinsics=intr)
    d = IMU_DIM + 18
    assert phi.shape == (d, d) and q.shape == (d, d)
    eps = 1e-6
    num = np.zeros((IMU_DIM, d))
    for i in range(d):
        e = np.zeros(d)
        e[i] = eps
        xs = []
        for sign in (1.0, -1.0):
            pert = intr.copy()
            pert.boxplus(sign * e[IMU_DIM:])
            x, _, _ = propagate_values(
                _boxplus(x0, sign * e[:IMU_DIM]), t, gyro, accel, method, noise, None, pert
            )
            xs.append(x)
        num[:, i] = (_boxminus(xs[0], x1) - _boxminus(xs[1], x1)) / (2 * eps)
    scale = np.abs(num).max(axis=0, keepdims=True) + 1e-3  # per column
    assert np.max(np.abs(phi[:IMU_DIM] - num) / scale) < 1e-7  # measured 1e-8 (DISCRETE), 2e-8 (RK4)
    # The intrinsics are constants: identity rows, no process noise.
    np.testing.assert_array_equal(phi[IMU_DIM:], np.eye(d)[IMU_DIM:])
    np.testing.assert_array_equal(q[IMU_DIM:], 0.0)
    x_plain, _, _ = propagate_values(x0, t, gyro, accel, method, noise)
    assert not np.allclose(x_plain.R_WB, x1.R_WB)  # the corrections are applied to the mean


def test_identity_intrinsics_reproduce_the_plain_propagation():
    """With T = I the mean, the IMU block of Phi and Q equal the filter without intrinsics (to round-off)."""
    rng = np.random.default_rng(4)
    x0 = random_imu_values(rng)
    t = np.linspace(0.0, 0.033, 34)
    gyro = rng.normal(0, 1.0, (34, 3))
    accel = rng.normal(0, 3.0, (34, 3))
    noise = ImuNoise()
    x1, phi1, q1 = propagate_values(x0, t, gyro, accel, Integration.RK4, noise)
    x2, phi2, q2 = propagate_values(
        x0, t, gyro, accel, Integration.RK4, noise, intrinsics=ImuIntrinsics.identity(True, False)
    )
    np.testing.assert_allclose(x2.R_WB, x1.R_WB, atol=1e-14)
    np.testing.assert_allclose(x2.p_WB, x1.p_WB, atol=1e-13)
    np.testing.assert_allclose(phi2[:IMU_DIM, :IMU_DIM], phi1, atol=1e-12)
    np.testing.assert_allclose(q2[:IMU_DIM, :IMU_DIM], q1, atol=1e-18)


def test_prediction_chain_with_intrinsics_equals_the_eager_prediction():
    """The lazy chain (one StepMean per sample, batched Phi) equals one eager propagate_values."""
    rng = np.random.default_rng(5)
    intr = _random_intrinsics(rng)
    prop = Propagator(ImuNoise(), Integration.RK4)
    for k in range(12):
        prop.feed_imu(ImuSample(0.005 * k, rng.normal(0, 1.0, 3), rng.normal(0, 3.0, 3) + [0, 0, 9.81]))
    x0 = random_imu_values(rng)
    d = IMU_DIM + intr.dim
    A = rng.normal(size=(d, d))
    P0 = A @ A.T * 1e-3
    chain = PredictionChain(0, 0.01, x0, P0, prop, intr)
    for k in range(3, 12):
        index, vals = chain.advance(0.005 * k)
    cov = chain.cov(index)
    x1, phi, q = prop.predict(x0, 0.01, 0.055, intr)
    np.testing.assert_allclose(vals.R_WB, x1.R_WB, atol=1e-13)
    np.testing.assert_allclose(vals.p_WB, x1.p_WB, atol=1e-13)
    expect = (phi @ P0 @ phi.T + q)[:IMU_DIM, :IMU_DIM]
    np.testing.assert_allclose(cov, 0.5 * (expect + expect.T), rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match="P_imu has shape"):
        PredictionChain(0, 0.01, x0, np.eye(IMU_DIM), prop, intr)


def test_bad_choice_is_named():
    with pytest.raises(ValueError, match="imu_intrinsics must be one of"):
        ImuIntrinsics.from_choice("accel")
    assert ImuIntrinsics.from_choice("none") is None
    assert ImuIntrinsics.from_choice("gyro+accel").dim == 18


def _truth_rate(t: np.ndarray) -> np.ndarray:
    """Angular rate (rad/s) in B, shape (n, 3): three sinusoids, each axis excited (head-like, <= 2 rad/s)."""
    return np.stack([1.5 * np.sin(2.1 * t), 1.2 * np.sin(1.3 * t + 1.0), 2.0 * np.sin(0.9 * t + 2.0)], axis=1)


def test_filter_recovers_a_known_gyro_matrix():
    """Identifiability: a gyro with a known 3x3 scale/misalignment M and bias, the attitude measured.

    Attitude and position are measured at 25 Hz; the filter's T_g converges to M^-1 within its covariance
    (chi-square on the 9 entries, 99.9 %) and its sigma falls far below the prior.
    """
    rng = np.random.default_rng(11)
    rate_hz, seconds = 200.0, 20.0
    n = int(rate_hz * seconds) + 1
    t = np.arange(n) / rate_hz
    # Truth: attitude integrated from the rate on a 10x finer grid (midpoint rule).
    sub = 10
    R_true = np.empty((n, 3, 3))
    R = np.eye(3)
    R_true[0] = R
    h = 1.0 / rate_hz / sub
    for k in range(n - 1):
        ts = t[k] + (np.arange(sub) + 0.5) * h
        for w in _truth_rate(ts):
            R = R @ exp_so3(w * h)
        R_true[k + 1] = R
    M = np.eye(3) + np.diag([8e-3, -6e-3, 5e-3])
    M[~np.eye(3, dtype=bool)] = [3e-3, -4e-3, 2e-3, -3e-3, 4e-3, 1e-3]
    b_g = np.array([0.01, -0.02, 0.015])
    noise = ImuNoise()
    sig_g = noise.gyro_noise_density_rad_s_sqrthz * np.sqrt(rate_hz)
    sig_a = noise.accel_noise_density_m_s2_sqrthz * np.sqrt(rate_hz)
    gyro = _truth_rate(t) @ M.T + b_g + rng.normal(0, sig_g, (n, 3))
    # Still in place: specific force R^T (-g_W); the accelerometer is ideal but for its white noise.
    accel = np.einsum("kji,j->ki", R_true, [0.0, 0.0, 9.81]) + rng.normal(0, sig_a, (n, 3))
    prop = Propagator(noise, Integration.RK4)
    imu0 = ImuValues(R_true[0].copy(), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    cov0 = np.diag([1e-6] * 3 + [1e-6] * 3 + [1e-4] * 3 + [1e-3] * 3 + [1e-4] * 3)
    sigma0 = 0.02
    intr = ImuIntrinsics.identity(True, False)
    st = State(0.0, imu0, cov0, np.eye(3), np.zeros(3), intrinsics=intr, intrinsics_cov=np.eye(9) * sigma0**2)
    for k in range(n):
        prop.feed_imu(ImuSample(t[k], gyro[k], accel[k]))
    sig_rot, sig_pos = 1e-3, 1e-3
    for k in range(8, n, 8):  # 25 Hz
        prop.propagate(st, t[k])
        H = np.zeros((6, st.dim))
        H[0:3, 0:3] = np.eye(3)
        H[3:6, 3:6] = np.eye(3)
        z_rot = log_so3(st.imu.R_WB.T @ R_true[k] @ exp_so3(rng.normal(0, sig_rot, 3)))
        z_pos = rng.normal(0, sig_pos, 3) - st.imu.p_WB
        R_meas = np.diag([sig_rot**2] * 3 + [sig_pos**2] * 3)
        ekf_update(st, H, np.concatenate([z_rot, z_pos]), R_meas)
    sl = st.block("imu_intr_gyro").indices
    err = (st.intrinsics.T_g - np.linalg.inv(M)).ravel()
    P = st.cov[sl, sl]
    assert err @ np.linalg.solve(P, err) < 27.9  # chi-square(9), 99.9 %
    assert np.sqrt(np.diag(P)).max() < 0.1 * sigma0
    assert np.abs(err).max() < 2e-3  # the 1e-2 errors are found to better than 2e-3 on every entry
    # The model w = T_g (w_m - b_g) has the bias in the sensor's readings, as the simulated gyro adds it.
    np.testing.assert_allclose(st.imu.gyro_bias_rad_s, b_g, atol=5e-4)


def test_correct_readings_without_intrinsics_is_bias_removal():
    g, a = np.ones((2, 3)), 2 * np.ones((2, 3))
    w, f = correct_readings(None, g, a, np.full(3, 0.5), np.full(3, 0.25))
    np.testing.assert_array_equal(w, 0.5)
    np.testing.assert_array_equal(f, 1.75)


@pytest.mark.slow
def test_msckf_estimates_the_gyro_matrix_on_a_synthetic_flight():
    """The whole filter (``imu_intrinsics="gyro"``) on ``test_msckf``'s flight, a gyro reading M w + b.

    Simulated features (0.5 px), M with 1e-2 scale and misalignment errors, 20 s (5-20 s of CPU by load):
    the estimated ``T_g`` is within its covariance of ``M^-1`` (chi-square, 9 dof, 99.9 %; measured 4.0),
    its sigmas fall to a quarter of the 0.02 prior or less (measured 1.2e-3-5.0e-3: the yaw-rate column,
    excited by a near-constant 0.4 rad/s, is the least known) and the position NEES stays consistent.
    """
    from test_msckf import SyntheticWorld, perturbed_truth_start
    from viotb.vio.msckf import MsckfEstimator
    from viotb.vio.msckf_params import MsckfParams
    from viotb.vio.types import CameraFrame

    rng = np.random.default_rng(2)
    world = SyntheticWorld(np.random.default_rng(1002))
    noise = ImuNoise()
    est = MsckfEstimator(
        world.calib,
        noise,
        MsckfParams(frontend="sim", pixel_sigma_px=0.5, imu_intrinsics="gyro", imu_intrinsic_sigma=0.02),
    )
    M = np.eye(3) + np.diag([1e-2, -8e-3, 6e-3])
    M[~np.eye(3, dtype=bool)] = [5e-3, -6e-3, 4e-3, -5e-3, 7e-3, 3e-3]
    imu_dt = 1.0 / 200.0
    init, bg, ba = perturbed_truth_start(world, rng)
    est.initialize(init)
    nees = []
    for k in range(1, int(20.0 / imu_dt) + 1):
        t = k * imu_dt
        _, p, _, omega, f = world.pose(t)
        gyro = M @ omega + bg + rng.normal(0.0, noise.gyro_noise_density_rad_s_sqrthz / np.sqrt(imu_dt), 3)
        acc = f + ba + rng.normal(0.0, noise.accel_noise_density_m_s2_sqrthz / np.sqrt(imu_dt), 3)
        est.feed_imu(ImuSample(t, gyro, acc))
        if k % 10 == 0:
            est.feed_camera(CameraFrame(t_s=t, features=world.observe(t, rng, 0.5)))
            e = est.estimate()
            err = e.p_WB - p
            nees.append(err @ np.linalg.solve(e.cov[3:6, 3:6], err))
    st = est.state
    sl = st.block("imu_intr_gyro").indices
    err = (st.intrinsics.T_g - np.linalg.inv(M)).ravel()
    P = st.cov[sl, sl]
    assert err @ np.linalg.solve(P, err) < 27.9
    assert np.sqrt(np.diag(P)).max() < 0.25 * 0.02
    assert np.mean(nees) < 6.0


def test_state_places_the_intrinsic_blocks_after_the_imu_and_corrects_them():
    """Blocks [imu, gyro, accel, extrinsic]; an update's correction lands row-major in T_g / T_a."""
    from viotb.vio.state import ekf_propagate

    imu = ImuValues(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    intr = ImuIntrinsics.identity(True, True)
    st = State(0.0, imu, np.eye(15), np.eye(3), np.zeros(3), 0.0, np.eye(6), None, intr, np.eye(18) * 1e-4)
    assert [b.name for b in st.blocks] == ["imu", "imu_intr_gyro", "imu_intr_accel", "extrinsic"]
    assert st.block("imu_intr_gyro").offset == 15 and st.block("extrinsic").offset == 33
    assert st.propagated_dim == 33
    H = np.zeros((2, st.dim))
    H[0, 15 + 5] = 1.0  # T_g[1, 2]
    H[1, 24 + 6] = 1.0  # T_a[2, 0]
    ekf_update(st, H, np.array([0.01, -0.02]), 1e-12)
    assert st.intrinsics.T_g[1, 2] == pytest.approx(0.01) and st.intrinsics.T_a[2, 0] == pytest.approx(-0.02)
    assert intr.T_g[1, 2] == 0.0  # the state keeps a copy
    with pytest.raises(ValueError, match="must be \\(33, 33\\)"):
        ekf_propagate(st, np.eye(15), np.zeros((15, 15)))
