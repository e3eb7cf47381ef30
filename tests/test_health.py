"""Tests of vio/health.py: each condition from hand-made inputs with known answers, and no false alarms."""

from __future__ import annotations

import numpy as np
from viotb.vio.health import HealthMonitor, HealthParams
from viotb.vio.types import GRAVITY_M_S2, HealthStatus, ImuSample, StateEstimate


def _feed_imu(mon: HealthMonitor, seconds: float, rng, accel_std: float, gyro: float, sat_at: float = -1.0):
    for k in range(int(seconds * 200)):
        t = k / 200.0
        acc = np.array([0.0, 0.0, GRAVITY_M_S2]) + rng.normal(0.0, accel_std, 3)
        mon.observe_imu(ImuSample(t, np.array([gyro, 0.0, 0.0]), acc, saturated=abs(t - sat_at) < 1e-9))


def _fly(
    mon: HealthMonitor,
    seconds: float,
    rng,
    R_WB: np.ndarray,
    accel_W,
    speed_m_s: float,
    noise_m_s2: float = 0.01,
) -> None:
    """Feed 200 Hz IMU samples of a body with a fixed attitude and a world acceleration ``accel_W(t)``.

    After every 10th sample the monitor also gets an estimate (true attitude, speed ``speed_m_s`` along x).
    """
    for k in range(int(seconds * 200)):
        t = k / 200.0
        f_B = R_WB.T @ (np.asarray(accel_W(t)) + [0.0, 0.0, GRAVITY_M_S2]) + rng.normal(0.0, noise_m_s2, 3)
        mon.observe_imu(ImuSample(t, np.zeros(3), f_B))
        if k % 10 == 0:
            est = StateEstimate(t, R_WB, np.zeros(3), np.array([speed_m_s, 0.0, 0.0]), cov=np.eye(15) * 1e-4)
            mon.observe_frame(t, HealthStatus(t, True, 100, updated_features=30), est)


def test_excitation_flag_needs_translation_without_world_acceleration():
    rng = np.random.default_rng(0)
    level = np.eye(3)
    cruise = HealthMonitor()
    _fly(cruise, 5.0, rng, level, lambda t: [0.0, 0.0, 0.0], speed_m_s=1.0)
    # The window (2 s) fills from the first estimate (t = 0), then the 0.5 s hold: 2.5 s, to one check period
    # (the test runs every excitation_check_s of IMU time) plus one sample.
    (c,) = cruise.report()
    late = cruise.params.excitation_check_s + 0.01
    assert c.name == "insufficient_excitation" and -0.01 < c.t_s_first - 2.5 < late, c
    # At rest there is no scale to lose; an oscillating acceleration (0.5 m/s^2) excites.
    for speed, acc in ((0.0, lambda t: [0.0, 0.0, 0.0]), (1.0, lambda t: [0.5 * np.sin(2.0 * t), 0.0, 0.0])):
        quiet = HealthMonitor()
        _fly(quiet, 5.0, rng, level, acc, speed_m_s=speed)
        assert quiet.report() == [], speed


def test_excitation_is_measured_in_the_world_frame():
    """A tilted body accelerating at a constant 1 m/s^2 sideways is excited.

    Its body-frame specific force is constant (per-axis std: noise only); rotated by the estimated attitude
    it is 1 m/s^2 of world acceleration. Given an attitude that lines the same readings up with gravity,
    they read as an unexcited cruise.
    """
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.1), -np.sin(0.1)], [0.0, np.sin(0.1), np.cos(0.1)]])
    mon = HealthMonitor()
    _fly(mon, 5.0, np.random.default_rng(1), tilt, lambda t: [0.0, 1.0, 0.0], speed_m_s=1.0)
    assert mon.report() == []
    fooled = HealthMonitor()
    rng = np.random.default_rng(1)
    for k in range(1000):
        t = k / 200.0
        f_B = tilt.T @ np.array([0.0, 1.0, GRAVITY_M_S2])
        fooled.observe_imu(ImuSample(t, np.zeros(3), f_B + rng.normal(0.0, 0.01, 3)))
        if k % 10 == 0:
            R_aligned = _rotation_taking(f_B, np.array([0.0, 0.0, 1.0]))
            est = StateEstimate(t, R_aligned, np.zeros(3), np.array([1.0, 0.0, 0.0]), cov=np.eye(15) * 1e-4)
            fooled.observe_frame(t, HealthStatus(t, True, 100, updated_features=30), est)
    assert fooled.first_time("insufficient_excitation") is not None


def _rotation_taking(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R with R a / |a| = b / |b| (Rodrigues)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def test_saturation_names_count_and_time():
    mon = HealthMonitor()
    _feed_imu(mon, 3.0, np.random.default_rng(0), accel_std=0.5, gyro=0.5, sat_at=1.5)
    (c,) = mon.report()
    assert c.name == "imu_saturation" and c.t_s_first == 1.5 and "1 saturated" in c.evidence


def test_feature_poverty_after_n_frames_and_divergence():
    mon = HealthMonitor(HealthParams(poverty_frames=5))
    est = StateEstimate(0.0, np.eye(3), np.zeros(3), np.zeros(3), cov=np.eye(15) * 1e-4)
    for k in range(10):
        mon.observe_frame(k * 0.05, HealthStatus(k * 0.05, True, tracked_features=3), est)
    assert abs(mon.first_time("feature_poverty") - 0.2) < 1e-12  # 5th poor frame
    assert "feature_poverty" in mon.active()
    mon.observe_frame(0.55, HealthStatus(0.55, True, tracked_features=100), est)
    assert "feature_poverty" not in mon.active()
    big = StateEstimate(0.6, np.eye(3), np.zeros(3), np.zeros(3), cov=np.eye(15) * 200.0)
    mon.observe_frame(0.6, HealthStatus(0.6, True, tracked_features=100), big)
    assert mon.first_time("divergence") == 0.6
    mon2 = HealthMonitor()
    mon2.observe_frame(1.0, HealthStatus(1.0, True, 100, diverged=True, reason="x"), None)
    assert mon2.report()[0].name == "divergence"


def test_initialization_timeout_and_gravity_norm():
    late = HealthMonitor(HealthParams(init_timeout_s=2.0))
    _feed_imu(late, 3.0, np.random.default_rng(0), accel_std=0.01, gyro=0.0)
    assert abs(late.first_time("initialization_failure") - 2.005) < 1e-9
    mon = HealthMonitor()
    rng = np.random.default_rng(1)
    for k in range(200):
        acc = np.array([0.0, 0.0, 10.3]) + rng.normal(0, 0.01, 3)
        mon.observe_imu(ImuSample(k / 200.0, np.zeros(3), acc))
    est = StateEstimate(1.0, np.eye(3), np.zeros(3), np.zeros(3), cov=np.eye(15) * 1e-4)
    mon.observe_frame(1.0, HealthStatus(1.0, True, 100), est)
    assert mon.report()[0].name == "initialization_failure" and "gravity norm" in mon.report()[0].evidence


def _sync_frames(mon: HealthMonitor, nis: float, speed_m_s: float, n: int = 40, n_features: int = 30):
    for k in range(n):
        est = StateEstimate(
            k * 0.05,
            np.eye(3),
            np.zeros(3),
            np.array([speed_m_s, 0.0, 0.0]),
            omega_B_rad_s=np.array([0.0, 0.0, 0.1]),
            cov=np.eye(15) * 1e-4,
        )
        h = HealthStatus(k * 0.05, True, 60, updated_features=n_features, nis_per_dof_all=nis)
        mon.observe_frame(k * 0.05, h, est)


def test_high_nis_while_moving_names_time_sync_or_extrinsic():
    mon = HealthMonitor()
    _sync_frames(mon, nis=1.5, speed_m_s=2.0)
    (c,) = mon.report()
    assert c.name == "time_sync_or_extrinsic_suspected" and "NIS per dof 1.50" in c.evidence
    assert abs(c.t_s_first - 29 * 0.05) < 1e-9  # the 30-update window fills at frame 30
    # Consistent filter (NIS ~ 1), at rest with a high NIS, too few features, or no NIS: nothing.
    for nis, speed, nf in ((1.0, 2.0, 30), (1.5, 0.0, 30), (1.5, 2.0, 3), (float("nan"), 2.0, 30)):
        quiet = HealthMonitor()
        _sync_frames(quiet, nis=nis, speed_m_s=speed, n_features=nf)
        assert quiet.report() == [], (nis, speed, nf)


def test_moving_past_features_that_never_enter_an_update_is_divergence():
    mon = HealthMonitor()
    for k in range(60):  # 3 s at 20 Hz, 1 m/s, 100 tracks, no feature ever used
        t = k * 0.05
        est = StateEstimate(t, np.eye(3), np.zeros(3), np.array([1.0, 0.0, 0.0]), cov=np.eye(15) * 1e-4)
        mon.observe_frame(t, HealthStatus(t, True, tracked_features=100, updated_features=0), est)
    (c,) = mon.report()
    # The clock starts at the first frame (t = 0); the first frame more than 2 s later is 2.05 s.
    assert c.name == "divergence" and abs(c.t_s_first - 2.05) < 1e-9 and "none used" in c.evidence
    # Updates every 6th frame, or no motion, or too few tracks: nothing.
    for used_every, speed, tracks in ((6, 1.0, 100), (10**6, 0.0, 100), (10**6, 1.0, 10)):
        quiet = HealthMonitor()
        for k in range(60):
            t = k * 0.05
            est = StateEstimate(t, np.eye(3), np.zeros(3), np.array([speed, 0.0, 0.0]), cov=np.eye(15) * 1e-4)
            used = 30 if k % used_every == 0 and k > 0 else 0
            quiet.observe_frame(t, HealthStatus(t, True, tracked_features=tracks, updated_features=used), est)
        # (10 tracks is feature poverty, but not divergence)
        assert "divergence" not in {c.name for c in quiet.report()}, (used_every, speed, tracks)


def test_calibration_drift_names_the_calibration_that_moved():
    from viotb.vio.types import CalibrationDrift

    est = StateEstimate(1.0, np.eye(3), np.zeros(3), np.zeros(3), cov=np.eye(15) * 1e-4)
    deg = np.deg2rad(1.0)

    def named(drift: CalibrationDrift) -> set[str]:
        mon = HealthMonitor()
        mon.observe_frame(1.0, HealthStatus(1.0, True, 100, updated_features=30, calibration=drift), est)
        return {c.name for c in mon.report()}

    # Limits: more than 5 sigma and more than 2 ms / 0.5 deg / 2 cm.
    late = CalibrationDrift(time_offset_s=0.003, time_offset_sigma_s=1e-4)
    assert named(late) == {"time_offset_miscalibrated"}
    assert named(CalibrationDrift(time_offset_s=0.003, time_offset_sigma_s=1e-3)) == set()  # 3 sigma
    assert named(CalibrationDrift(time_offset_s=0.001, time_offset_sigma_s=1e-5)) == set()  # below 2 ms
    zeros, tiny = np.zeros(3), np.full(3, 1e-3)
    rot = CalibrationDrift(
        rotation_BC_rad=np.array([deg, 0.0, 0.0]),
        rotation_sigma_rad=np.full(3, 0.02 * deg),
        translation_BC_m=zeros,
        translation_sigma_m=tiny,
    )
    assert named(rot) == {"extrinsic_miscalibrated"}
    small = CalibrationDrift(
        rotation_BC_rad=np.array([0.3 * deg, 0.0, 0.0]),
        rotation_sigma_rad=tiny * 1e-3,
        translation_BC_m=np.array([0.03, 0.0, 0.0]),
        translation_sigma_m=np.full(3, 0.01),
    )
    assert named(small) == set()  # 0.3 deg is below 0.5 deg; 3 cm is only 3 sigma
    assert named(CalibrationDrift()) == set()  # nothing estimated (all NaN)
