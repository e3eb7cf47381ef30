"""The display pose filter against closed forms.

No lag on IMU-measured motion, the second-order step response, the frequency response of the
estimator-to-display path, the first-order orientation pull, snaps.
"""

from __future__ import annotations

import numpy as np
import pytest
from viotb.vio.display_pose import DisplayPoseFilter, DisplayPoseParams
from viotb.vio.lie import exp_so3, log_so3

DT = 1e-3


def _still(filt: DisplayPoseFilter, n: int, p_f: np.ndarray, R_f: np.ndarray | None = None, t0: float = 0.0):
    """Feed ``n`` still samples with the estimator at ``(R_f, p_f)``; returns display positions (n, 3)."""
    R_f = np.eye(3) if R_f is None else R_f
    out = []
    for k in range(n):
        _, p_d, _ = filt.update(t0 + (k + 1) * DT, R_f, p_f, np.zeros(3), np.zeros(3), np.zeros(3))
        out.append(p_d)
    return np.array(out)


def test_motion_the_imu_measures_passes_without_lag():
    """Estimator = truth, IMU = truth: the display equals the estimate (the filter adds nothing)."""
    filt = DisplayPoseFilter(DisplayPoseParams(f_still_hz=0.1, f_moving_hz=0.1))
    omega_B = np.array([0.3, -1.2, 2.0])
    a_W = np.array([0.5, -0.2, 0.3])
    worst_p = worst_R = 0.0
    for k in range(2000):
        t = k * DT
        R = exp_so3(omega_B * t)
        p = 0.5 * a_W * t * t + np.array([1.0, 2.0, 1.5])
        R_d, p_d, _ = filt.update(t, R, p, a_W * t, omega_B, a_W)
        worst_p = max(worst_p, float(np.linalg.norm(p_d - p)))
        worst_R = max(worst_R, float(np.linalg.norm(log_so3(R_d.T @ R))))
    assert worst_p < 1e-9 and worst_R < 1e-9


@pytest.mark.parametrize("damping", [0.7, 1.0])
def test_position_step_follows_the_second_order_closed_form(damping):
    """Display minus estimate obeys x'' + 2 zeta w x' + w^2 x = 0, x(0) = -d, x'(0) = 2 zeta w d."""
    f_c, d = 0.5, 0.004
    filt = DisplayPoseFilter(DisplayPoseParams(f_still_hz=f_c, f_moving_hz=f_c, damping=damping))
    _still(filt, 1, np.zeros(3))
    p_disp = _still(filt, 4000, np.array([d, 0.0, 0.0]), t0=DT)[:, 0]
    w, z = 2 * np.pi * f_c, damping
    t = np.arange(1, 4001) * DT
    x0, xd0 = -d, 2 * z * w * d
    if z < 1.0:
        wd = w * np.sqrt(1 - z * z)
        x = np.exp(-z * w * t) * (x0 * np.cos(wd * t) + (xd0 + z * w * x0) / wd * np.sin(wd * t))
    else:
        x = np.exp(-w * t) * (x0 + (xd0 + w * x0) * t)
    np.testing.assert_allclose(p_disp - d, x, atol=0.01 * d)
    assert abs(p_disp[-1] - d) < 0.02 * d


def test_estimator_wobble_is_attenuated_as_the_transfer_function_says():
    """A sinusoidal estimator error reaches the display with gain |H(jw)| of the module's low-pass."""
    p = DisplayPoseParams(f_still_hz=0.1, f_moving_hz=0.1, damping=0.7)
    filt = DisplayPoseFilter(p)
    f_err, amp = 3.0, 1e-3
    t = np.arange(1, 30001) * DT
    disp = []
    for tk in t:
        _, p_d, _ = filt.update(
            tk, np.eye(3), np.array([amp * np.sin(2 * np.pi * f_err * tk), 0, 0]), *[np.zeros(3)] * 3
        )
        disp.append(p_d[0])
    tail = np.array(disp)[-int(10 / f_err / DT) :]  # the last 10 periods, transients gone
    s = 2j * np.pi * f_err
    wc = 2 * np.pi * p.f_still_hz
    gain = abs((2 * p.damping * wc * s + wc**2) / (s**2 + 2 * p.damping * wc * s + wc**2))
    measured = np.sqrt(2.0) * np.std(tail)
    assert measured == pytest.approx(gain * amp, rel=0.03)
    assert gain < 0.05  # 3 Hz wobble of the estimate: 20x smaller on the display


def test_orientation_pull_is_first_order():
    """A small estimator attitude offset decays as (1 - wc dt)^k."""
    f_c, angle = 0.2, 0.005
    filt = DisplayPoseFilter(DisplayPoseParams(f_still_hz=f_c, f_moving_hz=f_c))
    filt.update(0.0, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    R_f = exp_so3(np.array([0.0, 0.0, angle]))
    errs = []
    for k in range(1, 2001):
        R_d, _, _ = filt.update(k * DT, R_f, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
        errs.append(float(np.linalg.norm(log_so3(R_d.T @ R_f))))
    expected = angle * (1.0 - 2 * np.pi * f_c * DT) ** np.arange(1, 2001)
    np.testing.assert_allclose(errs, expected, rtol=1e-6, atol=1e-12)


def test_crossover_rises_with_head_motion():
    filt = DisplayPoseFilter(DisplayPoseParams(f_still_hz=0.1, f_moving_hz=3.0, omega_full_rad_s=1.0))
    assert filt.crossover_hz(np.zeros(3), np.zeros(3)) == pytest.approx(0.1)
    assert filt.crossover_hz(np.array([0.0, 0.5, 0.0]), np.zeros(3)) == pytest.approx(1.55)
    assert filt.crossover_hz(np.array([0.0, 0.0, 4.0]), np.zeros(3)) == pytest.approx(3.0)


def test_large_jumps_snap():
    """A relocalization-sized jump is taken at once, not smoothed over seconds."""
    filt = DisplayPoseFilter(DisplayPoseParams(snap_m=0.03))
    _still(filt, 10, np.zeros(3))
    p_d = _still(filt, 1, np.array([0.10, 0.0, 0.0]), t0=10 * DT)
    np.testing.assert_allclose(p_d[-1], [0.10, 0.0, 0.0])
    assert filt.snaps == 1


def test_bad_settings_and_time_order_are_refused():
    with pytest.raises(ValueError, match="f_still_hz"):
        DisplayPoseParams(f_still_hz=0.0)
    with pytest.raises(ValueError, match="f_moving_hz"):
        DisplayPoseParams(f_still_hz=1.0, f_moving_hz=0.5)
    filt = DisplayPoseFilter()
    _still(filt, 2, np.zeros(3))
    with pytest.raises(ValueError, match="not after"):
        filt.update(DT, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
