"""Tests of vio/window_batch.py: every batched function against its one-at-a-time twin."""

from __future__ import annotations

import numpy as np
import pytest
from random_states import random_imu_values
from viotb.vio.lie import exp_so3, log_so3, right_jacobian_inv_so3, right_jacobian_so3
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.types import ImuNoise
from viotb.vio.window_batch import (
    BatchPreintegration,
    ImuFactorStack,
    boxminus_batch,
    exp_so3_batch,
    imu_factors,
    integrate_gyro,
    log_so3_batch,
    right_jacobian_batch,
    right_jacobian_inv_batch,
    stack_values,
)
from viotb.vio.window_factors import boxminus, imu_factor, preintegrate


def test_so3_maps_match_lie_including_small_and_near_pi_angles():
    """Exp, Log, Jr and Jr^-1 on random, tiny (1e-9 rad) and near-pi rotation vectors, to 1e-12."""
    rng = np.random.default_rng(0)
    phi = np.concatenate([rng.normal(size=(30, 3)), 1e-9 * rng.normal(size=(4, 3))])
    for batch, single in (
        (exp_so3_batch, exp_so3),
        (right_jacobian_batch, right_jacobian_so3),
        (right_jacobian_inv_batch, right_jacobian_inv_so3),
    ):
        out = batch(phi)
        for i, p in enumerate(phi):
            np.testing.assert_allclose(out[i], single(p), atol=1e-12)
    near_pi = np.array([[np.pi - 1e-6, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-5], [0.3, -2.0, 2.2]])
    R = np.stack([exp_so3(p) for p in np.concatenate([phi, near_pi])])
    logs = log_so3_batch(R)
    for i in range(len(R)):
        np.testing.assert_allclose(logs[i], log_so3(R[i]), atol=1e-12)


def test_stacked_imu_factors_match_imu_factor():
    """Residuals, Jacobians and square-root information of 4 factors equal ``imu_factor``'s (1e-12)."""
    rng = np.random.default_rng(1)
    noise = ImuNoise()
    xs = [random_imu_values(rng) for _ in range(5)]
    imu = []
    for k in range(4):
        t = np.arange(25) * 0.005
        pre = preintegrate(
            t,
            rng.normal(size=(25, 3)),
            rng.normal(size=(25, 3)) + [0, 0, 9.81],
            random_imu_values(rng),
            noise,
        )
        imu.append((k, pre))
    stack = ImuFactorStack.build(imu, noise)
    R, rest = stack_values(xs)
    r, J_i, J_j, _ = imu_factors(stack, R, rest)
    for i, (k, pre) in enumerate(imu):
        r1, J_i1, J_j1, C = imu_factor(pre, xs[k], xs[k + 1], noise)
        np.testing.assert_allclose(r[i], r1, atol=1e-12)
        np.testing.assert_allclose(J_i[i], J_i1, atol=1e-12)
        np.testing.assert_allclose(J_j[i], J_j1, atol=1e-12)
        W = stack.sqrt_info[i]
        np.testing.assert_allclose(W.T @ W @ C, np.eye(15), atol=1e-8)
        np.testing.assert_allclose(np.tril(W, -1), 0.0)
    R0, rest0 = stack_values(xs[::-1])
    dx = boxminus_batch(R, rest, R0, rest0)
    for i, (x, x0) in enumerate(zip(xs, xs[::-1], strict=True)):
        np.testing.assert_allclose(dx[i], boxminus(x, x0), atol=1e-12)


def test_integrate_gyro_is_the_preintegrated_rotation():
    """The gyro-only rotation equals the preintegration's ``delta_R`` at the same bias (midpoint readings)."""
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.004, 0.006, size=30))
    gyro = rng.normal(size=(30, 3)) * 3.0
    x = random_imu_values(rng)
    pre = preintegrate(t, gyro, np.tile([0.0, 0.0, 9.81], (30, 1)), x, ImuNoise())
    np.testing.assert_allclose(integrate_gyro(t, gyro, x.gyro_bias_rad_s), pre.delta_R, atol=1e-12)


@pytest.mark.parametrize("rotate_midpoint", [False, True])
def test_batch_preintegration_matches_the_sample_by_sample_recursion(rotate_midpoint):
    """Increments, bias Jacobians and covariance against ImuPreintegration.integrate, with a repeated time."""
    rng = np.random.default_rng(3)
    t = np.insert(np.cumsum(rng.uniform(0.004, 0.006, 40)), 5, 0.0)
    t[5] = t[4]  # a reading with no time step is skipped by both
    gyro = rng.normal(0.0, 1.5, (41, 3))
    accel = rng.normal(0.0, 3.0, (41, 3)) + [0.0, 0.0, 9.81]
    x = random_imu_values(rng)
    noise = ImuNoise()
    seq = ImuPreintegration(x.gyro_bias_rad_s, x.accel_bias_m_s2, noise)
    for k in range(40):
        if t[k + 1] > t[k]:
            a_mid, w_mid = 0.5 * (accel[k] + accel[k + 1]), 0.5 * (gyro[k] + gyro[k + 1])
            seq.integrate(a_mid, w_mid, t[k + 1] - t[k], rotate_midpoint)
    batch = BatchPreintegration(t, gyro, accel, x.gyro_bias_rad_s, x.accel_bias_m_s2, noise, rotate_midpoint)
    attrs = (
        "delta_R",
        "delta_v",
        "delta_p",
        "cov",
        "d_R_d_bg",
        "d_v_d_bg",
        "d_v_d_ba",
        "d_p_d_bg",
        "d_p_d_ba",
    )
    for attr in attrs:
        ref = np.asarray(getattr(seq, attr))
        np.testing.assert_allclose(getattr(batch, attr), ref, rtol=1e-10, atol=1e-12 * np.max(np.abs(ref)))
    assert batch.dt_s == seq.dt_s
    # It continues like any preintegration.
    for pre in (seq, batch):
        pre.integrate(accel[0], gyro[0], 0.005)
    np.testing.assert_allclose(batch.cov, seq.cov, rtol=1e-10, atol=1e-12 * np.max(np.abs(seq.cov)))


def test_midpoint_preintegration_matches_the_closed_form_of_a_steady_turn():
    """Constant yaw rate w and constant body specific force a: dv = int Rz(w t) a dt in closed form.

    dv = (a_x sin(wT) / w, a_x (1 - cos(wT)) / w, a_z T) and dp = int dv. Rotating each midpoint reading by
    its step's start attitude alone would leave |w| a_x dt T / 2 = 7.5 mm/s here; the half-step rotation
    is second order in dt.
    """
    w, a_x, a_z, T = 2.0, 3.0, 9.81, 1.0
    t = np.linspace(0.0, T, 201)  # 200 Hz
    gyro = np.tile([0.0, 0.0, w], (len(t), 1))
    accel = np.tile([a_x, 0.0, a_z], (len(t), 1))
    pre = BatchPreintegration(t, gyro, accel, np.zeros(3), np.zeros(3), ImuNoise(), rotate_midpoint=True)
    dv = np.array([a_x * np.sin(w * T) / w, a_x * (1.0 - np.cos(w * T)) / w, a_z * T])
    dp = np.array([a_x * (1.0 - np.cos(w * T)) / w**2, a_x * (T - np.sin(w * T) / w) / w, 0.5 * a_z * T**2])
    np.testing.assert_allclose(pre.delta_v, dv, atol=2e-5)
    np.testing.assert_allclose(pre.delta_p, dp, atol=2e-5)
    # The default (start attitude) carries the first-order error |w| a_x dt T / 2, in the turn's plane.
    plain = BatchPreintegration(t, gyro, accel, np.zeros(3), np.zeros(3), ImuNoise())
    err = np.linalg.norm(plain.delta_v - dv)
    assert 0.5 * (0.5 * w * a_x * 0.005 * T) < err < 1.5 * (0.5 * w * a_x * 0.005 * T)
