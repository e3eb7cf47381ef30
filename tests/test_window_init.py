"""Tests of vio/window_init.py: the static start's coupled tilt and accelerometer-bias prior.

The expectation is built independently: the static initializer's geometry simulated exactly (the gravity
direction from the mean specific force of a still IMU with a horizontal bias, rotations by exp/log), and the
errors it leaves compared with what the coupled covariance predicts.
"""

from __future__ import annotations

import numpy as np
import pytest
from viotb.vio.lie import exp_so3, log_so3
from viotb.vio.types import GRAVITY_M_S2
from viotb.vio.window_init import couple_static_tilt_bias


def _static_init(R_true: np.ndarray, b_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R_est, b_est)`` of a static initializer: the up direction from ``f``, the bias along it only."""
    f = R_true.T @ np.array([0.0, 0.0, GRAVITY_M_S2]) + b_true
    u = f / np.linalg.norm(f)
    v = R_true.T @ np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, v)
    angle = np.arctan2(np.linalg.norm(axis), float(u @ v))
    R_est = R_true @ exp_so3(axis / np.linalg.norm(axis) * angle)  # R_est^T z = u, the yaw of R_true
    return R_est, (np.linalg.norm(f) - GRAVITY_M_S2) * u


_DIAG = np.concatenate([np.full(3, 0.01**2), np.full(6, 1e-4), np.full(3, 1e-6), np.full(3, 0.1**2)])
"""Variances ``[dtheta, dp, dv, dbg, dba]`` as a static initializer reports them (tilt 0.01 rad, bias 0.1)."""


def _prior(R_est: np.ndarray) -> np.ndarray:
    return couple_static_tilt_bias(np.diag(_DIAG), R_est, 0.01)


def test_the_coupled_prior_predicts_the_bias_error_from_the_tilt_error():
    """Given the tilt error the static geometry leaves, the prior's conditional mean is the bias error.

    Five random attitudes and horizontal biases of 0.05-0.1 m/s^2: ``E[db | dtheta] = C_bt C_tt^-1 dtheta``
    matches the true ``db`` to second order (1 % of its size), and the uncoupled prior (no correlation) would
    predict zero.
    """
    rng = np.random.default_rng(0)
    for _ in range(5):
        R_true = exp_so3(rng.normal(size=3) * 0.5)
        b_true = rng.normal(size=3) * 0.06
        R_est, b_est = _static_init(R_true, b_true)
        dtheta, db = log_so3(R_est.T @ R_true), b_true - b_est
        cov = _prior(R_est)
        predicted = cov[12:15, 0:3] @ np.linalg.solve(cov[0:3, 0:3], dtheta)
        assert np.linalg.norm(predicted - db) < 0.01 * np.linalg.norm(db) + 1e-6
        assert np.linalg.norm(db) > 0.03


def test_the_coupled_prior_is_a_covariance_with_the_given_marginals():
    """Symmetric, positive definite, the orientation block unchanged, the bias along up unchanged."""
    R = exp_so3(np.array([0.2, -0.1, 0.7]))
    cov = _prior(R)
    np.testing.assert_array_equal(cov, cov.T)
    assert np.linalg.eigvalsh(cov).min() > 0.0
    np.testing.assert_allclose(cov[0:12, 0:12], np.diag(_DIAG[:12]))
    u = R.T @ np.array([0.0, 0.0, 1.0])
    assert float(u @ cov[12:15, 12:15] @ u) == pytest.approx(0.1**2, rel=1e-12)
    # Horizontal bias variance: the tilt's 0.01 rad times g, plus the independent 0.01 m/s^2.
    h = np.cross(u, np.array([1.0, 0.0, 0.0]))
    h /= np.linalg.norm(h)
    assert float(h @ cov[12:15, 12:15] @ h) == pytest.approx((0.01 * GRAVITY_M_S2) ** 2 + 0.01**2, rel=1e-9)
    with pytest.raises(ValueError, match="independent_sigma_m_s2"):
        couple_static_tilt_bias(cov, R, 0.0)
