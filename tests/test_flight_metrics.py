"""Streamed flight log and chunked metrics (envs/run/flight_log.py, flight_metrics.py) against whole arrays.

The reference formulas are the whole-array metrics ``viotb fly`` used before the log was streamed (numpy
over full columns, ``align_umeyama``); the streamed log, in small chunks so that many of them go through the
temporary file, must give the same columns bit for bit and the same metrics to 1e-12 relative.
"""

import numpy as np
import pytest
from viotb.envs.run.flight_log import FlightLog
from viotb.envs.run.flight_metrics import blackout_metrics, flight_metrics, lights_out_metrics
from viotb.vio.metrics import align_umeyama


def _reference_metrics(log, mission_t0, init_time):
    t, p_true, p_est, p_set = log.t_s, log.p_true_W, log.p_est_W, log.p_set_W
    out = {"hover_rms_m": None, "max_err_m": None, "ate_posyaw_m": None, "est_rms_m": None}
    if mission_t0 is not None:
        m = t >= mission_t0
        err = np.linalg.norm(p_true[m] - p_set[m], axis=1)
        if err.size:
            out["hover_rms_m"] = float(np.sqrt(np.mean(err**2)))
            out["max_err_m"] = float(np.max(err))
    ok = np.all(np.isfinite(p_est), axis=1)
    if init_time is not None and ok.sum() >= 3:
        est_err = np.linalg.norm(p_est[ok] - p_true[ok], axis=1)
        out["est_rms_m"] = float(np.sqrt(np.mean(est_err**2)))
        al = align_umeyama(p_est[ok], p_true[ok], "posyaw")
        aligned = (al.s * (al.R @ p_est[ok].T)).T + al.t
        out["ate_posyaw_m"] = float(np.sqrt(np.mean(np.sum((aligned - p_true[ok]) ** 2, axis=1))))
    return out


def _reference_blackout(log, blackouts):
    t = log.t_s
    err_set = np.linalg.norm(log.p_true_W - log.p_set_W, axis=1)
    err_est = np.linalg.norm(log.p_est_W - log.p_true_W, axis=1)
    ft, nf = log.frame_t_s, log.frame_features
    excursion, est_err, recovered = 0.0, 0.0, True
    for a, b in blackouts:
        m = (t >= a) & (t <= b + 1.0)
        if not np.any(m):
            recovered = False
            continue
        excursion = max(excursion, float(np.nanmax(err_set[m])))
        est_err = max(est_err, float(np.nanmax(err_est[m])))
        recovered = recovered and bool(np.any(nf[(ft > b) & (ft <= b + 1.0)] >= 20))
    return {"blackout_excursion_m": excursion, "blackout_est_err_m": est_err, "blackout_recovered": recovered}


def _reference_lights(log, intervals, back_m=0.10):
    t = log.t_s
    err = np.linalg.norm(log.p_true_W - log.p_set_W, axis=1)
    after = t >= intervals[0][0]
    out = {"lights_out_excursion_m": float(np.nanmax(err[after])) if np.any(after) else None}
    end = intervals[-1][1]
    m = t >= end
    if not np.any(m):
        return {**out, "lights_out_back_s": None}
    far = np.flatnonzero(~(err[m] < back_m))
    if len(far) == 0:
        out["lights_out_back_s"] = 0.0
    elif far[-1] == int(np.sum(m)) - 1:
        out["lights_out_back_s"] = None
    else:
        out["lights_out_back_s"] = float(t[m][far[-1] + 1] - end)
    return out


def _flight(n: int, seed: int, chunk_rows: int, in_memory: bool, gauge_tick: int = 40) -> FlightLog:
    """A synthetic flight: NaN estimate and setpoint before ``gauge_tick``, a yawed, offset estimate after."""
    rng = np.random.default_rng(seed)
    log = FlightLog(in_memory=in_memory, chunk_rows=chunk_rows)
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    for k in range(n):
        t_s = 0.004 * k
        p_true = np.array([np.sin(t_s), np.cos(0.7 * t_s), 1.0 + 0.1 * t_s])
        gauged = k >= gauge_tick
        p_set = p_true + rng.normal(scale=0.05, size=3) * (1.0 + 3.0 * (1.5 < t_s < 2.0))
        log.append_tick(
            t_s, "ground" if not gauged else "mission",
            p_true_W=p_true,
            p_est_W=R @ p_true + [0.2, -0.1, 0.05] + rng.normal(scale=0.01, size=3) if gauged else np.nan,
            p_sigma_W=rng.uniform(size=3) if gauged else np.nan,
            p_set_W=p_set if gauged else np.nan,
            yaw_true=float(rng.normal()), yaw_est=float(rng.normal()) if gauged else np.nan,
            thrusts_N=rng.uniform(size=4), gyro_B=rng.normal(size=3), accel_B=rng.normal(size=3),
        )  # fmt: skip
        if k % 10 == 0:
            log.append_frame(t_s, int(rng.integers(0, 60)), ())
    return log


@pytest.mark.parametrize("n", [1, 63, 64, 65, 1000])
def test_streamed_columns_equal_in_memory_bit_for_bit(n):
    streamed, held = _flight(n, 0, 64, False), _flight(n, 0, 64, True)
    assert len(streamed) == len(held) == n
    for name in ("t_s", "p_true_W", "p_est_W", "p_sigma_W", "p_set_W", "yaw_est", "thrusts_N", "accel_B"):
        a, b = getattr(streamed, name), getattr(held, name)
        np.testing.assert_array_equal(a, b)
        assert a.shape[0] == n and not a.flags.writeable
    assert list(streamed.phase) == list(held.phase)
    chunks = list(streamed.tick_chunks("t_s", "p_est_W"))
    assert [c[0].shape[0] for c in chunks] == [64] * ((n - 1) // 64) + [n - 64 * ((n - 1) // 64)]
    np.testing.assert_array_equal(np.concatenate([c[1] for c in chunks]), held.p_est_W)
    with pytest.raises(AttributeError, match="no attribute 'p_truth'"):
        next(streamed.tick_chunks("p_truth"))


def _assert_same(got: dict, want: dict) -> None:
    assert got.keys() == want.keys()
    for k, v in want.items():
        if isinstance(v, float):
            assert got[k] == pytest.approx(v, rel=1e-12, abs=0.0), k
        else:
            assert got[k] == v, k


@pytest.mark.parametrize(("mission_t0", "init_time"), [(1.0, 0.1), (None, 0.1), (1.0, None), (99.0, 0.1)])
def test_chunked_metrics_equal_whole_array_formulas(mission_t0, init_time):
    log = _flight(1500, 1, 64, False)  # 24 chunks through the temporary file
    got, want = flight_metrics(log, mission_t0, init_time), _reference_metrics(log, mission_t0, init_time)
    _assert_same(got, want)
    if mission_t0 == 1.0:
        assert got["max_err_m"] == want["max_err_m"]  # maxima are exact
    if init_time is not None:
        assert 0.0 < got["ate_posyaw_m"] < 0.03  # the yaw and offset are aligned away, the noise remains


def test_chunked_blackout_and_lights_out_equal_whole_array_formulas():
    log = _flight(1500, 2, 64, False)
    for blackouts in [((0.0, 0.1),), ((1.0, 1.6), (3.0, 3.5), (50.0, 51.0)), ((0.26, 0.5),)]:
        _assert_same(blackout_metrics(log, blackouts), _reference_blackout(log, blackouts))
    assert blackout_metrics(log, ()) == {}
    for intervals in [
        ((1.0, 1.2),),
        ((0.5, 1.0), (1.4, 1.5)),
        ((5.0, 5.5),),
        ((0.1, 0.12),),
        ((1.0, 5.995),),
    ]:
        for back_m in (0.10, 0.12, 0.5, 10.0):
            _assert_same(
                lights_out_metrics(log, intervals, back_m), _reference_lights(log, intervals, back_m)
            )


def _step_error_flight(n: int, last_far_tick: int, chunk_rows: int = 64) -> FlightLog:
    """Truth 1 m from the setpoint up to ``last_far_tick``, on it afterwards."""
    log = FlightLog(chunk_rows=chunk_rows)
    for k in range(n):
        p = np.array([0.0, 0.0, 1.0])
        off = np.array([1.0 if k <= last_far_tick else 0.0, 0.0, 0.0])
        log.append_tick(
            0.004 * k, "mission", p_true_W=p + off, p_est_W=p, p_sigma_W=np.zeros(3), p_set_W=p, yaw_true=0.0,
            yaw_est=0.0, thrusts_N=np.zeros(4), gyro_B=np.zeros(3), accel_B=np.zeros(3),
        )  # fmt: skip
    return log


@pytest.mark.parametrize(("last_far_tick", "back_s"), [(127, 0.004 * 128 - 0.2), (128, 0.004 * 129 - 0.2)])
def test_lights_out_back_time_across_a_chunk_boundary(last_far_tick, back_s):
    # Tick 127 ends the second chunk: the tick after it, where the drone is back, opens the third.
    log = _step_error_flight(300, last_far_tick)
    got = lights_out_metrics(log, ((0.1, 0.2),), 0.5)
    assert got == {"lights_out_excursion_m": 1.0, "lights_out_back_s": pytest.approx(back_s, abs=1e-15)}
    assert got == _reference_lights(log, ((0.1, 0.2),), 0.5)
    never_back = _step_error_flight(300, 299)
    assert lights_out_metrics(never_back, ((0.1, 0.2),), 0.5)["lights_out_back_s"] is None
    assert lights_out_metrics(log, ((0.6, 0.7),), 0.5)["lights_out_back_s"] == 0.0  # back before the light


def test_logged_tick_equals_the_gauge_in_matrix_form():
    """The per-tick log's gauge in floats gives the matrix form's values to round-off.

    ``R_g p + t_g`` (estimate, setpoint), ``sqrt(diag(R_g C R_g^T))`` and ``yaw(R_g R_WB)``.
    """
    from types import SimpleNamespace

    from viotb.controllers.types import FlatOutput
    from viotb.envs.run.closed_loop import TruthState
    from viotb.envs.run.fly import _gauge, _gauge_floats, _log_tick
    from viotb.vio.lie import exp_so3, yaw_from_rotmat
    from viotb.vio.types import ImuSample, StateEstimate

    rng = np.random.default_rng(9)
    log, want = FlightLog(), []
    for k in range(50):
        R_est, R_true = exp_so3(rng.normal(size=3)), exp_so3(rng.normal(size=3))
        R_g, t_g = _gauge(R_est, rng.normal(size=3), R_true, rng.normal(size=3))
        A = rng.normal(size=(15, 15))
        cov = A @ A.T * 1e-3
        est = StateEstimate(t_s=0.1, R_WB=R_est, p_WB=rng.normal(size=3), v_WB=np.zeros(3), cov=cov)
        sp = FlatOutput(p_W=rng.normal(size=3))
        tr = TruthState(0.1, R_true, rng.normal(size=3), np.zeros(3), np.zeros(3))
        imu = ImuSample(0.1, rng.normal(size=3), rng.normal(size=3), False)
        loop = SimpleNamespace(last_imu=imu, t_s=0.004 * k)
        _log_tick(log, loop, "mission", est, sp, _gauge_floats(R_g, t_g), tr, rng.uniform(size=4))
        C = R_g @ est.cov_position_W_m2 @ R_g.T
        want.append(
            (R_g @ est.p_WB + t_g, np.sqrt(np.diag(C)), yaw_from_rotmat(R_g @ R_est), R_g @ sp.p_W + t_g)
        )
    p_est, p_sigma, yaw_est, p_set = (np.array([w[i] for w in want]) for i in range(4))
    np.testing.assert_allclose(log.p_est_W, p_est, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(log.p_sigma_W, p_sigma, rtol=1e-12)
    np.testing.assert_allclose(log.yaw_est, yaw_est, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(log.p_set_W, p_set, rtol=0.0, atol=1e-12)
    with pytest.raises(ValueError, match="p_est_W has 2 values, expected 3"):
        others = ("p_true_W", "p_sigma_W", "p_set_W", "yaw_true", "yaw_est", "thrusts_N", "gyro_B", "accel_B")
        log.append_tick(0.0, "mission", p_est_W=(1.0, 2.0), **dict.fromkeys(others, np.nan))
