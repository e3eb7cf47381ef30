"""Tests for viotb.controllers.setpoints: analytic derivatives vs finite differences, rest at the ends."""

from __future__ import annotations

import math

import numpy as np
import pytest
from viotb.controllers.profiles import min_jerk_profile
from viotb.controllers.setpoints import (
    ExcitationManeuver,
    FigureEight,
    HoverPoint,
    Sequence,
    Setpoint,
    StraightLine,
    Takeoff,
    Waypoints,
)

_H_S = 1e-5
"""Central-difference step (s)."""
_FD_ATOL = 1e-6
"""Central differences of smooth signals with O(1-10) derivatives: truncation ~h^2, rounding ~1e-16 / h."""


def _check_derivatives(sp: Setpoint, times_s: np.ndarray) -> None:
    for t in times_s:
        lo, mid, hi = sp.sample(t - _H_S), sp.sample(t), sp.sample(t + _H_S)
        np.testing.assert_allclose(mid.v_W, (hi.p_W - lo.p_W) / (2 * _H_S), atol=_FD_ATOL)
        np.testing.assert_allclose(mid.a_W, (hi.v_W - lo.v_W) / (2 * _H_S), atol=_FD_ATOL)
        np.testing.assert_allclose(mid.j_W, (hi.a_W - lo.a_W) / (2 * _H_S), atol=10 * _FD_ATOL)
        assert mid.yaw_rate_rad_s == pytest.approx((hi.yaw_rad - lo.yaw_rad) / (2 * _H_S), abs=_FD_ATOL)


def _assert_at_rest(sp: Setpoint, t_s: float) -> None:
    out = sp.sample(t_s)
    np.testing.assert_allclose(np.concatenate([out.v_W, out.a_W, [out.yaw_rate_rad_s]]), 0.0, atol=1e-12)


def test_min_jerk_profile_closed_form() -> None:
    assert min_jerk_profile(0.0)[:3] == (0.0, 0.0, 0.0)
    assert min_jerk_profile(1.0)[:3] == (1.0, 0.0, 0.0)
    s, ds, d2s, d3s = min_jerk_profile(0.5)
    assert s == pytest.approx(0.5, abs=1e-15)
    assert ds == pytest.approx(1.875, abs=1e-15)  # peak speed of minimum jerk: 15/8 of the average
    assert d2s == pytest.approx(0.0, abs=1e-15)
    assert d3s == pytest.approx(-30.0, abs=1e-12)


def test_hover_point_is_at_rest() -> None:
    sp = HoverPoint(p_W=[1.0, 2.0, 3.0], yaw_rad=0.3)
    out = sp.sample(12.3)
    np.testing.assert_allclose(out.p_W, [1.0, 2.0, 3.0], atol=0)
    assert out.yaw_rad == 0.3
    _assert_at_rest(sp, 5.0)
    assert sp.duration_s == np.inf


def test_waypoints_derivatives_and_timing() -> None:
    points = np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [2.0, 1.0, 1.5]])
    sp = Waypoints(points, yaws_rad=[0.0, 1.0, 0.5], speed_m_s=1.0)
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    np.testing.assert_allclose(sp.segment_times_s, np.maximum(lengths, 1.0), atol=1e-15)
    rng = np.random.default_rng(0)
    interior = np.concatenate([rng.uniform(0.01, 1.99, 5), rng.uniform(2.01, sp.duration_s - 0.01, 5)])
    _check_derivatives(sp, interior)
    for k, t in enumerate([0.0, 2.0, sp.duration_s]):
        np.testing.assert_allclose(sp.sample(t).p_W, points[k], atol=1e-12)
        _assert_at_rest(sp, t)
    # Peak speed on a rest-to-rest minimum-jerk segment is 1.875 x the average.
    assert np.linalg.norm(sp.sample(1.0).v_W) == pytest.approx(1.875 * 2.0 / 2.0, abs=1e-12)
    np.testing.assert_allclose(sp.sample(100.0).p_W, points[-1], atol=1e-12)


def test_waypoints_bad_input() -> None:
    with pytest.raises(ValueError, match="points_W_m"):
        Waypoints(np.zeros((1, 3)), speed_m_s=1.0)
    with pytest.raises(ValueError, match="speed_m_s or segment_times_s"):
        Waypoints(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="segment_times_s"):
        Waypoints(np.zeros((3, 3)), segment_times_s=[1.0, -1.0])
    with pytest.raises(ValueError, match="speed_m_s"):
        Waypoints(np.zeros((2, 3)), speed_m_s=0.0)


def test_takeoff_climbs_smoothly() -> None:
    sp = Takeoff(start_W_m=[0.5, -0.5, 0.06], altitude_m=1.0, duration_s=3.0, yaw_rad=0.2)
    np.testing.assert_allclose(sp.sample(0.0).p_W, [0.5, -0.5, 0.06], atol=1e-15)
    np.testing.assert_allclose(sp.sample(3.0).p_W, [0.5, -0.5, 1.0], atol=1e-15)
    _assert_at_rest(sp, 0.0)
    _assert_at_rest(sp, 3.0)
    _check_derivatives(sp, np.array([0.3, 1.1, 2.0, 2.9]))
    assert sp.sample(1.7).yaw_rad == pytest.approx(0.2, abs=1e-15)


def test_figure_eight_derivatives_and_rest_ends() -> None:
    sp = FigureEight(
        center_xy_m=[1.0, -1.0], size_m=[1.0, 0.5], period_s=6.0, altitude_m=1.2, ramp_s=2.0, laps=2
    )
    assert sp.duration_s == pytest.approx(14.0, abs=1e-12)
    rng = np.random.default_rng(0)
    _check_derivatives(sp, rng.uniform(0.01, sp.duration_s - 0.01, 20))
    for t in (0.0, sp.duration_s):
        np.testing.assert_allclose(sp.sample(t).p_W, [1.0, -1.0, 1.2], atol=1e-12)
        _assert_at_rest(sp, t)
    # At full rate: the lemniscate x = a sin(theta), y = b sin(2 theta), theta = 2 pi (t - ramp / 2) / T.
    t = 4.0
    theta = 2 * np.pi * (t - 1.0) / 6.0
    np.testing.assert_allclose(
        sp.sample(t).p_W, [1.0 + np.sin(theta), -1.0 + 0.5 * np.sin(2 * theta), 1.2], atol=1e-12
    )


def test_figure_eight_forever_and_bad_laps() -> None:
    sp = FigureEight(center_xy_m=[0.0, 0.0])
    assert sp.duration_s == np.inf
    _check_derivatives(sp, np.array([0.5, 1.5, 7.3, 30.1]))
    with pytest.raises(ValueError, match="laps"):
        FigureEight(center_xy_m=[0.0, 0.0], period_s=1.0, ramp_s=3.0, laps=1)


def test_straight_line_cruises_at_constant_speed_and_ends_at_rest() -> None:
    sp = StraightLine(
        start_W_m=[-2.0, 0.5, 1.0], direction_W=[2.0, 0.0, 0.0], length_m=4.0, speed_m_s=0.8, ramp_s=2.0
    )
    assert sp.duration_s == pytest.approx(4.0 / 0.8 + 2.0, abs=1e-12)
    _check_derivatives(sp, np.random.default_rng(0).uniform(0.01, sp.duration_s - 0.01, 20))
    for t, p in ((0.0, [-2.0, 0.5, 1.0]), (sp.duration_s, [2.0, 0.5, 1.0])):
        np.testing.assert_allclose(sp.sample(t).p_W, p, atol=1e-12)
        _assert_at_rest(sp, t)
    # Between the ramps: exactly the cruise speed along +x, no acceleration, and half a ramp of lag.
    for t in (2.0, 3.5, 5.0):
        out = sp.sample(t)
        np.testing.assert_allclose(out.v_W, [0.8, 0.0, 0.0], atol=1e-12)
        np.testing.assert_allclose(out.a_W, 0.0, atol=1e-12)
        assert out.p_W[0] == pytest.approx(-2.0 + 0.8 * (t - 1.0), abs=1e-12)
    with pytest.raises(ValueError, match="direction_W"):
        StraightLine(start_W_m=[0.0, 0.0, 1.0], direction_W=[0.0, 0.0, 0.0], length_m=1.0)


def test_excitation_derivatives_and_rest_ends() -> None:
    sp = ExcitationManeuver(center_W_m=[0.0, 0.0, 1.0], yaw_center_rad=0.5, duration_s=6.0)
    rng = np.random.default_rng(0)
    _check_derivatives(sp, rng.uniform(0.01, 5.99, 20))
    for t in (0.0, 6.0):
        np.testing.assert_allclose(sp.sample(t).p_W, [0.0, 0.0, 1.0], atol=1e-12)
        assert sp.sample(t).yaw_rad == pytest.approx(0.5, abs=1e-12)
        np.testing.assert_allclose(sp.sample(t).v_W, 0.0, atol=1e-12)
    # It does excite: peak accelerations of order 1 m/s^2 on x and y.
    acc = np.array([sp.sample(t).a_W for t in np.linspace(0.0, 6.0, 601)])
    assert np.all(np.max(np.abs(acc[:, :2]), axis=0) > 0.5)
    assert np.max(np.linalg.norm(acc, axis=1)) < 3.0


def test_sequence_chains_takeoff_excitation_hover() -> None:
    takeoff = Takeoff(start_W_m=[0.0, 0.0, 0.06], altitude_m=1.0, duration_s=3.0)
    wiggle = ExcitationManeuver(center_W_m=[0.0, 0.0, 1.0], duration_s=5.0)
    hover = HoverPoint(p_W=[0.0, 0.0, 1.0])
    seq = Sequence([takeoff, wiggle, hover])
    assert seq.start_times_s == [0.0, 3.0, 8.0]
    assert seq.duration_s == np.inf
    np.testing.assert_allclose(seq.sample(1.2).p_W, takeoff.sample(1.2).p_W, atol=0)
    np.testing.assert_allclose(seq.sample(4.5).a_W, wiggle.sample(1.5).a_W, atol=0)
    np.testing.assert_allclose(seq.sample(20.0).p_W, [0.0, 0.0, 1.0], atol=0)
    _check_derivatives(seq, np.array([1.0, 2.5, 4.0, 6.5]))


def test_sequence_rejects_jumps_and_endless_items() -> None:
    with pytest.raises(ValueError, match="apart"):
        Sequence([Takeoff([0.0, 0.0, 0.0], 1.0), HoverPoint([0.0, 0.0, 2.0])])
    with pytest.raises(ValueError, match="never ends"):
        Sequence([HoverPoint([0.0, 0.0, 1.0]), HoverPoint([0.0, 0.0, 1.0])])
    with pytest.raises(ValueError, match="at least one"):
        Sequence([])


def _array_excitation(ex: ExcitationManeuver, t: float) -> np.ndarray:
    """The windowed sines' Leibniz rule as one array expression (the form the float path replaced)."""
    c = 2.0 * math.pi / ex.duration_s
    cos, sin = math.cos(c * t), math.sin(c * t)
    h = np.array([0.5 * (1.0 - cos), 0.5 * c * sin, 0.5 * c**2 * cos, -0.5 * c**3 * sin])[:, None]
    amp = np.append(ex.amplitude_m, ex.yaw_amplitude_rad)
    g = ExcitationManeuver._sine(amp, np.append(ex.frequency_hz, ex.yaw_frequency_hz), t)
    binomial = ((1,), (1, 1), (1, 2, 1), (1, 3, 3, 1))
    return np.array([sum(k_c * h[k] * g[n - k] for k, k_c in enumerate(binomial[n])) for n in range(4)])


def test_excitation_and_min_jerk_float_paths_match_array_forms_bit_for_bit():
    """The per-tick float arithmetic of the setpoints equals the numpy expressions it replaced exactly."""
    ex = ExcitationManeuver(np.array([0.1, -0.2, 1.5]), yaw_center_rad=0.3)
    for t in np.linspace(0.0, ex.duration_s, 301):
        d, f = _array_excitation(ex, float(t)), ex.sample(float(t))
        np.testing.assert_array_equal(f.p_W, ex.center_W_m + d[0, :3])
        for got, want in ((f.v_W, d[1, :3]), (f.a_W, d[2, :3]), (f.j_W, d[3, :3])):
            np.testing.assert_array_equal(got, want)
        assert f.yaw_rad == ex.yaw_center_rad + float(d[0, 3]) and f.yaw_rate_rad_s == float(d[1, 3])
    p0, p1, T = np.array([0.1, 0.2, 0.05]), np.array([0.4, -0.3, 1.5]), 3.0
    seg = Waypoints(np.stack([p0, p1]), segment_times_s=[T])
    for t in np.linspace(0.0, T, 97):
        s, ds, d2s, d3s = min_jerk_profile(float(t) / T)
        f, dp = seg.sample(float(t)), p1 - p0
        np.testing.assert_array_equal(f.p_W, p0 + s * dp)
        np.testing.assert_array_equal(f.v_W, dp * ds / T)
        np.testing.assert_array_equal(f.a_W, dp * d2s / T**2)
        np.testing.assert_array_equal(f.j_W, dp * d3s / T**3)
