"""The joint preintegration-error covariance of the dynamic initialization against a Monte Carlo."""

from __future__ import annotations

import copy

import numpy as np
from viotb.vio.init_dynamic_cov import preintegration_error_cov, transition
from viotb.vio.lie import exp_so3, log_so3
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.types import ImuNoise

RATE_HZ = 100.0
N_SAMPLES = 60
TARGETS = tuple(range(0, N_SAMPLES + 1, 5))  # samples at which it is read: 0 (the start), then every 50 ms


def _signals():
    """A rotating, accelerating body: gyro (rad/s) and specific force (m/s^2), shape (N, 3) each."""
    t = np.arange(N_SAMPLES) / RATE_HZ
    gyro = np.column_stack([0.8 * np.sin(3.0 * t), 1.5 * np.cos(2.0 * t), 2.0 + 0.0 * t])
    accel = np.column_stack([2.0 * np.cos(4.0 * t), -1.0 + 3.0 * t, 9.81 + np.sin(5.0 * t)])
    return gyro, accel


def _snapshots(gyro, accel, noise):
    pim = ImuPreintegration(np.zeros(3), np.zeros(3), noise)
    out = [copy.deepcopy(pim)]
    for k in range(N_SAMPLES):
        pim.integrate(accel[k], gyro[k], 1.0 / RATE_HZ)
        if k + 1 in TARGETS:
            out.append(copy.deepcopy(pim))
    return out


def test_preintegration_error_cov_matches_monte_carlo():
    """White noise and bias random walk drawn per sample; the closed form uses one walk step per target."""
    noise = ImuNoise(0.01, 0.02, 0.1, 0.5)
    gyro, accel = _signals()
    clean = _snapshots(gyro, accel, noise)
    C = preintegration_error_cov(clean, noise)
    rng = np.random.default_rng(0)
    dt = 1.0 / RATE_HZ
    errs = []
    for _ in range(400):
        bg = (
            np.cumsum(rng.normal(size=(N_SAMPLES, 3)), axis=0)
            * noise.gyro_random_walk_rad_s2_sqrthz
            * dt**0.5
        )
        ba = (
            np.cumsum(rng.normal(size=(N_SAMPLES, 3)), axis=0) * noise.accel_random_walk_m_s3_sqrthz * dt**0.5
        )
        bg = np.vstack([np.zeros(3), bg[:-1]])  # the bias starts at zero (the linearization point)
        ba = np.vstack([np.zeros(3), ba[:-1]])
        g_noisy = gyro + bg + rng.normal(size=gyro.shape) * noise.gyro_noise_density_rad_s_sqrthz / dt**0.5
        a_noisy = accel + ba + rng.normal(size=accel.shape) * noise.accel_noise_density_m_s2_sqrthz / dt**0.5
        noisy = _snapshots(g_noisy, a_noisy, noise)
        e = [
            np.concatenate([log_so3(c.delta_R.T @ m.delta_R), m.delta_v - c.delta_v, m.delta_p - c.delta_p])
            for c, m in zip(clean, noisy, strict=True)
        ]
        errs.append(np.concatenate(e))
    errs = np.asarray(errs)
    C_mc = np.cov(errs.T)[9:, 9:]  # the start (index 0) has no error
    C = C[9:, 9:]
    sd, sd_mc = np.sqrt(np.diag(C)), np.sqrt(np.diag(C_mc))
    # Standard deviations within 15 % (400 draws: ~4 % sampling error) from the second interval on; in the
    # first the linear interpolation of a walk step's effect over the interval overstates the position part.
    np.testing.assert_allclose(sd_mc[9:], sd[9:], rtol=0.15)
    assert np.all(sd_mc[:9] <= 1.15 * sd[:9]) and np.all(sd_mc[:9] >= 0.6 * sd[:9])
    # Correlations between all pairs (across times and components) within 0.25 (~5 sampling sigmas).
    corr, corr_mc = C / np.outer(sd, sd), C_mc / np.outer(sd_mc, sd_mc)
    assert np.max(np.abs(corr - corr_mc)) < 0.25
    # The cross-time blocks are far from zero (the test would be vacuous otherwise).
    assert np.max(np.abs(corr[45:54, -9:])) > 0.5  # 0.3 s against 0.6 s


def test_transition_composes_increments():
    """``Phi(j, i)`` against a finite perturbation of the first part of a split preintegration."""
    noise = ImuNoise()
    gyro, accel = _signals()
    pim_i, pim_j = _snapshots(gyro, accel, noise)[3:7:3]
    # The part i -> j alone, then the composition with a perturbed 0 -> i (Forster eq. 33 form).
    part = ImuPreintegration(np.zeros(3), np.zeros(3), noise)
    for k in range(TARGETS[3], TARGETS[6]):
        part.integrate(accel[k], gyro[k], 1.0 / RATE_HZ)
    rng = np.random.default_rng(1)
    e_i = 1e-6 * rng.normal(size=9)
    R_i = pim_i.delta_R @ exp_so3(e_i[0:3])
    v_i, p_i = pim_i.delta_v + e_i[3:6], pim_i.delta_p + e_i[6:9]
    R_j = R_i @ part.delta_R
    v_j = v_i + R_i @ part.delta_v
    p_j = p_i + v_i * part.dt_s + R_i @ part.delta_p
    e_j = np.concatenate([log_so3(pim_j.delta_R.T @ R_j), v_j - pim_j.delta_v, p_j - pim_j.delta_p])
    np.testing.assert_allclose(e_j, transition(pim_i, pim_j) @ e_i, rtol=1e-4, atol=1e-11)
