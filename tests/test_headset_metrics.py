"""Headset metrics on constructed error signals with known answers."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.vio.headset_metrics import (
    HeadsetMetricParams,
    drift_pct,
    headset_metrics,
    interpolate_poses,
    jitter_rms,
    pose_rate_hz,
    prediction_errors,
)
from viotb.vio.lie import exp_so3

RATE_HZ = 500.0
T_S = np.arange(0.0, 20.0, 1.0 / RATE_HZ)


def _truth(t):
    """A head walking a 2 m-radius circle while yawing: (R (N, 3, 3), p (N, 3))."""
    yaw = 0.3 * t
    p = np.column_stack([2.0 * np.cos(yaw), 2.0 * np.sin(yaw), 1.6 + 0.02 * np.sin(2 * np.pi * 1.8 * t)])
    return Rotation.from_euler("z", yaw[:, None]).as_matrix(), p


def _axis(vec):
    return np.asarray(vec, dtype=float) / np.linalg.norm(vec)


@pytest.mark.parametrize("freq_hz", [5.0, 12.0, 40.0])
def test_sinusoid_above_cutoff_gives_amplitude_over_sqrt2(freq_hz):
    amp_m = 2e-3
    err = np.outer(amp_m * np.sin(2 * np.pi * freq_hz * T_S + 0.3), _axis([1.0, -2.0, 0.5]))
    assert 1e3 * jitter_rms(T_S, err) == pytest.approx(2.0 / np.sqrt(2.0), rel=0.01)


def test_slow_drift_and_offset_below_cutoff_give_no_jitter():
    # 5 mm offset + a 1 mm/s ramp + a 0.05 Hz 30 mm swim: all below the 1 Hz cutoff.
    err = np.column_stack(
        [5e-3 + 1e-3 * T_S, 30e-3 * np.sin(2 * np.pi * 0.05 * T_S), np.full_like(T_S, -2e-3)]
    )
    assert 1e3 * jitter_rms(T_S, err) < 0.02  # mm, against ~30 mm of error
    # ...and they do not disturb a jitter riding on them.
    shake = 1e-3 * np.sin(2 * np.pi * 9.0 * T_S)
    assert 1e3 * jitter_rms(T_S, err + shake[:, None] * _axis([0, 0, 1])) == pytest.approx(
        1.0 / np.sqrt(2.0), rel=0.01
    )


def test_white_noise_jitter_is_its_sigma():
    rng = np.random.default_rng(0)
    sigma = 1e-3
    err = rng.normal(0.0, sigma, size=(len(T_S), 3))
    # A 1 Hz high-pass removes 1/250 of the 250 Hz noise band: the RMS of the 3-D norm is sqrt(3) sigma.
    assert jitter_rms(T_S, err) == pytest.approx(np.sqrt(3.0) * sigma, rel=0.02)


def test_uneven_sampling_is_resampled():
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0.0, 20.0, 8000))
    err = np.outer(1e-3 * np.sin(2 * np.pi * 6.0 * t), [1.0, 0.0, 0.0])
    assert 1e3 * jitter_rms(t, err) == pytest.approx(1.0 / np.sqrt(2.0), rel=0.02)


def test_headset_metrics_on_a_constructed_run():
    R_true, p_true = _truth(T_S)
    # Position: 3 mm constant offset + 1.5 mm at 10 Hz along x. Rotation: 0.2 deg at 7 Hz about a fixed axis.
    e_p = np.column_stack(
        [3e-3 + 1.5e-3 * np.sin(2 * np.pi * 10.0 * T_S), np.zeros_like(T_S), np.zeros_like(T_S)]
    )
    axis = _axis([0.3, 1.0, -0.2])
    angles = np.deg2rad(0.2) * np.sin(2 * np.pi * 7.0 * T_S)
    R_est = np.stack([exp_so3(axis * a) @ R for a, R in zip(angles, R_true, strict=True)])
    m = headset_metrics(T_S, R_est, p_true + e_p, R_true, p_true)
    assert m.jitter_pos_mm == pytest.approx(1.5 / np.sqrt(2.0), rel=0.01)
    assert m.jitter_rot_deg == pytest.approx(0.2 / np.sqrt(2.0), rel=0.01)
    # ATE = sqrt(mean((3 + 1.5 sin)^2)) = sqrt(9 + 1.125) mm; max = 4.5 mm.
    assert m.world_lock_ate_mm == pytest.approx(np.sqrt(9.0 + 1.5**2 / 2.0), rel=1e-3)
    assert m.max_err_mm == pytest.approx(4.5, rel=1e-3)  # the 10 Hz peak falls between 500 Hz samples
    assert m.pose_rate_hz == pytest.approx(RATE_HZ, rel=1e-9)
    path_m = np.sum(np.linalg.norm(np.diff(p_true, axis=0), axis=1))
    assert m.drift_pct == pytest.approx(100.0 * np.linalg.norm(e_p[-1]) / path_m, rel=1e-9)
    assert m.pred_err_pos_mm_p95 is None and "no prediction" in m.notes["pred_err_pos_mm_p95"]
    assert set(m.to_dict()) >= {"jitter_pos_mm", "jitter_rot_deg", "world_lock_ate_mm", "pose_rate_hz"}


def test_prediction_errors_count_only_fast_turns():
    n = 200
    speed = np.where(np.arange(n) % 2 == 0, np.deg2rad(200.0), np.deg2rad(100.0))
    fast = speed > np.deg2rad(150.0)
    err_mm = np.where(fast, np.repeat(np.arange(1.0, 101.0), 2), 1000.0)  # slow samples: huge, ignored
    err_deg = err_mm / 100.0
    axis = _axis([1.0, 1.0, 0.0])
    R_true = np.repeat(np.eye(3)[None], n, axis=0)
    R_pred = np.stack([exp_so3(axis * np.deg2rad(e)) for e in err_deg])
    p_true = np.zeros((n, 3))
    p_pred = np.outer(err_mm * 1e-3, _axis([0.0, 2.0, 1.0]))
    stats = prediction_errors(R_pred, p_pred, R_true, p_true, speed)
    assert (stats.n_fast, stats.n_total) == (100, 200)
    assert stats.pos_mm == pytest.approx(np.percentile(np.arange(1.0, 101.0), 95), rel=1e-9)  # 95.05
    assert stats.rot_deg == pytest.approx(0.9505, rel=1e-9)
    none = prediction_errors(R_pred, p_pred, R_true, p_true, np.zeros(n))
    assert none.pos_mm is None and none.n_fast == 0


def test_pose_rate_drift_interpolation_and_errors():
    assert pose_rate_hz(np.arange(0.0, 3.0, 1.0 / 72.0)) == pytest.approx(72.0)
    assert drift_pct(np.zeros((5, 3)), np.zeros((5, 3))) is None
    p_true = np.column_stack([np.linspace(0.0, 10.0, 11), np.zeros(11), np.zeros(11)])
    assert drift_pct(p_true + [0.0, 0.1, 0.0], p_true) == pytest.approx(1.0)
    R_true, p_true = _truth(T_S)
    R_i, p_i = interpolate_poses(np.array([1.001]), T_S, R_true, p_true)
    R_exact, p_exact = _truth(np.array([1.001]))
    np.testing.assert_allclose(R_i, R_exact, atol=1e-12)
    np.testing.assert_allclose(p_i, p_exact, atol=2e-6)  # linear: |p''| h^2 / 8 = 1.3e-6 m
    with pytest.raises(ValueError, match="strictly increasing"):
        pose_rate_hz(np.array([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="Nyquist"):
        jitter_rms(T_S, np.zeros((len(T_S), 3)), HeadsetMetricParams(jitter_cutoff_hz=300.0))
