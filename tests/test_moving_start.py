"""Moving starts (issue #13): recordings and streams begun mid-trajectory, and initialization on them."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from dataclasses import replace

import numpy as np
import pytest
from viotb.envs.data.euroc import read_euroc
from viotb.envs.data.record import default_start_in_motion_s, record_scenario
from viotb.envs.run.init_check import check_initialization, moving_start_monte_carlo
from viotb.envs.scenarios.motions import TRAJECTORY_FACTORIES, MotionParams, StillStart, TimeShifted
from viotb.envs.scenarios.registry import get_scenario
from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream
from viotb.vio.initialization import InitParams
from viotb.vio.lie import quat_wxyz_to_rotmat


def test_time_shifted_trajectory_is_the_tail_of_the_original():
    inner = StillStart(TRAJECTORY_FACTORIES["figure8"](MotionParams(10.0)), 1.5)
    shifted = TimeShifted(inner, 3.2)
    assert shifted.duration_s == pytest.approx(inner.duration_s - 3.2)
    t = np.array([0.0, 0.37, 2.0])
    a, b = shifted.sample_many(t), inner.sample_many(t + 3.2)
    np.testing.assert_array_equal(a.t_s, t)
    for name in ("p_WB", "v_WB", "a_WB", "R_WB", "omega_B"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    one = shifted.sample(0.37)
    assert one.t_s == 0.37
    np.testing.assert_allclose(one.p_WB, inner.sample(0.37 + 3.2).p_WB, atol=1e-12)
    with pytest.raises(ValueError, match="start_s"):
        TimeShifted(inner, inner.duration_s + 1.0)


def test_stream_start_at_drops_the_head_and_keeps_the_motion():
    cfg = StreamConfig(motion="circle", seconds=4.0, landmark_count=200)
    full = synthesize_stream(cfg, seed=0)
    moving = synthesize_stream(replace(cfg, start_at_s=2.5), seed=0)
    # Same motion, entered 2.5 s in: the truth at t is the full stream's at t + 2.5 s.
    k = int(round(2.5 * 200))
    np.testing.assert_allclose(moving.truth.p_WB[:100], full.truth.p_WB[k : k + 100], atol=1e-12)
    assert moving.truth.t_s[0] == 0.0 and moving.truth.t_s[-1] == pytest.approx(5.5 - 2.5)
    assert np.linalg.norm(moving.truth.v_WB[0]) > 0.5  # moving at the first sample
    with pytest.raises(ValueError, match="start_at_s"):
        synthesize_stream(replace(cfg, start_at_s=6.0))


def test_record_start_in_motion_writes_truth_from_the_moving_start(tmp_path):
    sc = get_scenario("circle")
    start = default_start_in_motion_s(sc)
    res = record_scenario(
        "circle", tmp_path / "rec", seed=0, seconds=0.5, resolution=(64, 48), start_at_s=start
    )
    assert res["start_at_s"] == start and res["start_speed_m_s"] > 0.3
    ds = read_euroc(res["out"])
    truth = TimeShifted(sc.make_trajectory(start + 0.5), start)
    s0 = truth.sample(0.0)
    gt = ds.groundtruth
    np.testing.assert_allclose(gt.p_WB[0], s0.p_WB, atol=1e-6)
    np.testing.assert_allclose(quat_wxyz_to_rotmat(gt.quat_wxyz_WB[0]), s0.R_WB, atol=1e-6)
    np.testing.assert_allclose(gt.v_WB[0], s0.v_WB, atol=1e-6)
    # A start where the vehicle is still at rest is refused, naming the value.
    with pytest.raises(ValueError, match="start_at_s=0.5"):
        record_scenario("circle", tmp_path / "rest", seconds=0.5, resolution=(64, 48), start_at_s=0.5)


@pytest.fixture(scope="module")
def aggressive_start():
    """The MSCKF's first estimate on the aggressive motion entered 4 s in (no rest, sim front end)."""
    cfg = StreamConfig(motion="aggressive", seconds=8.0, landmark_count=600, start_at_s=4.0)
    return check_initialization(synthesize_stream(cfg, seed=0), "msckf")


def test_moving_start_initializes_dynamically_against_truth(aggressive_start):
    """The MSCKF on a moving start: a dynamic initialization with the scale and velocity right.

    It starts 1.8 s after the first image (on all 20 seeds of the benchmark), when the reported scale sigma
    first drops below 0.67 %; the scale error is within 3 of its sigmas (the sigma is honest: over 20
    seeds the largest ratio is 1.54, the RMS 0.69).
    """
    check = aggressive_start
    assert check.method == "dynamic" and check.delay_s < 2.0
    assert abs(check.scale_error) < 0.02
    assert 0.0 < check.scale_sigma <= InitParams().max_scale_sigma
    assert abs(check.scale_error) <= 3.0 * check.scale_sigma
    assert check.velocity_error_m_s < 0.05 * check.speed_m_s + 0.02
    assert 0 < check.dynamic_tries <= 20  # a try every second frame from 0.5 s on


def test_moving_start_gravity_direction_within_2_deg(aggressive_start):
    """The gravity direction of that start: 0.36 deg here, up to 1.4 deg over 20 seeds (2.1 before)."""
    assert aggressive_start.tilt_error_deg < 2.0


def test_constant_velocity_start_refuses_to_initialize():
    """Entered mid-cruise of the constant-velocity line (no rest): the scale is unobservable, so no state."""
    cfg = StreamConfig(motion="line", seconds=10.0, landmark_count=600, start_at_s=5.0)
    stream = synthesize_stream(cfg, seed=0)
    assert np.ptp(np.linalg.norm(stream.truth.v_WB[:400], axis=1)) < 1e-6  # cruise at constant speed
    check = check_initialization(stream, "msckf", max_delay_s=1.0)
    assert check.t_init_s is None and check.method == ""


@pytest.fixture(scope="module")
def monte_carlo_20():
    """Every moving start (``MOVING_STARTS``) over 20 seeds, sim front end (~10 CPU-minutes)."""
    return moving_start_monte_carlo(list(range(20)))


@pytest.mark.slow
def test_moving_start_monte_carlo_never_initializes_wrong(monte_carlo_20):
    """Over 20 seeds: every initialization that happens has its scale within 2 % (no wrong start)."""
    wrong = [r for r in monte_carlo_20 if r["t_init_s"] is not None and not abs(r["scale_error"]) <= 0.02]
    assert not wrong, wrong


@pytest.mark.slow
def test_moving_start_monte_carlo_scale_sigma_is_honest(monte_carlo_20):
    """Over 20 seeds the scale errors at initialization stay within 3.5 of their reported sigmas."""
    ok = [r for r in monte_carlo_20 if r["t_init_s"] is not None and np.isfinite(r["scale_error"])]
    ratios = [abs(r["scale_error"]) / r["scale_sigma"] for r in ok]
    assert ok and max(ratios) <= 3.5, ratios


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="open (issue #13): no start initializes within 1.5 s (see the report)")
def test_moving_start_monte_carlo_initializes_within_1_5_s(monte_carlo_20):
    """The issue's target: initialized within 1.5 s of the first image on every moving start."""
    late = [r for r in monte_carlo_20 if not r["delay_s"] <= 1.5]
    assert not late, late


@pytest.mark.slow
def test_aggressive_start_forced_at_1_5_s_has_an_honest_sigma_above_the_gate(monkeypatch):
    """Why 1.5 s is not reached: accepted at the first try after 1.5 s (1.6 s), 20 seeds.

    The reported scale sigma is ~1 % there (above the 0.67 % gate: a 2 % bound would hold at 2 sigma
    only) and honest: error / sigma RMS 1.02, largest 2.5, errors up to 2.6 % (measured).
    """
    import viotb.vio.msckf as msckf

    forced = InitParams(min_dynamic_window_s=1.49, max_scale_sigma=1.0, max_tilt_sigma_rad=1.0)
    monkeypatch.setattr(msckf, "InitParams", lambda: forced)
    rows = moving_start_monte_carlo(list(range(20)), (("aggressive", 4.0),), max_delay_s=2.0)
    assert all(r["t_init_s"] is not None and 1.5 <= r["delay_s"] <= 1.65 for r in rows)
    sigma = np.array([r["scale_sigma"] for r in rows])
    z = np.array([r["scale_error"] for r in rows]) / sigma
    assert np.all(sigma > InitParams().max_scale_sigma)
    assert 0.7 <= np.sqrt(np.mean(z**2)) <= 1.4 and np.max(np.abs(z)) <= 3.5, z


def test_cli_record_start_in_motion(tmp_path):
    from typer.testing import CliRunner
    from viotb.envs.tools.cli import app

    runner = CliRunner()
    args = ["record", "circle", "--seconds", "0.3", "--resolution", "64x48", "--json"]
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "a"), "--start-in-motion"])
    assert res.exit_code == 0, res.output
    assert '"start_at_s": 3.5' in res.output  # the default: 2 s after the 1.5 s still start
    bad = runner.invoke(app, [*args, "--out", str(tmp_path / "b"), "--start-at-s", "3"])
    assert bad.exit_code != 0 and "--start-in-motion" in bad.output
