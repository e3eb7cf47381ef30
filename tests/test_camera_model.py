"""Tests of the camera timing model (envs/camera_model.py)."""

from __future__ import annotations

import numpy as np
import pytest
from viotb.envs.sim.camera_timing import CameraModelParams, frame_schedule


def test_counts_and_stamps_without_offset():
    sched = frame_schedule(CameraModelParams(rate_hz=20.0), 10.0, np.random.default_rng(0))
    assert len(sched) == 201  # exposures at 0, 0.05, ..., 10.0 inclusive
    np.testing.assert_allclose(sched.t_stamp_cam_s, np.arange(201) / 20.0, atol=0.0)
    np.testing.assert_array_equal(sched.t_exposure_imu_s, sched.t_stamp_cam_s)
    assert sched.kept.all()
    np.testing.assert_array_equal(sched.kept_indices, np.arange(201))


@pytest.mark.parametrize("offset_s", [0.013, -0.021])
def test_time_offset_and_latency(offset_s):
    params = CameraModelParams(rate_hz=10.0, time_offset_s=offset_s, latency_s=0.04)
    sched = frame_schedule(params, 5.0, np.random.default_rng(0))
    np.testing.assert_allclose(sched.t_exposure_imu_s - sched.t_stamp_cam_s, offset_s, atol=1e-15)
    np.testing.assert_allclose(sched.t_arrival_imu_s - sched.t_exposure_imu_s, 0.04, atol=1e-15)
    # Camera stamps sit on the camera's own 10 Hz grid; exposures stay inside [0, 5] s on the IMU clock.
    np.testing.assert_allclose(sched.t_stamp_cam_s * 10.0, np.round(sched.t_stamp_cam_s * 10.0), atol=1e-9)
    assert sched.t_exposure_imu_s.min() >= 0.0 and sched.t_exposure_imu_s.max() <= 5.0
    assert len(sched) == 50  # one of the 51 grid points falls outside [0, 5] for a non-zero offset
    np.testing.assert_allclose(np.diff(sched.t_exposure_imu_s), 0.1, atol=1e-12)


def test_blackout_respected_and_drops_seeded():
    params = CameraModelParams(
        rate_hz=20.0, drop_probability=0.3, blackout_intervals_s=((2.0, 3.5), (7.0, 7.2))
    )
    a = frame_schedule(params, 10.0, np.random.default_rng(0))
    b = frame_schedule(params, 10.0, np.random.default_rng(0))
    c = frame_schedule(params, 10.0, np.random.default_rng(1))
    np.testing.assert_array_equal(a.kept, b.kept)
    assert not np.array_equal(a.kept, c.kept)
    t = a.t_exposure_imu_s
    in_blackout = ((t >= 2.0) & (t < 3.5)) | ((t >= 7.0) & (t < 7.2))
    assert in_blackout.sum() == 30 + 4
    assert not a.kept[in_blackout].any()
    # Outside blackouts the drop rate is about 30 % (binomial, n = 167: 3 sigma = 0.11).
    drop_rate = 1.0 - a.kept[~in_blackout].mean()
    assert abs(drop_rate - 0.3) < 0.11
    # Same draws whatever the probability: p = 0 keeps all non-blackout frames.
    none_dropped = frame_schedule(
        CameraModelParams(rate_hz=20.0, blackout_intervals_s=((2.0, 3.5),)), 10.0, np.random.default_rng(0)
    )
    assert none_dropped.kept.sum() == 201 - 30
    everything = frame_schedule(CameraModelParams(drop_probability=1.0), 1.0, np.random.default_rng(0))
    assert not everything.kept.any()


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"rate_hz": 0.0}, "rate_hz"),
        ({"width": -3}, "width"),
        ({"height": 2.5}, "height"),
        ({"drop_probability": 1.5}, "drop_probability"),
        ({"latency_s": -0.1}, "latency_s"),
        ({"pixel_noise_std": -1.0}, "pixel_noise_std"),
        ({"blackout_intervals_s": ((3.0, 2.0),)}, "blackout_intervals_s"),
    ],
)
def test_bad_params_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        CameraModelParams(**kwargs)


def test_bad_duration():
    with pytest.raises(ValueError, match="duration_s"):
        frame_schedule(CameraModelParams(), 0.0, np.random.default_rng(0))
