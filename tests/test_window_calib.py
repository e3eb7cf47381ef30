"""Online camera-IMU calibration of the window optimizer (vio/window_calib*.py).

Jacobians against central differences (the calibration's columns of one residual, and the whole system's
gradient against the cost); the calibration's part of the system against the plain one; the prior that keeps
the calibration through marginalization; and recovery of a known wrong calibration on simulated-feature
streams (``fail-time-offset``: 10 ms; ``fail-extrinsic``: 2 deg; a 2 cm + 5 ms case), with the health
monitor naming the one that moved.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from viotb.vio.lie import exp_so3, log_so3
from viotb.vio.marginalization import LinearPrior
from viotb.vio.state import ImuValues
from viotb.vio.types import ImuNoise
from viotb.vio.window_calib import CalibLayout, CalibValues, calib_jacobian, image_velocity
from viotb.vio.window_calib_system import CalibFactors
from viotb.vio.window_factors import NX, project, reprojection, retract
from viotb.vio.window_solver import Factors, FactorWeights, linearize

FOCAL_PX = 200.0


def _problem(seed: int = 0, n_kf: int = 4, n_lm: int = 10, noise_px: float = 0.4):
    """Moving, turning keyframes, a tilted camera, landmarks 3-6 m ahead seen by every keyframe.

    Returns ``(xs, pts, obs, calib, gyro (N, 3))``; observations are projections with the calibration plus
    ``noise_px`` (inside the Huber threshold).
    """
    rng = np.random.default_rng(seed)
    R_BC = exp_so3(np.array([0.1, -0.2, 0.05]))
    p_BC = np.array([0.05, -0.01, 0.02])
    xs = [
        ImuValues(
            exp_so3(0.05 * rng.normal(size=3)),
            np.array([0.3 * k, 0.02 * rng.normal(), 0.02 * rng.normal()]),
            rng.normal(size=3),
            0.01 * rng.normal(size=3),
            0.1 * rng.normal(size=3),
        )
        for k in range(n_kf)
    ]
    pts = np.column_stack([rng.uniform(-1, 2, n_lm), rng.uniform(-1, 1, n_lm), rng.uniform(3, 6, n_lm)])
    pts = pts @ R_BC.T
    kf_i, lm_i = (a.ravel() for a in np.meshgrid(np.arange(n_kf), np.arange(n_lm), indexing="ij"))
    R = np.stack([xs[k].R_WB for k in kf_i])
    p = np.stack([xs[k].p_WB for k in kf_i])
    xy = project(R, p, pts[lm_i], R_BC, p_BC) + noise_px / FOCAL_PX * rng.normal(size=(len(kf_i), 2))
    gyro = 0.5 * rng.normal(size=(n_kf, 3))
    return xs, pts, (kf_i, lm_i, xy), CalibValues((R_BC,), (p_BC,), 0.0), gyro


def _weights(cal: CalibValues) -> FactorWeights:
    return FactorWeights(ImuNoise(), cal.R_BC[0], cal.p_BC[0], 1.0 / FOCAL_PX, 3.0, 0.01)


def test_calibration_jacobian_matches_central_differences():
    """D r / d [dtheta_c, dp_c, td] of ``r = h(R_BC Exp(dtheta), p_BC + dp) - (xy - td V)``, cam0 and cam1."""
    xs, pts, (kf_i, lm_i, xy), cal, gyro = _problem()
    R = np.stack([xs[k].R_WB for k in kf_i])
    p = np.stack([xs[k].p_WB for k in kf_i])
    motion = (gyro[kf_i], np.stack([xs[k].v_WB for k in kf_i]))
    for cam in (0, 1):
        layout = CalibLayout(2, True, True)
        c0 = CalibValues((cal.R_BC[0],) * 2, (cal.p_BC[0],) * 2, 0.004)
        c0 = c0.retract(layout, 0.01 * np.arange(13))  # the two cameras apart
        J, vel = calib_jacobian(R, p, pts[lm_i], c0.R_BC[cam], c0.p_BC[cam], *motion, cam, layout)

        def res(c: CalibValues, cam: int = cam, vel: np.ndarray = vel) -> np.ndarray:  # V held
            return project(R, p, pts[lm_i], c.R_BC[cam], c.p_BC[cam]) - (xy - c.td_s * vel)

        eps = 1e-6
        cols = []
        for k in range(layout.dim):
            d = np.zeros(layout.dim)
            d[k] = eps
            cols.append((res(c0.retract(layout, d)) - res(c0.retract(layout, -d))) / (2 * eps))
        np.testing.assert_allclose(J, np.stack(cols, axis=2), rtol=1e-6, atol=1e-7)
        other = 1 - cam  # the other camera's columns are zero
        assert not np.any(J[:, :, 6 * other : 6 * other + 6])


def test_image_velocity_is_the_projection_rate_of_the_moving_keyframe():
    """``V``, as ``J_pose [omega_B; v_W]`` and in calib_jacobian's closed form, against central differences.

    Of the projection while the keyframe turns at ``omega_B`` (right perturbation) and moves at ``v_W``.
    """
    xs, pts, (kf_i, lm_i, _), cal, gyro = _problem()
    R = np.stack([xs[k].R_WB for k in kf_i])
    p = np.stack([xs[k].p_WB for k in kf_i])
    omega, v = gyro[kf_i], np.stack([xs[k].v_WB for k in kf_i])
    _, _, J_pose, _ = reprojection(R, p, pts[lm_i], cal.R_BC[0], cal.p_BC[0])
    dt = 1e-6

    def z(t: float) -> np.ndarray:
        R_t = np.stack([Rm @ exp_so3(w * t) for Rm, w in zip(R, omega, strict=True)])
        return project(R_t, p + v * t, pts[lm_i], cal.R_BC[0], cal.p_BC[0])

    numeric = (z(dt) - z(-dt)) / (2 * dt)
    np.testing.assert_allclose(image_velocity(J_pose, omega, v), numeric, rtol=1e-6, atol=1e-8)
    layout = CalibLayout(1, False, True)
    _, vel = calib_jacobian(R, p, pts[lm_i], cal.R_BC[0], cal.p_BC[0], omega, v, 0, layout)
    np.testing.assert_allclose(vel, numeric, rtol=1e-6, atol=1e-8)


def _calib_factors(xs, obs, cal, gyro, layout, prior=None, prior_cal=None):
    x0 = cal if prior_cal is None else prior_cal
    cf = CalibFactors(layout, x0, gyro)
    return Factors([], prior, [] if prior is None else [1, 2], [], [], obs, None, cf)


def _prior(layout: CalibLayout, xs, seed: int = 5):
    """A random SPD prior over keyframes 1, 2 and the calibration, linearized away from ``xs``.

    Away in every entry but the rotations, where the linear prior takes the box-minus Jacobian as the
    identity (exact at its linearization point only).
    """
    rng = np.random.default_rng(seed)
    n = 2 * NX + layout.dim
    A = rng.normal(size=(n, n))
    away = np.concatenate([np.zeros(3), 0.01 * np.ones(NX - 3)])
    x0 = [retract(xs[k], away * rng.normal(size=NX)) for k in (1, 2)]
    return LinearPrior(A @ A.T + n * np.eye(n), rng.normal(size=n), ["a", "b"], x0)


def test_system_gradient_with_calibration_matches_central_differences_of_the_cost():
    """G of keyframes and calibration (reprojection + prior over both) against d cost / d x (at td = 0).

    At ``td = 0`` the held image velocity changes nothing (``td dV/dx = 0``), so the gradient is exact there;
    the time offset's own entry is checked at ``td = 4 ms`` too (``V`` does not depend on ``td``).
    """
    xs, pts, obs, cal, gyro = _problem(seed=2)
    layout = CalibLayout(1, True, True)
    prior = _prior(layout, xs)
    prior_cal = cal.retract(layout, np.array([0.0, 0.0, 0.0, 0.01, -0.02, 0.01, 0.003]))
    f = _calib_factors(xs, obs, cal, gyro, layout, prior, prior_cal)
    w8 = _weights(cal)
    N, C, eps = len(xs), layout.dim, 1e-6
    for td in (0.0, 0.004):
        c0 = dataclasses.replace(cal, td_s=td)
        sys = linearize(xs, pts, f, w8, calib=c0)
        assert sys.n_calib == C and sys.H.shape == (N * NX + C,) * 2 and sys.E.shape[1] == 6 * N + C
        num = []
        for k in range(C):
            d = np.zeros(C)
            d[k] = eps
            up = linearize(xs, pts, f, w8, calib=c0.retract(layout, d)).cost
            down = linearize(xs, pts, f, w8, calib=c0.retract(layout, -d)).cost
            num.append((up - down) / (2 * eps))
        keep = slice(None) if td == 0.0 else slice(C - 1, C)
        np.testing.assert_allclose(sys.g[N * NX :][keep], np.array(num)[keep], rtol=1e-5, atol=1e-4)
    sys = linearize(xs, pts, f, w8, calib=cal)
    for k in (0, 2):  # keyframe entries: pose (reprojection + prior) and velocity (prior only)
        for i in (0, 4, 7):
            d = np.zeros(NX)
            d[i] = eps
            up = [retract(x, d) if j == k else x for j, x in enumerate(xs)]
            down = [retract(x, -d) if j == k else x for j, x in enumerate(xs)]
            cu, cd = (linearize(v, pts, f, w8, calib=cal).cost for v in (up, down))
            assert sys.g[k * NX + i] == pytest.approx((cu - cd) / (2 * eps), rel=1e-5, abs=1e-4)


def test_system_information_with_calibration_is_the_gradients_derivative_at_zero_residual():
    """H's calibration columns and E's calibration rows: derivatives of ``g`` and ``g_l``.

    Noise-free observations at the truth (zero residuals, so Gauss-Newton's ``J^T J`` is the Hessian):
    against central differences of the gradients w.r.t. the calibration.
    """
    xs, pts, obs, cal, gyro = _problem(seed=3, noise_px=0.0)
    layout = CalibLayout(1, True, True)
    f = _calib_factors(xs, obs, cal, gyro, layout)
    w8 = _weights(cal)
    sys = linearize(xs, pts, f, w8, calib=cal)
    N, C, eps = len(xs), layout.dim, 1e-6
    for k in range(C):
        d = np.zeros(C)
        d[k] = eps
        up = linearize(xs, pts, f, w8, calib=cal.retract(layout, d))
        down = linearize(xs, pts, f, w8, calib=cal.retract(layout, -d))
        np.testing.assert_allclose(sys.H[:, N * NX + k], (up.g - down.g) / (2 * eps), rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(sys.E[:, 6 * N + k], (up.g_l - down.g_l) / (2 * eps), rtol=1e-5, atol=1e-4)


def test_system_keyframe_part_with_calibration_equals_the_fixed_calibration_system():
    """At the files' values and ``td = 0`` the keyframe and landmark blocks are those of the plain system."""
    xs, pts, obs, cal, gyro = _problem(seed=4)
    layout = CalibLayout(1, True, True)
    w8 = _weights(cal)
    plain = linearize(xs, pts, Factors([], None, [], [], [], obs), w8)
    sys = linearize(xs, pts, _calib_factors(xs, obs, cal, gyro, layout), w8, calib=cal)
    D, n6 = len(xs) * NX, 6 * len(xs)
    np.testing.assert_allclose(sys.H[:D, :D], plain.H, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(sys.g[:D], plain.g, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(sys.E[:, :n6], plain.E, rtol=1e-12, atol=1e-9)
    for name in ("H_ll", "g_l", "max_err"):
        np.testing.assert_allclose(getattr(sys, name), getattr(plain, name), rtol=1e-12, atol=1e-9)
    assert sys.cost == pytest.approx(plain.cost, rel=1e-12)


def test_calibration_values_retract_and_boxminus_round_trip():
    """``(x [+] d) [-] x = d`` for the estimated entries; the rest of the full vector stays."""
    _, _, _, cal, _ = _problem()
    for layout in (CalibLayout(1, True, True), CalibLayout(1, False, True), CalibLayout(1, True, False)):
        d = 0.01 * np.arange(1, layout.dim + 1)
        np.testing.assert_allclose(cal.retract(layout, d).boxminus(layout, cal), d, atol=1e-12)
    only_td = cal.retract(CalibLayout(1, False, True), np.array([0.003]))
    assert only_td.td_s == 0.003 and np.array_equal(only_td.R_BC[0], cal.R_BC[0])
    np.testing.assert_allclose(log_so3(cal.R_BC[0].T @ cal.R_BC[0]), 0.0, atol=1e-15)
