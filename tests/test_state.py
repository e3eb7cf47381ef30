"""Tests of vio/state.py: named blocks, covariance bookkeeping against closed forms."""

from dataclasses import replace

import numpy as np
import pytest
from viotb.vio.lie import exp_so3
from viotb.vio.state import (
    EXTRINSIC_BLOCK,
    IMU_BLOCK,
    POS,
    THETA,
    TIME_OFFSET_BLOCK,
    ImuValues,
    State,
    augment_clone,
    ekf_propagate,
    ekf_update,
    is_psd,
    marginal_covariance,
    marginalize,
    marginalize_oldest_clone,
    read_init_record,
)


def _random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return A @ A.T / n + 0.1 * np.eye(n)


def _state(rng: np.random.Generator, calib: bool = True) -> State:
    imu = ImuValues(
        exp_so3(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=3), np.zeros(3), np.zeros(3)
    )
    return State(
        0.0,
        imu,
        _random_spd(rng, 15),
        np.eye(3),
        np.zeros(3),
        0.0,
        extrinsic_cov=_random_spd(rng, 6) * 1e-3 if calib else None,
        time_offset_var_s2=1e-4 if calib else None,
    )


def _assert_sym_psd(st: State) -> None:
    np.testing.assert_allclose(st.cov, st.cov.T, atol=1e-12)
    assert np.linalg.eigvalsh(st.cov).min() > -1e-10
    assert is_psd(st)


def test_blocks_are_contiguous_and_named():
    st = _state(np.random.default_rng(0))
    assert [b.name for b in st.blocks] == [IMU_BLOCK, EXTRINSIC_BLOCK, TIME_OFFSET_BLOCK]
    assert st.dim == 22
    with pytest.raises(ValueError, match="no state block 'nope'"):
        st.block("nope")


def test_augment_clone_copies_pose_covariance_and_time_offset_jacobian():
    rng = np.random.default_rng(0)
    st = _state(rng)
    omega = rng.normal(size=3)
    P0 = st.cov.copy()
    blk = augment_clone(st, 1.0, omega)
    J = np.zeros((6, 22))
    J[0:3, THETA : THETA + 3] = np.eye(3)
    J[3:6, POS : POS + 3] = np.eye(3)
    J[0:3, 21] = omega
    J[3:6, 21] = st.imu.v_WB
    np.testing.assert_allclose(marginal_covariance(st, [blk]), J @ P0 @ J.T, atol=1e-12)
    np.testing.assert_allclose(st.cov[blk.indices, :22], J @ P0, atol=1e-12)
    _assert_sym_psd(st)
    with pytest.raises(ValueError, match="not newer"):
        augment_clone(st, 0.5, omega)


def test_marginalize_removes_rows_and_keeps_the_rest():
    rng = np.random.default_rng(0)
    st = _state(rng, calib=False)
    for t in (1.0, 2.0, 3.0):
        augment_clone(st, t)
    keep = [st.block(IMU_BLOCK), st.clone_block(1.0), st.clone_block(3.0)]
    expected = marginal_covariance(st, keep)
    marginalize(st, st.clone_block(2.0))
    assert list(st.clones) == [1.0, 3.0]
    assert st.dim == 27 and st.clone_block(3.0).offset == 21
    np.testing.assert_allclose(st.cov, expected, atol=0.0)
    assert marginalize_oldest_clone(st) == 1.0
    assert st.dim == 21
    _assert_sym_psd(st)


def test_ekf_update_matches_textbook_kalman_and_boxplus():
    rng = np.random.default_rng(0)
    st = _state(rng, calib=False)
    augment_clone(st, 1.0)
    P = st.cov.copy()
    H = rng.normal(size=(5, st.dim))
    r = rng.normal(size=5) * 0.1
    R = np.diag(rng.uniform(0.1, 0.5, 5))
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    p_before = st.imu.p_WB.copy()
    R_before = st.imu.R_WB.copy()
    dx = ekf_update(st, H, r, R)
    np.testing.assert_allclose(dx, K @ r, atol=1e-12)
    np.testing.assert_allclose(st.cov, (np.eye(st.dim) - K @ H) @ P, atol=1e-10)
    np.testing.assert_allclose(st.imu.p_WB, p_before + dx[POS : POS + 3], atol=1e-14)
    np.testing.assert_allclose(st.imu.R_WB, R_before @ exp_so3(dx[0:3]), atol=1e-14)
    _assert_sym_psd(st)
    with pytest.raises(ValueError, match="do not match"):
        ekf_update(st, H[:, :5], r, R)
    # An innovation covariance that is not positive definite is refused before anything changes.
    P_before = st.cov.copy()
    with pytest.raises(ValueError, match="not positive definite"):
        ekf_update(st, H, r, -np.eye(5) * 1e6)
    np.testing.assert_array_equal(st.cov, P_before)
    # No rows: no correction, the covariance stays (exactly: it is symmetric already).
    dx0 = ekf_update(st, np.zeros((0, st.dim)), np.zeros(0), 1.0)
    np.testing.assert_array_equal(dx0, np.zeros(st.dim))
    np.testing.assert_array_equal(st.cov, P_before)


def test_ekf_propagate_closed_form_and_psd():
    rng = np.random.default_rng(0)
    st = _state(rng, calib=False)
    augment_clone(st, 1.0)
    P = st.cov.copy()
    phi = np.eye(15) + 0.1 * rng.normal(size=(15, 15))
    Q = _random_spd(rng, 15) * 1e-3
    F = np.eye(st.dim)
    F[:15, :15] = phi
    Qf = np.zeros((st.dim, st.dim))
    Qf[:15, :15] = Q
    ekf_propagate(st, phi, Q)
    np.testing.assert_allclose(st.cov, F @ P @ F.T + Qf, atol=1e-12)
    _assert_sym_psd(st)


def test_bad_covariance_shape_is_a_clear_error():
    imu = ImuValues(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="imu_cov must have shape"):
        State(0.0, imu, np.eye(14), np.eye(3), np.zeros(3))


def test_init_record_yaw_gauge_sets_world_yaw_variance_and_keeps_tilt():
    """``sigma_yaw_rad``: the world-z part of the body-frame orientation error gets the gauge's variance.

    Closed form: for ``R_WB = R_hat Exp(dtheta)`` the world-frame rotation error is ``R_hat dtheta``, so its
    z variance is ``z^T R Sigma R^T z`` and must equal ``sigma_yaw^2``; any direction orthogonal to
    ``u = R^T z`` keeps the tilt variance. Without the field the covariance is the plain diagonal.
    """
    from viotb.vio.initialization import InitResult

    R_WB = exp_so3(np.array([0.3, -0.2, 1.1]))
    cov_diag = np.concatenate([np.full(3, 0.01**2), np.full(3, 1e-6), np.full(3, 1e-4), np.full(6, 1e-6)])
    base = InitResult(0.0, R_WB, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), "static", cov_diag)
    _, _, cov_plain = read_init_record(base)
    np.testing.assert_array_equal(cov_plain, np.diag(cov_diag))
    gauged = InitResult(
        0.0, R_WB, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), "static", cov_diag, sigma_yaw_rad=1e-4
    )
    _, _, cov = read_init_record(gauged)
    z = np.array([0.0, 0.0, 1.0])
    P_theta_W = R_WB @ cov[0:3, 0:3] @ R_WB.T
    assert z @ P_theta_W @ z == pytest.approx(1e-8, rel=1e-9)
    for x in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        assert x @ P_theta_W @ x == pytest.approx(1e-4, rel=1e-9)
        assert x @ P_theta_W @ z == pytest.approx(0.0, abs=1e-15)
    np.testing.assert_array_equal(cov[3:, 3:], np.diag(cov_diag[3:]))
    with pytest.raises(ValueError, match="sigma_yaw_rad"):
        read_init_record(replace(gauged, sigma_yaw_rad=-1.0))
