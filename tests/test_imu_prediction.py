"""The per-tick prediction with a lazy covariance (vio/imu_prediction.py) against the eager prediction.

The reference is the former ``MsckfEstimator.estimate``: every call predicts mean, ``Phi`` and ``Q`` to the
newest IMU sample with ``Propagator.predict``, chains them onto the previous call's and builds the 15 x 15
covariance at once. The lazy chain must give the same mean bit for bit (the controller flies on it) and
the same covariance to 1e-9 relative however often and however late it is read.
"""

import copy
import pickle
from dataclasses import replace

import numpy as np
import pytest
from random_states import random_imu_values
from test_msckf import SyntheticWorld, _truth_init
from viotb.vio.imu_prediction import LazyCovarianceEstimate, PredictionChain
from viotb.vio.msckf import MsckfEstimator
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.propagator import (
    Integration,
    Propagator,
    integrate_mean,
    step_transition,
    step_transitions,
)
from viotb.vio.state import IMU_BLOCK
from viotb.vio.types import CameraFrame, ImuNoise, ImuSample, StateEstimate


def _assert_rel(actual: np.ndarray, desired: np.ndarray, rel: float = 1e-9) -> None:
    scale = float(np.max(np.abs(desired)))
    np.testing.assert_allclose(actual, desired, rtol=rel, atol=rel * scale)


class _EagerReference:
    """The former ``MsckfEstimator.estimate``: mean, ``Phi``, ``Q`` and covariance at every call."""

    def __init__(self) -> None:
        self.cache = None

    def __call__(self, est: MsckfEstimator) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        st = est.state
        t_new = est._last_imu.t_s if est._last_imu is not None else st.t_s
        c = self.cache
        if c is not None and c[0] == est._version and c[1] == t_new:
            _, t_out, vals, _, _, cov = c
        else:
            if c is not None and c[0] == est._version and c[1] <= t_new:
                _, t0, vals0, phi0, q0, _ = c
            else:
                t0, vals0, phi0, q0 = st.t_s, st.imu, np.eye(15), np.zeros((15, 15))
            compiled, est.propagator.compiled = est.propagator.compiled, False  # the numpy reference
            vals, phi, q = est.propagator.predict(vals0, t0, t_new)
            est.propagator.compiled = compiled
            phi_tot, q_tot = phi @ phi0, phi @ q0 @ phi.T + q
            t_out = max(t_new, t0)
            sl = st.block(IMU_BLOCK).indices
            cov = phi_tot @ st.cov[sl, sl] @ phi_tot.T + q_tot
            self.cache = (est._version, t_out, vals, phi_tot, q_tot, cov)
        return t_out, vals.R_WB, vals.p_WB, 0.5 * (cov + cov.T)


def _fly_filter(read_every: int, seed: int = 0, compiled: bool = False):
    """A synthetic flight at 200 Hz IMU / 20 Hz camera with estimates at 250 Hz-like uneven ticks.

    The filter predicts with the compiled kernels or (``compiled`` False) the numpy functions the
    reference calls.

    Returns per call ``(lazy estimate, reference tuple, read now)``; covariances of the calls with
    ``read now`` are read at once, the rest only at the end (after later frames changed the filter).
    """
    rng = np.random.default_rng(seed)
    world = SyntheticWorld(np.random.default_rng(100 + seed))
    est = MsckfEstimator(world.calib, ImuNoise(), MsckfParams(frontend="sim"))
    est.propagator.compiled = compiled
    est.initialize(_truth_init(world))
    ref = _EagerReference()
    out, calls = [], 0
    for k in range(1, 121):
        t = 0.005 * k
        _, _, _, omega, f = world.pose(t)
        est.feed_imu(ImuSample(t, omega + rng.normal(0, 0.01, 3), f + rng.normal(0, 0.05, 3)))
        if k % 10 == 0:
            est.feed_camera(CameraFrame(t_s=t - 0.0013, features=world.observe(t, rng, 0.5)))
        for _ in range(1 + (k % 4 == 0)):  # five ticks per four samples: some calls see no new sample
            e = est.estimate()
            r = ref(est)
            read = calls % read_every == 0
            if read:
                _ = e.cov
            out.append((e, r, read))
            calls += 1
    return out


@pytest.mark.parametrize("read_every", [1, 5, 10_000])
def test_lazy_prediction_equals_the_eager_one(read_every):
    rows = _fly_filter(read_every)
    for e, (t_ref, R_ref, p_ref, cov_ref), _ in rows:
        assert isinstance(e, LazyCovarianceEstimate)
        assert e.t_s == t_ref
        np.testing.assert_array_equal(e.R_WB, R_ref)  # the mean bit for bit
        np.testing.assert_array_equal(e.p_WB, p_ref)
        _assert_rel(e.cov, cov_ref)
    if read_every == 1:  # read at every tick: the eager prediction's own operations
        for e, (_, _, _, cov_ref), _ in rows:
            np.testing.assert_array_equal(e.cov, cov_ref)


@pytest.mark.parametrize("read_every", [1, 7])
def test_compiled_lazy_prediction_equals_the_numpy_eager_one(read_every):
    """The kernels' mean and covariance against the numpy eager prediction, through a filter's updates."""
    rows = _fly_filter(read_every, seed=1, compiled=True)
    for e, (t_ref, R_ref, p_ref, cov_ref), _ in rows:
        assert e.t_s == t_ref
        _assert_rel(e.R_WB, R_ref)
        _assert_rel(e.p_WB, p_ref)
        _assert_rel(e.cov, cov_ref)


@pytest.mark.parametrize("method", [Integration.DISCRETE, Integration.RK4])
def test_batched_transitions_equal_per_interval(method):
    rng = np.random.default_rng(3)
    x = random_imu_values(rng)
    steps = []
    for _ in range(7):
        w0, w1 = rng.normal(0, 2.0, (2, 3))
        a0, a1 = rng.normal(0, 1.0, (2, 3)) + [0, 0, 9.81]
        step = integrate_mean(x, w0, w1, a0, a1, float(rng.uniform(0.002, 0.008)), method)
        steps.append(step)
        x = step.new
    batched = step_transitions(steps)
    for phi, step in zip(batched, steps, strict=True):
        _assert_rel(phi, step_transition(step), 1e-12)


def test_chain_index_errors_and_time_order():
    prop = Propagator(ImuNoise())
    for k in range(5):
        prop.feed_imu(ImuSample(0.01 * k, np.zeros(3), np.array([0.0, 0.0, 9.81])))
    x = random_imu_values(np.random.default_rng(0))
    chain = PredictionChain(0, 0.01, x, np.eye(15), prop)
    i, _ = chain.advance(0.02)
    assert chain.advance(0.02)[0] == i and len(chain) == 1
    with pytest.raises(ValueError, match="before the newest prediction"):
        chain.advance(0.015)
    with pytest.raises(IndexError, match="no prediction 3"):
        chain.cov(3)
    with pytest.raises(ValueError, match="needs cov or source"):
        z = np.zeros(3)
        LazyCovarianceEstimate(0.0, np.eye(3), z, z, z, z, z)


def test_lazy_estimate_reads_copies_and_pickles_like_the_record():
    e, (_, _, _, cov_ref), _ = _fly_filter(10_000)[-1]
    assert not e.cov_ready
    moved = replace(e, p_WB=e.p_WB + 1.0)  # dataclasses.replace reads the covariance
    assert e.cov_ready and isinstance(moved, StateEstimate)
    np.testing.assert_array_equal(moved.cov, e.cov)
    for clone in (pickle.loads(pickle.dumps(e)), copy.deepcopy(e)):
        assert type(clone) is StateEstimate
        np.testing.assert_array_equal(clone.cov, e.cov)
        np.testing.assert_array_equal(clone.p_WB, e.p_WB)
    np.testing.assert_array_equal(e.cov_position_W_m2, e.cov[3:6, 3:6])
    _assert_rel(e.cov, cov_ref)


def test_flight_log_sigmas_of_lazy_estimates_equal_the_eager_covariance():
    """``fly._log_tick`` defers a lazy estimate's sigma cells; once filled they are the eager ones."""
    from types import SimpleNamespace

    from viotb.envs.run.flight_log import FlightLog
    from viotb.envs.run.fly import _log_tick

    rows = _fly_filter(10_000)[-40:]  # none read yet: every row's sigma waits
    log = FlightLog()
    c, s = np.cos(0.3), np.sin(0.3)
    gauge = (c, s, 0.1, -0.2, 0.05)
    R_g = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    imu = ImuSample(0.0, np.zeros(3), np.array([0.0, 0.0, 9.81]))
    truth = SimpleNamespace(p_WB=np.zeros(3), R_WB=np.eye(3))
    for k, (e, _, _) in enumerate(rows):
        loop = SimpleNamespace(t_s=0.004 * k, last_imu=imu)
        _log_tick(log, loop, "mission", e, None, gauge, truth, np.zeros(4))
    assert not any(e.cov_ready for e, _, _ in rows)
    sigma = log.p_sigma_W  # the read fills them, the covariances of each chain in one batch
    for got, (_, (_, _, _, cov_ref), _) in zip(sigma, rows, strict=True):
        want = np.sqrt(np.diag(R_g @ cov_ref[3:6, 3:6] @ R_g.T))
        _assert_rel(got, want, 1e-9)
