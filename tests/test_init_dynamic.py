"""The dynamic initializer's parts against closed forms and independent solvers (issue #13, item 2)."""

from __future__ import annotations

import numpy as np
from test_initialization import _synthetic_window
from viotb.vio.init_preintegration import RunningPreintegration, preintegrate_to
from viotb.vio.lie import exp_so3
from viotb.vio.types import GRAVITY_M_S2, ImuNoise, ImuSample


def _rolling_at_rest(seconds: float, rate_hz: float = 200.0, roll_rate_rad_s: float = 1.0):
    """IMU samples of a body at rest rolling about x at a constant rate (exact readings, no noise)."""
    out = []
    for k in range(int(round(seconds * rate_hz)) + 1):
        t = k / rate_hz
        R_WB = exp_so3(np.array([roll_rate_rad_s * t, 0.0, 0.0]))
        f_B = R_WB.T @ np.array([0.0, 0.0, GRAVITY_M_S2])  # specific force at rest
        out.append(ImuSample(t, np.array([roll_rate_rad_s, 0.0, 0.0]), f_B))
    return out


def test_preintegration_of_a_rolling_body_at_rest_matches_the_closed_form():
    """At rest, ``dv = R_WB0^T (-g) T`` and ``dp = R_WB0^T (-g) T^2 / 2`` whatever the rotation (eq. 33).

    Applying the midpoint reading with the step's start rotation would leave ``|w| |f| dt / 2`` per second
    (0.037 m/s here after 1.5 s); the half-step rotation removes it to second order.
    """
    T = 1.5
    samples = _rolling_at_rest(T)
    (_, pim), _ = preintegrate_to(samples, [0.0, T], T, ImuNoise())
    up = np.array([0.0, 0.0, GRAVITY_M_S2])
    np.testing.assert_allclose(pim.delta_R, exp_so3(np.array([T, 0.0, 0.0])), atol=1e-9)
    np.testing.assert_allclose(pim.delta_v, up * T, atol=2e-4)
    np.testing.assert_allclose(pim.delta_p, 0.5 * up * T * T, atol=2e-4)


def test_running_preintegration_reused_equals_a_fresh_one():
    """Snapshots of a preintegration extended try after try equal those of a fresh one on the same samples."""
    samples = _rolling_at_rest(1.0, roll_rate_rad_s=2.0)
    frame_times = [samples[10 * k].t_s for k in range(1, 20)]  # 20 Hz frames on the IMU clock
    run = RunningPreintegration(ImuNoise())
    for n in (6, 11, 19):  # three tries, each with more frames (the window grows)
        times = frame_times[:n]
        upto = [s for s in samples if s.t_s <= times[-1] + 1e-12]
        reused, end_reused = run.snapshots(upto, times, upto[-1].t_s)
        fresh, end_fresh = preintegrate_to(upto, times, upto[-1].t_s, ImuNoise())
        for a, b in zip([*reused, end_reused], [*fresh, end_fresh], strict=True):
            np.testing.assert_allclose(a.delta_R, b.delta_R, atol=1e-12)
            np.testing.assert_allclose(a.delta_v, b.delta_v, atol=1e-12)
            np.testing.assert_allclose(a.delta_p, b.delta_p, atol=1e-12)
            np.testing.assert_allclose(a.cov, b.cov, rtol=1e-9, atol=1e-18)
    # A window that starts later (the buffer slid) starts over from its first frame.
    later = run.snapshots(samples, frame_times[4:10], frame_times[9])[0]
    assert later[0].dt_s == 0.0 and later[-1].dt_s > 0.2


def test_schur_linear_solve_matches_dense_least_squares():
    """The feature-eliminated linear alignment against ``numpy.linalg.lstsq`` on the stacked system."""
    rng = np.random.default_rng(4)
    win = _synthetic_window(rng, 8, 4, 25)
    A_g, A_f, b = win.linear_rows()
    weights = rng.uniform(0.2, 1.0, win.n_obs)
    x = win.solve_linear(A_g, A_f, b, weights)
    A = np.zeros((2 * win.n_obs, 6 + 3 * win.n_f))
    for o in range(win.n_obs):
        j = win.obs_feat[o]
        A[2 * o : 2 * o + 2, 0:6] = A_g[o]
        A[2 * o : 2 * o + 2, 6 + 3 * j : 9 + 3 * j] = A_f[o]
    w = np.repeat(weights, 2)
    x_ref, *_ = np.linalg.lstsq(A * w[:, None], b.ravel() * w, rcond=None)
    np.testing.assert_allclose(x, x_ref, rtol=1e-6, atol=1e-8)
