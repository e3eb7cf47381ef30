"""Tests of vio/zero_velocity.py: stillness detection shared by the MSCKF's ZUPT and the window's factor."""

import numpy as np
import scipy.linalg
from viotb.vio.frontend import Tracks
from viotb.vio.lie import exp_so3
from viotb.vio.state import BA, BG, THETA, VEL, ImuValues
from viotb.vio.types import GRAVITY_M_S2, ImuNoise
from viotb.vio.zero_velocity import ZeroVelocityDetector, ZeroVelocityParams, stillness_test


def _still_imu(R_WB, n=40, rng=None):
    f_B = R_WB.T @ np.array([0.0, 0.0, GRAVITY_M_S2])
    gyro = np.zeros((n, 3))
    accel = np.tile(f_B, (n, 1))
    if rng is not None:
        gyro += rng.normal(0.0, 1e-3, gyro.shape)
        accel += rng.normal(0.0, 1e-2, accel.shape)
    return gyro, accel


def _values(R_WB, v_WB=(0.0, 0.0, 0.0)):
    return ImuValues(R_WB, np.zeros(3), np.asarray(v_WB, dtype=float), np.zeros(3), np.zeros(3))


def _tracks(t_s, uv_px):
    uv = np.asarray(uv_px, dtype=float)
    return Tracks(t_s, t_s, np.arange(len(uv), dtype=np.int64), uv / 400.0, uv)


def test_still_imu_passes_and_a_velocity_fails():
    R = exp_so3(np.array([0.1, -0.2, 0.3]))
    gyro, accel = _still_imu(R, rng=np.random.default_rng(0))
    cov = np.eye(15) * 1e-4
    p = ZeroVelocityParams()
    still = stillness_test(gyro, accel, _values(R), cov, ImuNoise(), 0.2, p)
    assert still.chi2 < 16.92
    moving = stillness_test(gyro, accel, _values(R, (0.1, 0.0, 0.0)), cov, ImuNoise(), 0.2, p)
    assert moving.chi2 > 30.0  # 0.1^2 / (1e-4 + 1e-4) = 50
    # Rows touch [dbg; dtheta, dba; dv] only.
    cols = np.nonzero(np.any(still.H != 0.0, axis=0))[0]
    assert set(cols) <= set(range(BG, BG + 3)) | set(range(THETA, THETA + 3)) | set(range(BA, BA + 3)) | set(
        range(VEL, VEL + 3)
    )


def test_extra_state_dimensions_leave_the_test_unchanged():
    R = exp_so3(np.array([0.0, 0.1, 0.0]))
    gyro, accel = _still_imu(R, rng=np.random.default_rng(1))
    cov = np.eye(15) * 1e-4
    big = scipy.linalg.block_diag(cov, np.eye(12))
    a = stillness_test(gyro, accel, _values(R), cov, ImuNoise(), 0.1, ZeroVelocityParams())
    b = stillness_test(gyro, accel, _values(R), big, ImuNoise(), 0.1, ZeroVelocityParams())
    assert b.H.shape == (9, 27)
    assert abs(a.chi2 - b.chi2) <= 1e-9 * a.chi2


def test_detector_marks_motion_from_features_speed_or_repeated_imu_failures():
    R = np.eye(3)
    gyro, accel = _still_imu(R)
    uv = np.random.default_rng(2).uniform(0, 300, (20, 2))
    prev, same, moved = _tracks(0.0, uv), _tracks(0.1, uv), _tracks(0.1, uv + 2.0)
    cov = np.eye(15) * 1e-4

    def readings():
        return gyro, accel

    det = ZeroVelocityDetector(ZeroVelocityParams(), ImuNoise(), chi2_gate=16.92)
    assert det.detect(prev, same, 0.1, _values(R), cov, readings) is not None
    assert not det.has_moved
    assert det.detect(prev, moved, 0.1, _values(R), cov, readings) is None
    assert det.has_moved and not det.allowed()

    det = ZeroVelocityDetector(ZeroVelocityParams(), ImuNoise(), chi2_gate=16.92)
    assert det.detect(prev, same, 0.1, _values(R, (0.3, 0.0, 0.0)), cov, readings) is None  # speed gate
    assert det.has_moved

    window = ZeroVelocityParams(max_speed_m_s=float("inf"), chi2_gate=16.92, imu_failures_to_move=2)
    det = ZeroVelocityDetector(window, ImuNoise(), chi2_gate=0.0)  # params.chi2_gate wins over the fallback
    slow = _values(R, (0.15, 0.0, 0.0))  # no speed gate, but the IMU test fails (chi2 ~ 112)
    assert det.detect(prev, same, 0.1, slow, cov, readings) is None and not det.has_moved
    assert det.detect(prev, same, 0.1, slow, cov, readings) is None and det.has_moved


def test_estimators_keep_their_zero_velocity_defaults():
    from viotb.vio.msckf import MsckfParams
    from viotb.vio.window import WindowParams

    assert MsckfParams().zero_velocity == ZeroVelocityParams()
    w = WindowParams().zero_velocity
    assert (w.max_speed_m_s, w.chi2_gate, w.imu_failures_to_move) == (float("inf"), 16.92, 2)
    assert (w.max_disparity_px, w.min_features, w.velocity_sigma_m_s) == (0.5, 10, 0.01)
