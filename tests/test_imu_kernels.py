"""The compiled propagation (vio/imu_kernels.py) against its numpy reference (vio/imu_integration.py).

Every kernel must equal the numpy function it replaces to 1e-9 relative (the last bits differ only where a
3 x 3 or 15 x 15 product is summed in another order than BLAS sums it) on random IMU streams: aggressive
rates and forces, tiny rotations (the series branches of Rodrigues' formulas), both integrators, first
estimates, zero-length intervals. The per-sample filter of ``tests/test_propagation_batch.py`` checks the
compiled span against the unbatched numpy filter as well.
"""

import numpy as np
import pytest
from random_states import random_imu_values
from viotb.vio import imu_kernels as kernels
from viotb.vio.imu_integration import (
    Integration,
    discrete_noise,
    discrete_noise_batch,
    integrate_mean,
    step_transition,
    step_transitions,
)
from viotb.vio.imu_kernels_calls import chain_links, mean_record, noise_vector, step_chain_totals, step_links
from viotb.vio.lie import exp_so3, right_jacobian_so3
from viotb.vio.propagator import Propagator, propagate_values
from viotb.vio.types import ImuNoise, ImuSample

METHODS = [Integration.DISCRETE, Integration.RK4]


def _assert_rel(actual: np.ndarray, desired: np.ndarray, rel: float = 1e-9) -> None:
    scale = float(np.max(np.abs(desired)))
    np.testing.assert_allclose(actual, desired, rtol=rel, atol=rel * scale)


def _readings(rng: np.random.Generator, n: int, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    gyro = rng.normal(0, 2.0 * scale, (n, 3))
    accel = rng.normal(0, 1.0, (n, 3)) + np.array([0.0, 0.0, 9.81])
    return gyro, accel


@pytest.mark.parametrize("scale", [1.0, 1e-7, 1e-10])
def test_rodrigues_kernel_equals_the_lie_functions(scale):
    rng = np.random.default_rng(3)
    for _ in range(50):
        phi = rng.normal(size=3) * scale
        _assert_rel(kernels._rodrigues(phi, False), exp_so3(phi), 1e-12)
        _assert_rel(kernels._rodrigues(phi, True), right_jacobian_so3(phi), 1e-12)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scale", [1.0, 1e-7, 1e-10])
def test_mean_kernel_equals_integrate_mean(method, scale):
    rng = np.random.default_rng(11)
    x = random_imu_values(rng, sigma_p_m=2.0, sigma_bg_rad_s=0.02, sigma_ba_m_s2=0.2)
    for _ in range(30):
        (w0, w1), (a0, a1) = _readings(rng, 2, scale)
        dt = float(rng.uniform(0.001, 0.02))
        ref = integrate_mean(x, w0, w1, a0, a1, dt, method)
        new = mean_record(x, w0, w1, a0, a1, dt, method)
        for field in ("theta", "R1", "theta_m", "Rm", "am", "a1"):
            want, got = getattr(ref, field), getattr(new, field)
            if want is None:
                assert got is None, field
            else:
                _assert_rel(got, want)
        _assert_rel(new.new.R_WB, ref.new.R_WB)
        _assert_rel(new.new.p_WB, ref.new.p_WB)
        _assert_rel(new.new.v_WB, ref.new.v_WB)
        np.testing.assert_array_equal(new.new.gyro_bias_rad_s, x.gyro_bias_rad_s)
        assert new.start is x and new.method == method and new.dt == dt
        x = new.new


@pytest.mark.parametrize("method", METHODS)
def test_step_links_equal_the_numpy_transitions_and_noises(method):
    rng = np.random.default_rng(4)
    x = random_imu_values(rng, sigma_p_m=2.0, sigma_bg_rad_s=0.02, sigma_ba_m_s2=0.2)
    noise = ImuNoise()
    gyro, accel = _readings(rng, 13)
    steps = []
    for k in range(12):
        dt = float(rng.uniform(0.002, 0.008))
        steps.append(integrate_mean(x, gyro[k], gyro[k + 1], accel[k], accel[k + 1], dt, method))
        x = steps[-1].new
    phis, qs = step_links(steps, noise)
    dts = np.array([s.dt for s in steps])
    _assert_rel(phis, step_transitions(steps))
    _assert_rel(qs, discrete_noise_batch(step_transitions(steps), noise, dts))
    for k, step in enumerate(steps):  # and each against the per-interval functions
        phi = step_transition(step)
        _assert_rel(phis[k], phi)
        _assert_rel(qs[k], discrete_noise(phi, noise, step.dt))
    # The kernel's own records (the compiled prediction's steps), and the links chained in the same call.
    compiled = [
        mean_record(s.start, gyro[k], gyro[k + 1], accel[k], accel[k + 1], s.dt, method)
        for k, s in enumerate(steps)
    ]
    phis_c, qs_c = step_links(compiled, noise)
    _assert_rel(phis_c, phis)
    _assert_rel(qs_c, qs)
    phi0, q0 = np.eye(15), np.diag(rng.uniform(0.1, 1.0, 15))
    tots = step_chain_totals(compiled, noise, phi0, q0)
    for got, want in zip(tots, chain_links(phis, qs, phi0, q0), strict=True):
        _assert_rel(got, want)


@pytest.mark.parametrize("d", [15, 21])
def test_chain_totals_equal_the_numpy_recursion(d):
    """Dense and structured links: the zero-skipping products give the dense products' sums."""
    rng = np.random.default_rng(d)
    m = 9
    phis = rng.normal(size=(m, d, d))
    phis[:, :, 4] = 0.0  # structural zeros, as the transitions have
    phis[::2, 3:9, 9:12] = 0.0
    A = rng.normal(size=(m, d, d))
    qs = A @ np.swapaxes(A, 1, 2)
    phi0, q0 = rng.normal(size=(d, d)), np.eye(d) * 0.3
    phi_tots, q_tots = chain_links(phis, qs, phi0, q0)
    phi_tot, q_tot = phi0, q0
    for k in range(m):
        phi_tot, q_tot = phis[k] @ phi_tot, phis[k] @ q_tot @ phis[k].T + qs[k]
        _assert_rel(phi_tots[k], phi_tot)
        _assert_rel(q_tots[k], q_tot)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("with_fej", [False, True])
def test_compiled_span_equals_the_numpy_span(method, seed, with_fej):
    """``propagate_values`` compiled against its numpy path: mean, span ``Phi``, ``Q`` and covariance."""
    rng = np.random.default_rng(20 + seed)
    x0 = random_imu_values(rng, sigma_p_m=2.0, sigma_bg_rad_s=0.02, sigma_ba_m_s2=0.2)
    fej = random_imu_values(rng, sigma_p_m=2.0, sigma_bg_rad_s=0.02, sigma_ba_m_s2=0.2) if with_fej else None
    n = 6 + 17 * seed
    t = np.cumsum(rng.uniform(0.002, 0.008, n))
    t[n // 2] = t[n // 2 - 1]  # a zero-length interval (skipped by both)
    gyro, accel = _readings(rng, n)
    noise = ImuNoise()
    ref, phi_ref, q_ref = propagate_values(x0, t, gyro, accel, method, noise, fej, None, False)
    new, phi, q = propagate_values(x0, t, gyro, accel, method, noise, fej, None, True)
    for field in ("R_WB", "p_WB", "v_WB"):
        _assert_rel(getattr(new, field), getattr(ref, field))
    np.testing.assert_array_equal(new.accel_bias_m_s2, x0.accel_bias_m_s2)
    _assert_rel(phi, phi_ref)
    _assert_rel(q, q_ref)
    A = rng.normal(size=(15, 15))
    P0 = A @ A.T * 1e-2 + np.eye(15) * 1e-4
    _assert_rel(phi @ P0 @ phi.T + q, phi_ref @ P0 @ phi_ref.T + q_ref)
    one = propagate_values(x0, t[:2], gyro[:2], accel[:2], method, noise, fej, None, True)
    one_ref = propagate_values(x0, t[:2], gyro[:2], accel[:2], method, noise, fej, None, False)
    for got, want in zip(one[1:], one_ref[1:], strict=True):  # a single interval (the per-tick case)
        _assert_rel(got, want)


def test_noise_vector_order_and_the_propagator_switch():
    noise = ImuNoise(1.0, 2.0, 3.0, 4.0)
    np.testing.assert_array_equal(
        noise_vector(noise),
        [
            noise.gyro_noise_density_rad_s_sqrthz,
            noise.gyro_random_walk_rad_s2_sqrthz,
            noise.accel_noise_density_m_s2_sqrthz,
            noise.accel_random_walk_m_s3_sqrthz,
        ],
    )
    rng = np.random.default_rng(8)
    x0 = random_imu_values(rng)
    props = [Propagator(ImuNoise(), compiled=c) for c in (False, True)]
    gyro, accel = _readings(rng, 5)
    for p in props:
        for k in range(5):
            p.feed_imu(ImuSample(0.005 * k, gyro[k], accel[k]))
    (ref, phi_ref, q_ref), (new, phi, q) = (p.predict(x0, 0.0013, 0.0171) for p in props)
    _assert_rel(new.p_WB, ref.p_WB)
    _assert_rel(phi, phi_ref)
    _assert_rel(q, q_ref)
    (v_ref, s_ref), (v_new, s_new) = (p.predict_mean(x0, 0.015, 0.02) for p in props)  # one interval
    _assert_rel(v_new.R_WB, v_ref.R_WB)
    _assert_rel(s_new.theta_m, s_ref.theta_m)
