"""Batched propagation (vio/propagator.py ``propagate_values``) against per-sample propagation.

The reference is the per-sample filter: :func:`integrate_step` and :func:`discrete_noise` chained interval by
interval, the covariance propagated at every IMU sample (``P <- Phi_k P Phi_k^T + Q_k``). The batched path
integrates the mean over the whole span and propagates the covariance once; both must agree to 1e-9
relative on random IMU streams, with first estimates and duplicate timestamps.
"""

from functools import partial

import numpy as np
import pytest
from random_states import random_imu_values
from viotb.vio.lie import exp_so3, exp_so3_batch, log_so3, right_jacobian_so3, right_jacobian_so3_batch
from viotb.vio.propagator import (
    Integration,
    discrete_noise,
    integrate_step,
    interpolate_readings,
    propagate_values,
    select_imu_readings,
)
from viotb.vio.types import ImuNoise

_random_imu = partial(random_imu_values, sigma_p_m=2.0, sigma_bg_rad_s=0.02, sigma_ba_m_s2=0.2)


def _random_stream(rng: np.random.Generator, n: int):
    """Jittered 200 Hz times with one repeated stamp, aggressive rates and forces."""
    t = np.cumsum(rng.uniform(0.002, 0.008, n))
    t[n // 2] = t[n // 2 - 1]  # a zero-length interval (skipped by both)
    gyro = rng.normal(0, 2.0, (n, 3))
    accel = rng.normal(0, 1.0, (n, 3)) + np.array([0.0, 0.0, 9.81])
    return t, gyro, accel


def _per_sample(x0, t, gyro, accel, method, noise, fej, P0):
    """The per-sample filter: mean and covariance stepped at every IMU interval."""
    w = gyro - x0.gyro_bias_rad_s
    a = accel - x0.accel_bias_m_s2
    cur, P = x0, P0
    for k in range(len(t) - 1):
        dt = float(t[k + 1] - t[k])
        if dt <= 0.0:
            continue
        cur, phi = integrate_step(cur, w[k], w[k + 1], a[k], a[k + 1], dt, method, fej)
        fej = None
        P = phi @ P @ phi.T + discrete_noise(phi, noise, dt)
    return cur, P


def _assert_rel(actual: np.ndarray, desired: np.ndarray, rel: float = 1e-9) -> None:
    scale = float(np.max(np.abs(desired)))
    np.testing.assert_allclose(actual, desired, rtol=rel, atol=rel * scale)


@pytest.mark.parametrize("method", [Integration.DISCRETE, Integration.RK4])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_fej", [False, True])
@pytest.mark.parametrize("compiled", [False, True])
def test_batched_propagation_equals_per_sample(method, seed, with_fej, compiled):
    rng = np.random.default_rng(seed)
    x0 = _random_imu(rng)
    fej = _random_imu(rng) if with_fej else None
    noise = ImuNoise()
    t, gyro, accel = _random_stream(rng, 4 + 9 * seed)
    A = rng.normal(size=(15, 15))
    P0 = A @ A.T * 1e-2 + np.eye(15) * 1e-4
    ref, P_ref = _per_sample(x0, t, gyro, accel, method, noise, fej, P0)
    new, phi, q = propagate_values(x0, t, gyro, accel, method, noise, fej, None, compiled)
    _assert_rel(new.R_WB, ref.R_WB)
    assert np.linalg.norm(log_so3(ref.R_WB.T @ new.R_WB)) < 1e-12
    _assert_rel(new.p_WB, ref.p_WB)
    _assert_rel(new.v_WB, ref.v_WB)
    np.testing.assert_array_equal(new.gyro_bias_rad_s, x0.gyro_bias_rad_s)
    _assert_rel(phi @ P0 @ phi.T + q, P_ref)


def test_single_interval_and_empty_span():
    rng = np.random.default_rng(5)
    x0 = _random_imu(rng)
    t, gyro, accel = np.array([0.0, 0.005]), rng.normal(size=(2, 3)), rng.normal(size=(2, 3))
    ref, phi_ref = integrate_step(
        x0, *(gyro - x0.gyro_bias_rad_s), *(accel - x0.accel_bias_m_s2), 0.005, Integration.RK4
    )
    new, phi, q = propagate_values(x0, t, gyro, accel, Integration.RK4, ImuNoise())
    _assert_rel(phi, phi_ref)
    _assert_rel(q, discrete_noise(phi_ref, ImuNoise(), 0.005))
    _assert_rel(new.p_WB, ref.p_WB)
    same, phi0, q0 = propagate_values(x0, np.array([1.0, 1.0]), gyro, accel, Integration.RK4, ImuNoise())
    np.testing.assert_array_equal(phi0, np.eye(15))
    np.testing.assert_array_equal(q0, np.zeros((15, 15)))
    np.testing.assert_array_equal(same.p_WB, x0.p_WB)


def test_batched_so3_functions_match_the_scalar_ones():
    rng = np.random.default_rng(3)
    phis = np.vstack([rng.normal(size=(20, 3)), rng.normal(size=(4, 3)) * 1e-9, np.zeros((1, 3))])
    E, J = exp_so3_batch(phis), right_jacobian_so3_batch(phis)
    for k, v in enumerate(phis):
        np.testing.assert_allclose(E[k], exp_so3(v), rtol=0, atol=1e-14)
        np.testing.assert_allclose(J[k], right_jacobian_so3(v), rtol=0, atol=1e-14)


def test_interpolation_and_selection_match_numpy_interp():
    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(0.001, 0.01, 30))
    vals = rng.normal(size=(30, 3))
    queries = np.concatenate([t[[0, 5, 29]], rng.uniform(t[0] - 0.05, t[-1] + 0.05, 40)])
    for q in queries:
        expected = np.array([np.interp(q, t, vals[:, i]) for i in range(3)])
        np.testing.assert_array_equal(interpolate_readings(t, vals, q), expected)
    for t0, t1 in (
        (t[3], t[9]),
        (t[3] + 1e-4, t[9] - 1e-4),
        (t[0] - 1.0, t[-1] + 1.0),
        (t[4] + 1e-5, t[4] + 2e-5),
    ):
        ts, gs, _ = select_imu_readings(t, vals, vals, t0, t1)
        inside = (t > t0) & (t < t1)
        np.testing.assert_array_equal(ts, np.concatenate([[t0], t[inside], [t1]]))
        np.testing.assert_array_equal(gs[1:-1], vals[inside])
        np.testing.assert_array_equal(
            gs[[0, -1]], [interpolate_readings(t, vals, t0), interpolate_readings(t, vals, t1)]
        )
