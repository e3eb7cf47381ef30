"""A frame is fed once the IMU has passed it: the samples through the first one at or past its time.

The estimator reaches the frame by interpolating the two readings around it. Fed only the samples up to
the frame, it held the last reading over the rest of the interval: on ``head-fast-turns`` (30 Hz frames on
a 200 Hz IMU, 350 deg/s) that put every frame's pose off by up to half the angular acceleration times the
interval squared (README "Consistency per scenario").
"""

from __future__ import annotations

import numpy as np
import pytest
from viotb.envs.run.replay import imu_end_for_frame
from viotb.vio.lie import exp_so3, log_so3
from viotb.vio.propagator import select_imu_readings


def _reference_end(t: np.ndarray, i: int, t_frame: float) -> int:
    """The rule spelled out sample by sample: feed while the sample or the one before is not past it."""
    while i < len(t) and (t[i] <= t_frame or (i > 0 and t[i - 1] < t_frame)):
        i += 1
    return i


def test_the_end_index_matches_the_rule_on_random_streams():
    rng = np.random.default_rng(0)
    for _ in range(200):
        t = np.cumsum(rng.uniform(0.001, 0.01, rng.integers(1, 40)))
        i = int(rng.integers(0, len(t) + 1))
        for t_frame in (*rng.uniform(t[0] - 0.02, t[-1] + 0.02, 5), *t[rng.integers(0, len(t), 3)]):
            assert imu_end_for_frame(t, i, float(t_frame)) == _reference_end(t, i, float(t_frame))


def test_on_the_grid_nothing_changes_and_off_it_the_next_sample_comes_too():
    t = np.arange(0.0, 0.1, 0.005)  # 200 Hz
    assert imu_end_for_frame(t, 0, 0.05) == 11  # a 20 Hz frame on a sample: through it, as before
    assert imu_end_for_frame(t, 0, 1.0 / 30.0) == 8  # 33.3 ms: through the sample at 35 ms
    assert imu_end_for_frame(t, 0, -0.01) == 0  # before the first sample: none
    assert imu_end_for_frame(t, 5, 0.01) == 5  # never back


def test_the_readings_at_an_off_grid_frame_are_interpolated_not_held():
    # Constant angular acceleration about z: w(t) = alpha t. The rotation to a frame between two samples is
    # alpha t_f^2 / 2 (closed form); trapezoids over the interpolated readings give it to round-off, while
    # holding the last sample over the final partial interval misses by alpha (t_f - t_k)^2 / 2.
    alpha, dt, t_f = 40.0, 0.005, 1.0 / 30.0
    t = np.arange(0.0, 0.06, dt)
    gyro = np.stack([np.zeros_like(t), np.zeros_like(t), alpha * t], axis=1)
    accel = np.zeros_like(gyro)

    def angle(n_fed: int) -> float:
        tt, gg, _ = select_imu_readings(t[:n_fed], gyro[:n_fed], accel[:n_fed], 0.0, t_f)
        R = np.eye(3)
        for k in range(len(tt) - 1):
            R = R @ exp_so3(0.5 * (gg[k] + gg[k + 1]) * (tt[k + 1] - tt[k]))
        return float(log_so3(R)[2])

    truth = 0.5 * alpha * t_f**2
    ahead = angle(imu_end_for_frame(t, 0, t_f))
    held = angle(int(np.searchsorted(t, t_f, side="right")))
    assert ahead == pytest.approx(truth, rel=1e-12)
    t_k = t[t <= t_f][-1]
    assert held == pytest.approx(truth - 0.5 * alpha * (t_f - t_k) ** 2, rel=1e-9)
