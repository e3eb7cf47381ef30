"""The flight log's columns (envs/run/flight_log.py): values kept exactly, growth, phases, read-only views."""

import numpy as np
import pytest
from viotb.envs.run.flight_log import FlightLog


def _tick(rng: np.random.Generator) -> dict:
    return {
        "p_true_W": rng.normal(size=3),
        "p_est_W": rng.normal(size=3),
        "p_sigma_W": rng.uniform(size=3),
        "p_set_W": rng.normal(size=3),
        "yaw_true": float(rng.normal()),
        "yaw_est": float(rng.normal()),
        "thrusts_N": rng.uniform(size=4),
        "gyro_B": rng.normal(size=3),
        "accel_B": rng.normal(size=3),
    }


def test_columns_hold_every_tick_exactly_across_chunks():
    rng = np.random.default_rng(0)
    log, ticks, phases = FlightLog(), [], []
    n = 9000  # three chunks of rows
    for k in range(n):
        tick = _tick(rng)
        phase = ("ground", "takeoff", "mission")[min(k // 3000, 2)]
        log.append_tick(0.004 * k, phase, **tick)
        ticks.append(tick)
        phases.append(phase)
    assert len(log) == n
    np.testing.assert_array_equal(log.t_s, 0.004 * np.arange(n))
    for name in ticks[0]:
        np.testing.assert_array_equal(getattr(log, name), np.array([t[name] for t in ticks]))
    assert log.p_true_W.shape == (n, 3) and log.thrusts_N.shape == (n, 4) and log.yaw_est.shape == (n,)
    assert list(log.phase) == phases
    with pytest.raises(ValueError):
        log.p_est_W[0, 0] = 1.0  # views are read-only


def test_nan_placeholders_frames_and_unknown_names():
    log = FlightLog()
    nan = np.nan
    log.append_tick(
        0.0, "ground", p_true_W=np.zeros(3), p_est_W=nan, p_sigma_W=nan, p_set_W=nan, yaw_true=0.0,
        yaw_est=nan, thrusts_N=np.zeros(4), gyro_B=nan, accel_B=nan,
    )  # fmt: skip
    assert np.isnan(log.p_est_W).all() and log.p_est_W.shape == (1, 3)
    for k in range(100):
        log.append_frame(0.05 * k, 40 + k, ("zupt",) if k % 2 else ())
    np.testing.assert_array_equal(log.frame_features, 40 + np.arange(100))
    assert log.frame_t_s[-1] == pytest.approx(4.95) and log.frame_conditions[1] == ("zupt",)
    with pytest.raises(AttributeError, match="no attribute 'p_truth'"):
        _ = log.p_truth


def test_append_row_equals_append_tick_and_checks_its_length():
    rng = np.random.default_rng(3)
    by_tick, by_row = FlightLog(chunk_rows=16), FlightLog(chunk_rows=16)
    names = (
        "p_true_W",
        "p_est_W",
        "p_sigma_W",
        "p_set_W",
        "yaw_true",
        "yaw_est",
        "thrusts_N",
        "gyro_B",
        "accel_B",
    )
    for k in range(40):
        tick = _tick(rng)
        phase = "takeoff" if k < 20 else "mission"
        by_tick.append_tick(0.004 * k, phase, **tick)
        row = [0.004 * k]
        for name in names:
            row += np.atleast_1d(tick[name]).tolist()
        by_row.append_row(phase, row)
    for name in ("t_s", *names):
        np.testing.assert_array_equal(getattr(by_row, name), getattr(by_tick, name))
    assert list(by_row.phase) == list(by_tick.phase)
    with pytest.raises(ValueError, match="24 values, expected 25"):
        by_row.append_row("mission", [0.0] * 24)


@pytest.mark.parametrize("in_memory", [False, True])
def test_deferred_cells_are_filled_before_reads_and_before_their_chunk_leaves_memory(in_memory):
    rng = np.random.default_rng(2)
    log, rows, calls = FlightLog(in_memory=in_memory, chunk_rows=4), [], []
    for k in range(11):
        row = rng.normal(size=25).tolist()
        sigma = rng.uniform(size=3).tolist()
        rows.append(row[:7] + sigma + row[10:])
        if k % 3 == 0:
            log.append_row("mission", rows[-1])
        else:  # the sigma cells come later, from a callable
            later = ("p_sigma_W", lambda s=sigma: calls.append(1) or s)
            log.append_row("mission", row[:7] + [np.nan] * 3 + row[10:], later)
        if k == 5:
            log.resolve_deferred()  # what the flight runner does at each frame
    # Deferred rows 1, 2, 4, 5, 7, 8, 10: rows 1-2 filled when chunk 0 left memory (before row 4), 4-5 by the
    # explicit call, 7 before row 8; 8 and 10 still wait.
    assert len(calls) == 5
    want = np.array(rows)[:, 7:10]
    np.testing.assert_array_equal(log.p_sigma_W, want)  # a read fills the pending ones first
    assert len(calls) == 7
    np.testing.assert_array_equal(np.concatenate([c[0] for c in log.tick_chunks("p_sigma_W")]), want)
    assert len(calls) == 7  # each callable ran once
