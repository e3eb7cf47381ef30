"""Tests of envs/failures.py: each failure shows its symptom and the monitor names it; no false alarms."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from viotb.envs.failures import (
    FAILURES,
    StreamConfig,
    along_track_velocity_stats,
    anchored_position_error_m,
    failure_report,
    run_stream,
    synthesize_stream,
)
from viotb.envs.fly import FLY_SCENARIOS
from viotb.envs.scenarios import get_scenario
from viotb.vio.msckf import MsckfParams
from viotb.vio.types import StateEstimate, TrajectoryArrays


def test_registered_open_and_closed_loop():
    for name in FAILURES:
        assert get_scenario(name).kind == "record"
    assert "fly-fail-gyro-saturation" in FLY_SCENARIOS
    with pytest.raises(ValueError, match="severity"):
        FAILURES["fail-bad-init"].config(-1.0)


@pytest.mark.parametrize(
    ("name", "latest_s"),
    [("fail-bad-init", 1.6), ("fail-no-excitation", 4.0), ("fail-feature-poverty", 2.0),
     ("fail-gyro-saturation", 4.0)],
)
def test_monitor_names_the_failure(name, latest_s):
    spec = FAILURES[name]
    r = run_stream(synthesize_stream(spec.config(1.0), seed=0))
    t = r.run.monitor.first_time(spec.condition)
    assert t is not None and t <= latest_s, r.run.monitor.report()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_false_alarm_on_nominal_hover(seed):
    r = run_stream(synthesize_stream(StreamConfig(motion="hover", seconds=6.0, landmark_count=600), seed))
    assert r.run.monitor.report() == []
    assert r.metrics["init_time_s"] is not None


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(20))
def test_no_false_alarm_on_nominal_hover_monte_carlo(seed):
    r = run_stream(synthesize_stream(StreamConfig(motion="hover", seconds=10.0, landmark_count=600), seed))
    assert r.run.monitor.report() == []


# Streams of 8 s of motion (after the 1.5 s still start) keep the default suite short.
SYNC_SECONDS = 8.0


@pytest.mark.parametrize(("name", "latest_s"), [("fail-time-offset", 5.0), ("fail-extrinsic", 6.5)])
def test_time_sync_or_extrinsic_is_named(name, latest_s):
    """Measured (seed 0): named at 3.65 s (10 ms offset) and 5.05 s (2 deg); motion starts at 1.5 s."""
    spec = FAILURES[name]
    r = run_stream(synthesize_stream(replace(spec.config(1.0), seconds=SYNC_SECONDS), seed=0))
    t = r.run.monitor.first_time("time_sync_or_extrinsic_suspected")
    assert t is not None and t <= latest_s, r.run.monitor.report()


def _nominal_figure8() -> StreamConfig:
    """The failing figure-8 (same speed) without the offset or the extrinsic error."""
    return replace(FAILURES["fail-time-offset"].config(1.0), seconds=SYNC_SECONDS, time_offset_s=0.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_false_alarm_on_nominal_circle(seed):
    r = run_stream(synthesize_stream(StreamConfig(motion="circle", seconds=6.0, landmark_count=600), seed))
    assert r.run.monitor.report() == []


def test_no_false_alarm_on_nominal_figure8():
    r = run_stream(synthesize_stream(_nominal_figure8(), 0))
    assert r.run.monitor.report() == []


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(20))
def test_no_false_alarm_on_nominal_circle_and_figure8_monte_carlo(seed):
    for cfg in (StreamConfig(motion="circle", seconds=10.0, landmark_count=600), _nominal_figure8()):
        r = run_stream(synthesize_stream(cfg, seed))
        assert r.run.monitor.report() == [], (cfg.motion, seed)


def test_time_offset_error_grows_with_speed():
    """10 ms offset on the figure-8 at speed scales 0.5 / 1 / 2 (seed 0): the fast run's error is the largest.

    Measured ATE 0.034 / 0.069 / 0.156 m (MSCKF clones every <= 3 frames) and 0.028 / 0.022 / 0.145 m (every
    <= 6 frames): the growth from 0.5 to 1 is not robust, and beyond 2 the error drops again (0.030 m at
    2.5, 0.029 m at 3.0), so only "fastest > 2 x slowest and > middle" is asserted.
    """
    ate = []
    for speed in (0.5, 1.0, 2.0):
        cfg = StreamConfig(motion="figure8", seconds=SYNC_SECONDS, speed_scale=speed, time_offset_s=0.01)
        ate.append(run_stream(synthesize_stream(cfg, 0)).metrics["ate_m"])
    assert ate[2] > 2.0 * ate[0] and ate[2] > ate[1], ate


def test_time_offset_calibration_converges_within_1ms():
    cfg = FAILURES["fail-time-offset"].config(1.0)
    prm = MsckfParams(frontend="sim", estimate_time_offset=True, time_offset_sigma_s=0.02)
    r = run_stream(synthesize_stream(cfg, seed=0), prm)
    assert abs(r.metrics["time_offset_est_s"] - cfg.time_offset_s) < 1e-3, r.metrics


def test_failure_report_writes_plot(tmp_path):
    rep = failure_report("fail-feature-poverty", tmp_path, seed=0, severity=1.0)
    assert rep["detected"] is True and (tmp_path / "fail-feature-poverty_error.png").is_file()
    # Coasting through a short gap with full texture afterwards beats the poor scene.
    assert rep["fixed"]["ate_m"] < rep["failing"]["ate_m"]


# Constant-velocity line (8 s: 2 s ramps, cruise at 1.0 m/s from 3.5 s to 7.5 s of stream time) against an
# excited figure-8 of the same length and a similar speed (mean 1.05 m/s, accelerations up to ~1.3 m/s^2).
EARLY_S, LATE_S = (3.5, 4.5), (6.5, 7.5)


def _excitation_pair(seed: int) -> tuple:
    line = run_stream(synthesize_stream(
        replace(FAILURES["fail-no-excitation"].config(1.0), landmark_count=600), seed))
    fig8 = run_stream(synthesize_stream(
        StreamConfig(motion="figure8", seconds=8.0, speed_scale=1.0, landmark_count=600), seed))
    return line, fig8


def _excitation_stats(seeds) -> dict:
    """Along-track velocity error (RMS over seeds) and mean filter sigma (m/s), per run and window."""
    acc = {k: [] for k in ("line", "fig8")}
    for seed in seeds:
        for name, r in zip(("line", "fig8"), _excitation_pair(seed), strict=True):
            acc[name].append([*along_track_velocity_stats(r, *EARLY_S),
                              *along_track_velocity_stats(r, *LATE_S)])
            if name == "line":
                assert r.run.monitor.first_time("insufficient_excitation") is not None, seed
    out = {}
    for name, rows in acc.items():
        a = np.array(rows)  # columns: early err, early sigma, late err, late sigma
        out[name] = {"early_err": float(np.sqrt(np.mean(a[:, 0] ** 2))), "early_sig": float(np.mean(a[:, 1])),
                     "late_err": float(np.sqrt(np.mean(a[:, 2] ** 2))), "late_sig": float(np.mean(a[:, 3]))}
    return out


def _fake_result(t_s, p_est, v_est, cov, p_gt, v_gt):
    """A duck-typed RunResult with hand-made estimates and truth (only the fields the helpers read)."""
    ests = [StateEstimate(float(t), np.eye(3), p, v, cov=cov)
            for t, p, v in zip(t_s, p_est, v_est, strict=True)]
    truth = TrajectoryArrays(np.asarray(t_s), np.asarray(p_gt), np.tile([1.0, 0, 0, 0], (len(t_s), 1)),
                             np.asarray(v_gt))
    return SimpleNamespace(run=SimpleNamespace(estimates=[None, *ests]), stream=SimpleNamespace(truth=truth))


def test_along_track_and_anchored_error_helpers_closed_form():
    t = np.linspace(0.0, 2.0, 21)
    v_gt = np.tile([0.0, 2.0, 0.0], (21, 1))  # 2 m/s along +y
    p_gt = np.outer(t, [0.0, 2.0, 0.0]) + [5.0, 1.0, 0.0]
    cov = np.diag([0.0] * 6 + [9.0, 0.04, 9.0] + [0.0] * 6)  # sigma 0.2 m/s along y, 3 across
    # Estimate: 10 % too fast along track plus an across-track error that must not count; its own origin.
    v_est = np.tile([0.5, 2.2, 0.0], (21, 1))
    p_est = np.outer(t, [0.5, 2.2, 0.0])
    r = _fake_result(t, p_est, v_est, cov, p_gt, v_gt)
    err, sig = along_track_velocity_stats(r, 0.5, 1.5)
    assert abs(err - 0.2) < 1e-12 and abs(sig - 0.2) < 1e-12
    s, e = anchored_position_error_m(r)
    np.testing.assert_allclose(s, 2.0 * t, atol=1e-12)  # true path length
    np.testing.assert_allclose(e, np.hypot(0.5, 0.2) * t, atol=1e-12)  # no offset or alignment absorbed
    with pytest.raises(ValueError, match="no moving estimate"):
        along_track_velocity_stats(r, 5.0, 6.0)


@pytest.fixture(scope="module")
def no_excitation_runs():
    spec = FAILURES["fail-no-excitation"]
    bad = run_stream(synthesize_stream(replace(spec.config(1.0), landmark_count=600), 0))
    cfg_fix, prm = spec.fixed(1.0)
    good = run_stream(synthesize_stream(replace(cfg_fix, landmark_count=600), 0), prm)
    return bad, good


def test_no_excitation_is_flagged_and_excited_run_is_not(no_excitation_runs):
    bad, good = no_excitation_runs
    assert bad.run.monitor.first_time("insufficient_excitation") is not None
    assert good.run.monitor.first_time("insufficient_excitation") is None


@pytest.mark.slow
@pytest.mark.xfail(
    strict=False,
    reason="not reproduced over 20 seeds: along-track velocity error (RMS, m/s x 100) / filter sigma, "
    "first -> last second of the cruise: line 3.53 / 3.72 -> 2.61 / 2.12, figure-8 2.53 / 2.69 -> 2.04 / "
    "1.59. The cruise error shrinks instead of growing, ends only 1.28x the excited run's, and is 1.23 "
    "sigma vs the figure-8's 1.28 (seeds 0-4 alone, 3.86 vs 1.57 and 1.8 vs 1.0 sigma, would have passed "
    "by chance)",
)
def test_no_excitation_scale_wanders_monte_carlo():
    """Constant velocity leaves the scale uncorrected while excitation corrects it (20 seeds).

    The lesson: "with no acceleration, scale is unobservable and the estimate of it wanders ... the system
    looks healthy". With a monocular camera the scale lives in the velocity, so the statistic is the error of
    the velocity along the direction of travel (scale error x speed, :func:`along_track_velocity_stats`) in
    the first and the last second of the 4 s cruise, against the same windows of an excited figure-8 of the
    same length and a similar speed, with the filter's own sigma of it. The claim implies (1) the cruise does
    not reduce the error while the excited run does, so it ends well above the excited run's, and (2) the
    filter does not see it (its sigma has no information to shrink on, so a shrinking sigma means an error
    beyond sigma).

    Why it fails here (see the xfail numbers): an EKF carries the scale learnt in the 2 s acceleration ramp in
    its velocity, and at constant velocity the IMU (ADIS16448 noise) holds that velocity to well under
    1 cm/s over 4 s; the 6 m room does not allow a longer cruise (a 16 s line at 0.43 m/s: the relative
    along-track error went 9.6 % -> 4.1 % over 8 seeds). The filter's sigma shrinks by ~43 % on both runs.
    The old single-seed statistic (sim(3) scale error of the two halves) went 1.26 % -> 1.02 % on seed 0.
    """
    st = _excitation_stats(range(20))
    line, fig8 = st["line"], st["fig8"]
    assert line["late_err"] >= line["early_err"], st  # the cruise does not correct the scale...
    assert fig8["late_err"] < fig8["early_err"], st  # ...the excitation does
    assert line["late_err"] > 1.5 * fig8["late_err"], st
    assert line["late_err"] > 1.3 * line["late_sig"] and fig8["late_err"] < 1.3 * fig8["late_sig"], st


def test_online_extrinsic_calibration_fixes_the_extrinsic_run():
    """Measured (seed 0, 8 s): ATE 0.106 m with the 2 deg error, 0.012 m with online calibration."""
    spec = FAILURES["fail-extrinsic"]
    cfg = replace(spec.config(1.0), seconds=SYNC_SECONDS)
    stream = synthesize_stream(cfg, 0)
    bad = run_stream(stream)
    _, prm = spec.fixed(1.0)
    good = run_stream(stream, prm)
    assert good.metrics["ate_m"] < 0.5 * bad.metrics["ate_m"], (bad.metrics, good.metrics)
    assert good.run.monitor.report() == []


@pytest.mark.slow
def test_long_loop_raises_nothing_spurious():
    """30 s of the long loop (loop closure is out of scope). Measured: no condition, final error 0.026 m."""
    r = run_stream(synthesize_stream(StreamConfig(motion="long-loop", seconds=30.0, landmark_count=600), 0))
    assert r.run.monitor.report() == []
    assert not r.metrics["diverged"]


@pytest.mark.slow
def test_long_loop_drift_is_not_corrected_at_the_return():
    """Steady drift -> odometry: 3 laps (53.6 m) back to the start pose, 5 seeds, no alignment.

    The error is the displacement since initialization against the truth (``anchored_position_error_m``),
    read at equal path-length checkpoints (1/3, 2/3 and all of the path: the ends of laps 1, 2 and 3, all at
    the start pose). Without loop closure returning to a known place corrects nothing: the estimate does not
    come back to its own start and the error at the returns grows with distance on average.

    Measured (cm) at 1/3 / 2/3 / end, seeds 0-4: 1.3/2.7/5.2, 3.9/3.5/4.0, 2.8/4.4/6.5, 1.3/3.4/5.3,
    4.1/3.6/5.8; means 2.7 / 3.5 / 5.4 (per seed not always monotonic: seeds 1 and 4 dip at 2/3).
    """
    at = []
    cfg = StreamConfig(motion="long-loop", seconds=30.0, landmark_count=600)
    for seed in range(5):
        r = run_stream(synthesize_stream(cfg, seed))
        s, err = anchored_position_error_m(r)
        truth_gap = np.linalg.norm(r.stream.truth.p_WB[-1] - r.stream.truth.p_WB[0])
        assert truth_gap < 1e-6, truth_gap  # the loop really ends where it started
        at.append([err[np.argmin(np.abs(s - f * s[-1]))] for f in (1.0 / 3.0, 2.0 / 3.0, 1.0)])
        assert at[-1][2] > 0.02, (seed, at[-1])  # the final return is not snapped back (> 2 cm)
    mean = np.mean(at, axis=0)
    assert mean[0] < mean[1] < mean[2], at
    assert mean[2] > 1.5 * mean[0], at
