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


def test_excitation_flag_raised_when_still_and_not_when_excited():
    rng = np.random.default_rng(0)
    still = HealthMonitor()
    _feed_imu(still, 5.0, rng, accel_std=0.01, gyro=0.0)
    # Window 2 s, hold 1 s: the first possible time is 3 s (to one IMU period).
    assert abs(still.first_time("insufficient_excitation") - 3.0) < 0.01
    moving = HealthMonitor()
    _feed_imu(moving, 5.0, rng, accel_std=0.5, gyro=0.0)
    assert moving.report() == []


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
        est = StateEstimate(k * 0.05, np.eye(3), np.zeros(3), np.array([speed_m_s, 0.0, 0.0]),
                            omega_B_rad_s=np.array([0.0, 0.0, 0.1]), cov=np.eye(15) * 1e-4)
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
