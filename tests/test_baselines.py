"""Tests of vio/baselines.py and vio/factory.py."""

import numpy as np
import pytest
from test_msckf import EUROC, SyntheticWorld, _truth_init
from viotb.vio.baselines import GroundTruthEstimator, ImuOnlyEstimator
from viotb.vio.factory import ESTIMATOR_NAMES, make_estimator
from viotb.vio.types import CameraFrame, Estimator, ImuNoise, ImuSample, StateEstimate


def test_factory_builds_every_name_and_rejects_unknown():
    world = SyntheticWorld(np.random.default_rng(0))
    for name in ESTIMATOR_NAMES:
        est = make_estimator(name, world.calib, ImuNoise(), frontend="sim")
        assert isinstance(est, Estimator) and est.name == name
    with pytest.raises(ValueError, match="allowed: msckf, window, imu-only, ground-truth"):
        make_estimator("window9", world.calib, ImuNoise())
    with pytest.raises(ValueError, match="allowed: klt, sim"):
        make_estimator("msckf", world.calib, ImuNoise(), frontend="orb")


def test_imu_only_dead_reckons_noise_free_imu_and_grows_covariance():
    world = SyntheticWorld(np.random.default_rng(0))
    est = ImuOnlyEstimator(world.calib, ImuNoise())
    assert est.estimate() is None
    est.initialize(_truth_init(world))
    c0 = est.estimate().cov.copy()
    for t in np.arange(0.005, 2.0 + 1e-9, 0.005):
        _, _, _, omega, f = world.pose(t)
        est.feed_imu(ImuSample(float(t), omega, f))
    est.feed_camera(CameraFrame(2.0))
    e = est.estimate()
    R, p, v, _, _ = world.pose(2.0)
    # RK4 on exact readings: error dominated by the linear interpolation of the rates (O(dt^2)).
    assert np.linalg.norm(e.p_WB - p) < 2e-3 and np.linalg.norm(e.v_WB - v) < 2e-3
    assert np.all(np.diag(e.cov) >= np.diag(c0))
    assert np.trace(e.cov[3:6, 3:6]) > 10 * np.trace(c0[3:6, 3:6])
    assert est.health().initialized


def test_imu_only_initializes_statically_on_euroc():
    from viotb.envs.data.euroc import read_euroc

    ds = read_euroc(EUROC.parent)
    est = ImuOnlyEstimator(ds.calib, ds.imu_noise)
    n = int(np.searchsorted(ds.imu.t_s, ds.imu.t_s[0] + 2.0))
    for i in range(n):
        est.feed_imu(ds.imu.sample(i))
    est.feed_camera(CameraFrame(float(ds.imu.t_s[n - 1])))
    e = est.estimate()
    assert e is not None
    # Static: gravity along the body's measured specific force.
    f_mean = np.mean(ds.imu.accel_B_m_s2[:n], axis=0)
    np.testing.assert_allclose(e.R_WB @ f_mean / np.linalg.norm(f_mean), [0, 0, 1], atol=0.01)


def test_ground_truth_passes_through():
    est = GroundTruthEstimator()
    assert est.estimate() is None and not est.health().initialized
    truth = StateEstimate(1.5, np.eye(3), np.array([1.0, 2.0, 3.0]), np.zeros(3))
    est.feed_truth(truth)
    est.feed_imu(ImuSample(1.6, np.zeros(3), np.zeros(3)))
    est.feed_camera(CameraFrame(1.6))
    assert est.estimate() is truth and est.health().initialized and est.health().t_s == 1.5
