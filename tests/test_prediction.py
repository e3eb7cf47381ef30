"""Display pose prediction: exact on the motions each model assumes, closed-form errors otherwise."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.vio.lie import exp_so3, left_jacobian_so3, log_so3
from viotb.vio.prediction import (
    DisplayPosePredictor,
    MotionState,
    PredictionParams,
    angular_acceleration_from_gyro,
    gravity_removed_acceleration_W,
    predict_pose,
)

CONST_TWIST = PredictionParams(motion_model="constant-twist")
WITH_ALPHA = PredictionParams(use_angular_acceleration=True)


def _rot_err_rad(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return float(np.linalg.norm(log_so3(R_a.T @ R_b)))


def _helix(t: float, R0, p0, omega_B, v_B):
    """Constant body twist (v_B, omega_B): T(t) = T0 Exp(t (v_B, omega_B)). Returns R, p, v_W, a_W."""
    R = R0 @ exp_so3(omega_B * t)
    p = p0 + R0 @ left_jacobian_so3(omega_B * t) @ (v_B * t)
    return R, p, R @ v_B, R @ np.cross(omega_B, v_B)


@pytest.fixture
def motion():
    rng = np.random.default_rng(3)
    R0 = Rotation.random(random_state=4).as_matrix()
    return R0, rng.normal(size=3), rng.normal(size=3) * 4.0, rng.normal(size=3), rng.normal(size=3) * 3.0


def test_constant_acceleration_model_is_exact_on_its_motion(motion):
    R0, p0, omega_B, v0, a_W = motion
    for dt in (0.02, 0.1, 0.7):
        pred = predict_pose(MotionState(1.0, R0, p0, v0, omega_B, a_W), dt_s=dt)
        np.testing.assert_allclose(pred.R_WB, R0 @ exp_so3(omega_B * dt), atol=1e-13)
        np.testing.assert_allclose(pred.p_WB, p0 + v0 * dt + 0.5 * a_W * dt**2, atol=1e-13)
        assert pred.t_s == 1.0 + dt


def test_constant_twist_model_is_exact_on_a_helix(motion):
    R0, p0, omega_B, v_B, _ = motion
    t0 = 0.37
    R, p, v_W, a_W = _helix(t0, R0, p0, omega_B, v_B)
    for dt in (0.02, 0.2, 1.5):
        pred = predict_pose(MotionState(t0, R, p, v_W, omega_B, a_W), CONST_TWIST, dt_s=dt)
        R_true, p_true, _, _ = _helix(t0 + dt, R0, p0, omega_B, v_B)
        assert _rot_err_rad(pred.R_WB, R_true) < 1e-12
        np.testing.assert_allclose(pred.p_WB, p_true, atol=1e-12)


def test_constant_acceleration_model_on_a_helix_errs_by_the_jerk_term(motion):
    # Taylor: p(t+dt) - (p + v dt + a dt^2/2) = j dt^3 / 6 + O(dt^4), with j_W = R [w]x [w]x v_B.
    R0, p0, omega_B, v_B, _ = motion
    R, p, v_W, a_W = _helix(0.0, R0, p0, omega_B, v_B)
    jerk = np.linalg.norm(np.cross(omega_B, np.cross(omega_B, v_B)))
    for dt in (0.02, 0.005):
        pred = predict_pose(MotionState(0.0, R, p, v_W, omega_B, a_W), dt_s=dt)
        err = np.linalg.norm(pred.p_WB - _helix(dt, R0, p0, omega_B, v_B)[1])
        assert err == pytest.approx(jerk * dt**3 / 6.0, rel=4.0 * np.linalg.norm(omega_B) * dt)


def test_constant_rate_rotation_errs_by_half_alpha_dt_squared_parallel_case():
    # alpha parallel to omega: rotations commute, R(t) = R0 Exp(w t + alpha t^2 / 2) exactly, so the
    # constant-rate prediction errs by exactly |alpha| dt^2 / 2 and the alpha-aware one not at all.
    axis = np.array([0.2, -0.5, 0.84]) / np.linalg.norm([0.2, -0.5, 0.84])
    omega_B, alpha_B = axis * np.deg2rad(300.0), axis * np.deg2rad(2000.0)
    R0 = Rotation.random(random_state=5).as_matrix()
    dt = 0.02
    R_true = R0 @ exp_so3(omega_B * dt + 0.5 * alpha_B * dt**2)
    state = MotionState(0.0, R0, np.zeros(3), np.zeros(3), omega_B, np.zeros(3), alpha_B)
    err = _rot_err_rad(predict_pose(state).R_WB, R_true)
    assert err == pytest.approx(np.linalg.norm(alpha_B) * dt**2 / 2.0, rel=1e-9)
    assert np.rad2deg(err) == pytest.approx(0.4, rel=1e-9)  # 2000 deg/s^2 over 20 ms
    assert _rot_err_rad(predict_pose(state, WITH_ALPHA).R_WB, R_true) < 1e-14


def _integrate_rotation(R0, omega0, alpha, duration, steps=4000):
    """dR/dt = R [omega0 + alpha t]x by exact exponentials of the midpoint rate (error O(h^2))."""
    R, h = R0.copy(), duration / steps
    for k in range(steps):
        R = R @ exp_so3((omega0 + alpha * (k + 0.5) * h) * h)
    return R


def test_constant_rate_rotation_error_general_alpha():
    rng = np.random.default_rng(6)
    R0 = Rotation.random(random_state=7).as_matrix()
    omega_B = rng.normal(size=3) * 3.0
    alpha_B = rng.normal(size=3) * 30.0
    dt = 0.02
    R_true = _integrate_rotation(R0, omega_B, alpha_B, dt)
    state = MotionState(0.0, R0, np.zeros(3), np.zeros(3), omega_B, np.zeros(3), alpha_B)
    err = _rot_err_rad(predict_pose(state).R_WB, R_true)
    # Leading order |alpha| dt^2 / 2; the next term is O(|omega| |alpha| dt^3).
    assert err == pytest.approx(np.linalg.norm(alpha_B) * dt**2 / 2.0, rel=np.linalg.norm(omega_B) * dt)
    err_magnus = _rot_err_rad(predict_pose(state, WITH_ALPHA).R_WB, R_true)
    assert err_magnus < 1e-4 * err
    # The third-order Magnus term matters: without it the error is ~|omega x alpha| dt^3 / 12.
    no_magnus = R0 @ exp_so3(omega_B * dt + 0.5 * alpha_B * dt**2)
    assert _rot_err_rad(no_magnus, R_true) == pytest.approx(
        np.linalg.norm(np.cross(omega_B, alpha_B)) * dt**3 / 12.0, rel=0.05
    )


def test_angular_acceleration_from_gyro_and_predictor_history():
    alpha = np.array([1.0, -20.0, 7.0])
    t = np.arange(0.0, 0.03, 0.001)
    omega = np.array([0.5, 2.0, -1.0]) + t[:, None] * alpha
    np.testing.assert_allclose(angular_acceleration_from_gyro(t, omega), alpha, atol=1e-9)
    predictor = DisplayPosePredictor(PredictionParams(use_angular_acceleration=True, alpha_window_s=0.01))
    for tk, wk in zip(t, omega, strict=True):
        predictor.add_gyro(tk, wk)
    np.testing.assert_allclose(predictor.angular_acceleration_B(), alpha, atol=1e-9)
    state = MotionState(t[-1], np.eye(3), np.zeros(3), np.zeros(3), omega[-1])
    expected = predict_pose(
        MotionState(t[-1], np.eye(3), np.zeros(3), np.zeros(3), omega[-1], alpha_B=alpha), WITH_ALPHA
    )
    pred = predictor.predict(state)
    np.testing.assert_allclose(pred.R_WB, expected.R_WB, atol=1e-12)
    assert pred.t_s == pytest.approx(t[-1] + 0.020)
    with pytest.raises(ValueError, match="span no time"):
        angular_acceleration_from_gyro(np.zeros(3), omega[:3])


def test_gravity_removed_acceleration_and_param_validation():
    R = exp_so3(np.array([0.3, -0.2, 1.0]))
    np.testing.assert_allclose(gravity_removed_acceleration_W(R, R.T @ [0.0, 0.0, 9.81]), 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="motion_model must be one of"):
        PredictionParams(motion_model="kalman")
    with pytest.raises(ValueError, match="needs motion_model='constant-acceleration'"):
        PredictionParams(motion_model="constant-twist", use_angular_acceleration=True)
    with pytest.raises(ValueError, match="latency_s"):
        PredictionParams(latency_s=-0.01)
