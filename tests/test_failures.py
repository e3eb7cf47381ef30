"""Tests of envs/failures.py: each failure shows its symptom and the monitor names it; no false alarms."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from viotb.envs.run.failure_runner import along_track_velocity_stats, anchored_position_error_m, run_stream
from viotb.envs.scenarios.failures import FAILURES
from viotb.envs.scenarios.registry import fly_scenario_names, get_scenario
from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream
from viotb.envs.sim.faults import SensorFaults
from viotb.envs.tools.failure_report import failure_report
from viotb.vio.msckf import MsckfParams
from viotb.vio.types import StateEstimate, TrajectoryArrays


def test_registered_open_and_closed_loop():
    for name in FAILURES:
        assert get_scenario(name).kind == "record"
    assert "fly-fail-gyro-saturation" in fly_scenario_names()
    with pytest.raises(ValueError, match="severity"):
        FAILURES["fail-bad-init"].config(-1.0)


@pytest.mark.parametrize(
    ("name", "latest_s"),
    [
        ("fail-bad-init", 1.6),
        ("fail-no-excitation", 6.5),
        ("fail-feature-poverty", 2.0),
        ("fail-gyro-saturation", 4.0),
    ],
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


def _monte_carlo(fixed: dict, grid: dict, seeds: int, tmp_path) -> list[dict]:
    """Rows of a sweep (``viotb sweep``'s engine on a local Ray instance, 2 workers) of mode ``stream``."""
    from viotb.envs.tools.sweep import run_sweep

    spec = {
        "fixed": {"mode": "stream", "frontend": "sim", **fixed},
        "grid": grid,
        "seeds": list(range(seeds)),
    }
    result = run_sweep(spec, tmp_path / "sweep", workers=2)
    import pandas as pd

    rows = pd.read_parquet(result.results).to_dict("records")
    assert len(rows) == result.runs and all(r["status"] == "ok" for r in rows), rows
    return rows


@pytest.mark.slow
def test_no_false_alarm_on_nominal_hover_monte_carlo(tmp_path):
    """20 seeds of a 10 s hover stream through the sweep engine (the MSCKF told the stream's 0.5 px)."""
    fixed = {"scenario": "hover", "seconds": 10.0, "stream.landmark_count": 600, "msckf.pixel_sigma_px": 0.5}
    rows = _monte_carlo(fixed, {"estimator": ["msckf"]}, 20, tmp_path)
    assert all(json.loads(r["conditions"]) == [] for r in rows), [(r["seed"], r["conditions"]) for r in rows]


# Streams of 8 s of motion (after the 1.5 s still start) keep the default suite short.
SYNC_SECONDS = 8.0


@pytest.mark.parametrize(("name", "latest_s"), [("fail-time-offset", 5.0), ("fail-extrinsic", 6.5)])
def test_time_sync_or_extrinsic_is_named(name, latest_s):
    """Measured (seed 0): named at 3.75 s (10 ms offset) and 5.5 s (2 deg); motion starts at 1.5 s."""
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
def test_no_false_alarm_on_nominal_circle_and_figure8_monte_carlo(tmp_path):
    """20 seeds each of the 10 s circle and the nominal fast figure-8, through the sweep engine."""
    base = {"seconds": 10.0, "stream.landmark_count": 600, "msckf.pixel_sigma_px": 0.5}
    circle = _monte_carlo({"scenario": "circle", **base}, {"estimator": ["msckf"]}, 20, tmp_path / "c")
    f8 = _nominal_figure8()
    figure8 = _monte_carlo(
        {
            "scenario": "figure8",
            "seconds": f8.seconds,
            "stream.speed_scale": f8.speed_scale,
            "stream.faults.assumed_time_offset_s": f8.faults.assumed_time_offset_s,
            "msckf.pixel_sigma_px": 0.5,
        },
        {"estimator": ["msckf"]},
        20,
        tmp_path / "f",
    )
    for r in circle + figure8:
        assert json.loads(r["conditions"]) == [], (r["config/scenario"], r["seed"], r["conditions"])


def test_time_offset_error_grows_with_speed():
    """10 ms offset on the figure-8 at speed scales 0.5 / 1 / 2 (seed 0): the fast run's error is the largest.

    Measured ATE 0.034 / 0.069 / 0.156 m (MSCKF clones every <= 3 frames) and 0.028 / 0.022 / 0.145 m (every
    <= 6 frames): the growth from 0.5 to 1 is not robust, and beyond 2 the error drops again (0.030 m at
    2.5, 0.029 m at 3.0), so only "fastest > 2 x slowest and > middle" is asserted.
    """
    ate = []
    for speed in (0.5, 1.0, 2.0):
        cfg = StreamConfig(
            motion="figure8",
            seconds=SYNC_SECONDS,
            speed_scale=speed,
            time_offset_s=0.01,
            faults=SensorFaults(assumed_time_offset_s=0.0),
        )
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


# No excitation: each run is started in flight at the start of the line's cruise (3.5 s, 1.0 m/s) with its
# velocity -- the metric scale of a monocular VIO -- 10 % too large and an honest 10 % prior sigma, then flies
# either the constant-velocity line to 7.5 s or, as the fix, a figure-8 of the same length and a similar speed
# (mean 1.05 m/s, accelerations up to ~1.3 m/s^2).
EARLY_S, LATE_S = (3.5, 4.0), (6.5, 7.5)
CRUISE_END_S = 7.5


def _scale_symptoms(seeds) -> dict:
    """Scale symptoms of the line and of its fix over ``seeds``.

    Per run kind: RMS over seeds of the late scale error and of the position error at the cruise end, the
    mean early and late filter sigma of the scale, and the monitor's excitation flag times.
    """
    spec = FAILURES["fail-no-excitation"]
    cfg_fix, prm_fix = spec.fixed(1.0)
    runs = {"line": (spec.config(1.0), None), "fig8": (cfg_fix, prm_fix)}
    out = {}
    for name, (cfg, prm) in runs.items():
        rows, flags, nis, others = [], [], [], set()
        for seed in seeds:
            r = run_stream(synthesize_stream(replace(cfg, landmark_count=600), seed), prm)
            nis += [
                h.nis_per_dof
                for h, e in zip(r.run.health, r.run.estimates, strict=True)
                if e is not None and np.isfinite(h.nis_per_dof) and EARLY_S[0] <= e.t_s < CRUISE_END_S
            ]
            others |= {c.name for c in r.run.monitor.report()} - {"insufficient_excitation"}
            _, early_sig = along_track_velocity_stats(r, *EARLY_S, relative=True)
            late_err, late_sig = along_track_velocity_stats(r, *LATE_S, relative=True)
            s, e = anchored_position_error_m(r)
            t = np.array([x.t_s for x in r.run.estimates if x is not None])
            k = int(np.searchsorted(t, CRUISE_END_S)) - 1
            rows.append([late_err, early_sig, late_sig, e[k], s[k]])
            flags.append(r.run.monitor.first_time("insufficient_excitation"))
        a = np.array(rows)
        out[name] = {
            "late_err": float(np.sqrt(np.mean(a[:, 0] ** 2))),
            "early_sig": float(np.mean(a[:, 1])),
            "late_sig": float(np.mean(a[:, 2])),
            "pos_err_m": float(np.sqrt(np.mean(a[:, 3] ** 2))),
            "path_m": float(np.mean(a[:, 4])),
            "flags": flags,
            "nis": float(np.mean(nis)),
            "others": others,
        }
    return out


def _assert_scale_symptoms(st: dict, injected: float = 0.1) -> None:
    line, fig8 = st["line"], st["fig8"]
    # The constant-velocity cruise leaves the scale error uncorrected and knows it (sigma stays)...
    assert line["late_err"] > 0.8 * injected and line["late_sig"] > 0.7 * injected, st
    # ...while the excited run corrects it and its sigma shrinks.
    assert fig8["late_err"] < 0.4 * injected and fig8["late_sig"] < 0.4 * injected, st
    # The uncorrected scale shows as a position error growing with the distance flown (~4 m of cruise).
    assert line["pos_err_m"] > 0.5 * injected * line["path_m"], st
    assert line["pos_err_m"] > 5.0 * fig8["pos_err_m"], st
    # The monitor names it within 3 s of the cruise start and stays quiet on the excited run.
    assert all(t is not None and t <= 6.5 for t in line["flags"]), st
    assert all(t is None for t in fig8["flags"]), st
    # "The system looks healthy": consistent residuals (NIS per dof ~1) and no other condition.
    assert 0.8 < line["nis"] < 1.2 and not line["others"], st


def test_no_excitation_leaves_the_scale_error_uncorrected():
    """Seeds 0-4: the constant-velocity cruise does not correct a scale error, the figure-8 does.

    Measured (seed 0): scale error 9.9 % -> 15.2 % on the line (sigma 10.0 % -> 9.5 %), 12.1 % -> 4.3 % on
    the figure-8 (sigma 11.8 % -> 2.3 %); position error at the cruise end 0.64 m over 3.9 m of line vs
    0.02 m over 4.0 m of figure-8; flagged at 6.04 s.
    """
    _assert_scale_symptoms(_scale_symptoms(range(5)))


@pytest.mark.slow
def test_no_excitation_leaves_the_scale_error_uncorrected_monte_carlo():
    """20 seeds. The line's late error wanders (2.3 % to 18 % over seeds 0-12) instead of converging."""
    _assert_scale_symptoms(_scale_symptoms(range(20)))


def _fake_result(t_s, p_est, v_est, cov, p_gt, v_gt):
    """A duck-typed RunResult with hand-made estimates and truth (only the fields the helpers read)."""
    ests = [
        StateEstimate(float(t), np.eye(3), p, v, cov=cov) for t, p, v in zip(t_s, p_est, v_est, strict=True)
    ]
    truth = TrajectoryArrays(
        np.asarray(t_s), np.asarray(p_gt), np.tile([1.0, 0, 0, 0], (len(t_s), 1)), np.asarray(v_gt)
    )
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


def test_online_extrinsic_calibration_fixes_the_extrinsic_run():
    """Measured (seed 0, 8 s): ATE 0.106 m with the 2 deg error, 0.012 m with online calibration."""
    spec = FAILURES["fail-extrinsic"]
    cfg = replace(spec.config(1.0), seconds=SYNC_SECONDS)
    stream = synthesize_stream(cfg, 0)
    bad = run_stream(stream)
    _, prm = spec.fixed(1.0)
    good = run_stream(stream, prm)
    assert good.metrics["ate_m"] < 0.5 * bad.metrics["ate_m"], (bad.metrics, good.metrics)
    # The fixed run names the cause; the NIS symptom is gone.
    assert [c.name for c in good.run.monitor.report()] == ["extrinsic_miscalibrated"]


@pytest.mark.parametrize(
    ("name", "named", "latest_s"),
    [
        ("fail-time-offset", "time_offset_miscalibrated", 4.0),
        ("fail-extrinsic", "extrinsic_miscalibrated", 4.0),
    ],
)
def test_joint_online_calibration_tells_time_offset_from_extrinsic(name, named, latest_s):
    """Both calibrations on: only the wrong one moves, so the monitor names the cause and not the other.

    Measured (seed 0): the 10 ms offset is named at 2.5 s (+10.03 +- 0.97 ms), the 2 deg rotation at 2.65 s
    ((-1.54, 0.08, -1.40) deg at 5.0 sigma); the motion starts at 1.5 s. ATE 1.1 cm for both.
    """
    spec = FAILURES[name]
    cfg, prm = spec.fixed(1.0)
    r = run_stream(synthesize_stream(replace(cfg, seconds=SYNC_SECONDS), 0), prm)
    assert [c.name for c in r.run.monitor.report()] == [named], r.run.monitor.report()
    assert r.run.monitor.first_time(named) <= latest_s
    if name == "fail-time-offset":
        assert abs(r.metrics["time_offset_est_s"] - cfg.time_offset_s) < 1e-3, r.metrics


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_joint_online_calibration_no_false_alarm_on_nominal_figure8(seed):
    _, prm = FAILURES["fail-time-offset"].fixed(1.0)
    r = run_stream(synthesize_stream(_nominal_figure8(), seed), prm)
    assert r.run.monitor.report() == []


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3, 20))
def test_joint_online_calibration_no_false_alarm_monte_carlo(seed):
    _, prm = FAILURES["fail-time-offset"].fixed(1.0)
    for cfg in (StreamConfig(motion="circle", seconds=10.0, landmark_count=600), _nominal_figure8()):
        r = run_stream(synthesize_stream(cfg, seed), prm)
        assert r.run.monitor.report() == [], (cfg.motion, seed)


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


def test_confident_wrong_start_is_named_divergence():
    """A start 3 deg tilted with a 20 % scale error and a confident prior (0.2 deg, 1 %) never recovers.

    The lesson: "a bad init is unrecoverable for a local estimator". The filter keeps ~100 tracks but
    cannot use one (they fail triangulation) and drifts on the IMU. Measured (seed 0, hover): named
    ``divergence`` at 8.45 s (started at 3.5 s), 24 m from the truth at the end; before the monitor's
    unused-features test nothing was raised.
    """
    from viotb.vio.lie import exp_so3

    cfg = StreamConfig(
        motion="hover", seconds=8.0, landmark_count=600, start_in_flight_s=3.5, initial_scale_error=0.2
    )
    stream = synthesize_stream(cfg, 0)
    init = stream.external_init
    speed = max(float(np.linalg.norm(init.v_WB)), 0.2)
    confident = np.repeat([np.deg2rad(0.2) ** 2, 1e-6, (0.01 * speed) ** 2, 1e-6, 0.02**2], 3)
    stream.external_init = replace(
        init, R_WB=exp_so3(np.array([np.deg2rad(3.0), 0.0, 0.0])) @ init.R_WB, cov_diag=confident
    )
    r = run_stream(stream)
    t = r.run.monitor.first_time("divergence")
    assert t is not None and t < 9.5, r.run.monitor.report()
    assert r.metrics["final_err_m"] > 1.0, r.metrics


def test_closed_loop_and_recorded_failures_follow_the_severity(tmp_path):
    from viotb.envs.data.euroc import read_euroc
    from viotb.envs.data.record import record_scenario
    from viotb.envs.scenarios.failures import failure_fly_scenario, failure_record_scenario
    from viotb.vio.lie import log_so3

    off = failure_fly_scenario("fly-fail-time-offset", 2.0).rig
    assert off.camera.time_offset_s == pytest.approx(0.02) and off.faults.assumed_time_offset_s == 0.0
    blank = failure_fly_scenario("fly-fail-feature-poverty", 2.0).rig.camera
    assert blank.blackout_intervals_s == ((10.0, 16.0),)
    assert failure_fly_scenario("fly-fail-extrinsic", 0.0).rig.faults.extrinsic_error_rad == 0.0
    with pytest.raises(ValueError, match="no severity knob"):
        failure_fly_scenario("fly-fail-long-loop", 2.0)
    assert failure_record_scenario("fail-bad-init", 2.0).faults.extra_gyro_bias_rad_s == pytest.approx(0.6)
    # The recorded calibration file carries twice the default rotation error.
    told = read_euroc(record_scenario("fail-extrinsic", tmp_path, seconds=0.5, severity=2.0)["out"]).calib
    default = read_euroc(record_scenario("fail-extrinsic", tmp_path / "d", seconds=0.5)["out"]).calib
    # Both errors are about the same axis, so the two told rotations differ by the default 2 deg.
    assert np.rad2deg(np.linalg.norm(log_so3(default.R_BC.T @ told.R_BC))) == pytest.approx(2.0, abs=1e-9)
