"""Tests of vio/lifecycle.py, the StateEstimate covariance accessors and the full Estimator protocol."""

import numpy as np
from test_msckf import SyntheticWorld
from viotb.vio.factory import ESTIMATOR_NAMES, make_estimator
from viotb.vio.frontend import Tracks
from viotb.vio.lifecycle import excitation_wanted, frame_health, track_conditions
from viotb.vio.types import ImuNoise, StateEstimate


def test_track_conditions_and_frame_health():
    assert track_conditions(0) == ("no_features",)
    assert track_conditions(19) == ("feature_poverty",)
    assert track_conditions(20) == ()
    tracks = Tracks.empty(1.0, 1.0)
    h = frame_health(1.0, tracks, "", updated_features=0, conditions=("zupt",))
    assert h.initialized and not h.diverged and h.conditions == ("zupt", "no_features")
    assert frame_health(1.0, tracks, "boom", updated_features=0).diverged


def test_excitation_wanted_reads_the_horizontal_accel_bias_sigma():
    cov = np.eye(15) * 1e-6
    assert not excitation_wanted(cov, 0.02)
    cov[13, 13] = 0.03**2
    assert excitation_wanted(cov, 0.02)


def test_state_estimate_covariance_accessors_name_the_blocks():
    cov = np.diag(np.arange(1.0, 16.0))
    e = StateEstimate(0.0, np.eye(3), np.zeros(3), np.zeros(3), cov=cov)
    for block, (a, b) in (
        (e.cov_orientation_rad2, (0, 3)),
        (e.cov_position_W_m2, (3, 6)),
        (e.cov_velocity_W_m2_s2, (6, 9)),
        (e.cov_gyro_bias_rad2_s2, (9, 12)),
        (e.cov_accel_bias_m2_s4, (12, 15)),
    ):
        np.testing.assert_array_equal(block, cov[a:b, a:b])
    np.testing.assert_allclose(e.position_sigma_W_m, np.sqrt([4.0, 5.0, 6.0]))


def test_every_estimator_implements_the_whole_protocol():
    world = SyntheticWorld(np.random.default_rng(0))
    truth = StateEstimate(0.0, np.eye(3), np.ones(3), np.zeros(3))
    for name in ESTIMATOR_NAMES:
        est = make_estimator(name, world.calib, ImuNoise(), frontend="sim")
        assert est.wants_excitation() is False  # nothing known yet, nothing asked
        est.feed_truth(truth)
        assert est.last_tracks_px().shape == (0, 2)
        if name == "ground-truth":
            est.initialize(object())  # documented no-op
            assert est.estimate() is truth
        else:
            assert est.estimate() is None
