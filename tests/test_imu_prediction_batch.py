"""Batched covariance reads and the estimate memo of the per-tick prediction (imu_prediction.py, msckf.py).

``PredictionChain.prefetch`` computes many predictions' covariances with stacked products; they must equal,
bit for bit, the covariances :meth:`PredictionChain.cov` computes one at a time (the flight log reads every
tick's). ``MsckfEstimator.estimate`` returns its last record again while no IMU sample and no frame
arrived; that record must hold what a fresh call computes.
"""

import numpy as np
import pytest
from test_imu_prediction import _fly_filter
from viotb.vio.imu_prediction import LazyCovarianceEstimate, PredictionChain, prefetch_covariances
from viotb.vio.propagator import Propagator
from viotb.vio.types import ImuNoise, ImuSample


def _computed(e: LazyCovarianceEstimate) -> bool:
    """Whether the estimate's covariance is computed: read already, or in its chain's memo."""
    return e.cov_ready or e._source[1] in e._source[0]._covs


@pytest.mark.parametrize("compiled", [False, True])
def test_prefetched_covariances_equal_the_per_index_ones(compiled: bool) -> None:
    one = [e for e, _, _ in _fly_filter(10_000, seed=2, compiled=compiled)]
    batch = [e for e, _, _ in _fly_filter(10_000, seed=2, compiled=compiled)]
    assert len(one) == len(batch) > 100
    per_index = [e.cov for e in one]  # one chain.cov call per estimate, oldest first
    # Frame by frame as the flight does (a few ticks, then a batch), some already read, some twice.
    for k in range(0, len(batch), 13):
        _ = batch[k].cov
    for start in range(0, len(batch), 12):
        prefetch_covariances(batch[start : start + 12] + batch[start : start + 3])
    assert all(_computed(e) for e in batch)
    for a, b in zip(per_index, batch, strict=True):
        assert np.array_equal(a, b.cov)


def test_prefetch_skips_plain_estimates_and_checks_indices() -> None:
    prop = Propagator(ImuNoise())
    rng = np.random.default_rng(0)
    for k in range(6):
        prop.feed_imu(ImuSample(0.005 * k, rng.normal(0, 0.1, 3), rng.normal(0, 0.1, 3) + [0, 0, 9.81]))
    rows = [e for e, _, _ in _fly_filter(10_000, seed=3)][:5]
    plain = LazyCovarianceEstimate(0.0, np.eye(3), *np.zeros((4, 3)), np.zeros(3), cov=np.eye(15))
    prefetch_covariances([plain, *rows])
    assert all(_computed(e) for e in rows)
    from viotb.vio.state import ImuValues

    vals = ImuValues(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    chain = PredictionChain(0, 0.0, vals, np.eye(15), prop)
    chain.advance(0.005)
    with pytest.raises(IndexError, match="no prediction 3"):
        chain.prefetch([0, 3])
    chain.prefetch([0])
    assert np.array_equal(chain.cov(0), chain._covs[0])


def test_estimate_memo_returns_what_a_fresh_call_computes() -> None:
    rows = _fly_filter(10_000, seed=4)
    estimates = [e for e, _, _ in rows]
    # Five ticks per four samples: every fourth sample is read twice, the second call the same record.
    repeats = sum(a is b for a, b in zip(estimates, estimates[1:], strict=False))
    assert repeats >= 25
    # A new sample gives a new record.
    assert len({id(e) for e in estimates}) == len(estimates) - repeats


def test_memoized_record_equals_a_recomputed_one() -> None:
    from test_msckf import SyntheticWorld, _truth_init
    from viotb.vio.msckf import MsckfEstimator
    from viotb.vio.msckf_params import MsckfParams
    from viotb.vio.types import CameraFrame

    rng = np.random.default_rng(5)
    world = SyntheticWorld(np.random.default_rng(105))
    est = MsckfEstimator(world.calib, ImuNoise(), MsckfParams(frontend="sim"))
    est.initialize(_truth_init(world))
    for k in range(1, 61):
        t = 0.005 * k
        _, _, _, omega, f = world.pose(t)
        est.feed_imu(ImuSample(t, omega + rng.normal(0, 0.01, 3), f + rng.normal(0, 0.05, 3)))
        if k % 10 == 0:
            est.feed_camera(CameraFrame(t_s=t - 0.0013, features=world.observe(t, rng, 0.5)))
        first = est.estimate()
        again = est.estimate()
        assert again is first
        est._published = None  # forget the memo: the same chain, the same prediction, recomputed
        fresh = est.estimate()
        assert fresh is not first
        for name in ("t_s", "R_WB", "p_WB", "v_WB", "gyro_bias_rad_s", "accel_bias_m_s2", "omega_B_rad_s"):
            assert np.array_equal(getattr(fresh, name), getattr(first, name)), name
        assert np.array_equal(fresh.cov, first.cov)
