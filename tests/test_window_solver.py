"""Tests of vio/window_solver.py: the solve budget and its warm start, the predicted decrease, FEJ.

On a window problem captured from a short simulated run: the budget, the warm start (budgeted solves reach
the unbudgeted optimum), the step's predicted decrease against the dense quadratic model, and the
first-estimate Jacobians' null space.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import viotb.vio.window as window_mod
import viotb.vio.window_solver as solver
from viotb.vio.window import WindowEstimator, WindowParams
from viotb.vio.window_batch import stack_values
from viotb.vio.window_factors import NX, retract
from viotb.vio.window_solver import (
    levenberg_marquardt,
    linearize,
    pose_index,
    predicted_decrease,
    schur_reduce,
    solve_steps,
    start_solve,
)


@pytest.fixture(scope="module")
def problem():
    """``(xs, pts, factors, weights)`` of the last keyframe solve of a 3.5 s simulated figure-8 (seed 0).

    The keyframe values are moved off the optimum (0.01 rad, 2 cm, 2 cm/s per axis) so the solves have
    work to do.
    """
    from viotb.envs.run.replay import monitor_run
    from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream

    stream = synthesize_stream(StreamConfig(motion="figure8", seconds=3.5, landmark_count=600), 0)
    captured = []
    real = window_mod.start_solve

    def capture(*args):
        captured.append(args[:4])
        return real(*args)

    window_mod.start_solve = capture
    try:
        est = WindowEstimator(
            stream.calib_given,
            stream.noise,
            WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px),
        )
        monitor_run(est, stream.imu, stream.frames, stream.time_offset_s)
    finally:
        window_mod.start_solve = real
    xs, pts, f, w8 = captured[-1]
    rng = np.random.default_rng(0)
    scale = np.concatenate([np.full(3, 0.01), np.full(3, 0.02), np.full(3, 0.02), np.zeros(6)])
    moved = [retract(x, scale * rng.normal(size=NX)) for x in xs]
    return moved, pts.copy(), f, w8


def _converged(problem):
    xs, pts, f, w8 = problem
    return levenberg_marquardt(xs, pts, f, w8, 50, 1e-4, relative_tolerance=0.0, min_decrease=1e-12)


def test_budget_bounds_the_linearizations(problem, monkeypatch):
    """At most ``max_iterations`` trial steps, each one linearization besides the first; 0 = no step."""
    xs, pts, f, w8 = problem
    calls = []
    real = solver.linearize
    monkeypatch.setattr(solver, "linearize", lambda *a, **k: calls.append(1) or real(*a, **k))
    for budget in (0, 1, 2, 3):
        calls.clear()
        res = levenberg_marquardt(xs, pts, f, w8, budget, 1e-4, relative_tolerance=0.0)
        assert res.iterations <= budget and len(calls) == res.iterations + 1
        assert not res.converged  # far from the optimum: the budget, not a stopping rule, ended it
    zero = levenberg_marquardt(xs, pts, f, w8, 0, 1e-4)
    assert zero.xs is xs and zero.pts is pts
    with pytest.raises(ValueError, match="max_iterations"):
        levenberg_marquardt(xs, pts, f, w8, -1, 1e-4)


def test_budgeted_solves_continue_to_the_unbudgeted_optimum(problem):
    """Budgeted solves, each from the previous one's values, reach the unbudgeted optimum.

    One step per call, each starting from the values and damping where the previous call stopped (the warm
    start); and the same call twice gives the same values (the budget counts steps, not time).
    """
    xs, pts, f, w8 = problem
    best = _converged(problem)
    assert best.converged
    lam = 1e-4
    for _ in range(30):
        res = levenberg_marquardt(xs, pts, f, w8, 1, lam, relative_tolerance=0.0)
        xs, pts, lam = res.xs, res.pts, res.damping
    np.testing.assert_allclose(res.system.cost, best.system.cost, rtol=1e-9)
    R, rest = stack_values(xs)
    R_best, rest_best = stack_values(best.xs)
    np.testing.assert_allclose(rest[:, :6], rest_best[:, :6], atol=1e-6)  # p (m), v (m/s)
    np.testing.assert_allclose(R, R_best, atol=1e-7)
    np.testing.assert_allclose(pts, best.pts, atol=1e-5)
    again = levenberg_marquardt(*problem, 2, 1e-4)
    once = levenberg_marquardt(*problem, 2, 1e-4)
    np.testing.assert_array_equal(stack_values(again.xs)[1], stack_values(once.xs)[1])


def test_a_solve_taken_in_parts_is_the_solve_taken_at_once(problem):
    """start_solve + solve_steps of 1, 2 and 2 steps give exactly levenberg_marquardt's 5-step solve."""
    xs, pts, f, w8 = problem
    once = levenberg_marquardt(xs, pts, f, w8, 5, 1e-4, relative_tolerance=0.0)
    st = start_solve(xs, pts, f, w8, 1e-4)
    taken = [solve_steps(st, n, relative_tolerance=0.0) for n in (1, 2, 2)]
    assert taken == [1, 2, 2] and st.iterations == once.iterations == 5
    assert st.converged == once.converged and st.damping == once.damping
    np.testing.assert_array_equal(stack_values(st.xs)[0], stack_values(once.xs)[0])
    np.testing.assert_array_equal(stack_values(st.xs)[1], stack_values(once.xs)[1])
    np.testing.assert_array_equal(st.pts, once.pts)
    assert st.system.cost == once.system.cost
    # A converged solve takes no more steps.
    done = start_solve(xs, pts, f, w8, 1e-4)
    solve_steps(done, 50, relative_tolerance=1e-3)
    assert done.converged and solve_steps(done, 5) == 0


def test_predicted_decrease_is_the_gauss_newton_model_decrease(problem):
    """predicted_decrease is the dense quadratic model's decrease for the Schur-reduced damped step.

    The model is -g^T h - 1/2 h^T H h with the keyframe and landmark blocks assembled densely.
    """
    xs, pts, f, w8 = problem
    sys = linearize(xs, pts, f, w8)
    lam = 1e-2
    S, g_red, H_ll_inv = schur_reduce(sys, lam)
    dx = np.linalg.solve(S, -g_red)
    pidx = pose_index(len(xs))
    dl = -(H_ll_inv @ (sys.g_l + np.swapaxes(sys.E, 1, 2) @ dx[pidx])[:, :, None])[:, :, 0]
    H = _full_hessian(sys, len(xs))
    h = np.concatenate([dx, dl.ravel()])
    grad = np.concatenate([sys.g, sys.g_l.ravel()])
    model = -grad @ h - 0.5 * h @ H @ h
    assert model > 0.0
    np.testing.assert_allclose(predicted_decrease(sys, lam, dx, dl), model, rtol=1e-6)


def _gauge_basis(xs, pts) -> np.ndarray:
    """Global translation (3) and yaw about gravity (1) as error-state directions, (N NX + 3 L, 4)."""
    N, L = len(xs), len(pts)
    U = np.zeros((N * NX + 3 * L, 4))
    e_z = np.array([0.0, 0.0, 1.0])
    for k, x in enumerate(xs):
        U[k * NX + 3 : k * NX + 6, :3] = np.eye(3)
        U[k * NX : k * NX + 3, 3] = x.R_WB.T @ e_z
        U[k * NX + 3 : k * NX + 6, 3] = np.cross(e_z, x.p_WB)
        U[k * NX + 6 : k * NX + 9, 3] = np.cross(e_z, x.v_WB)
    U[N * NX :, :3] = np.tile(np.eye(3), (L, 1))
    U[N * NX :, 3] = np.cross(e_z, pts).ravel()
    return U


def _full_hessian(sys, n_kf: int) -> np.ndarray:
    """The keyframe and landmark blocks of a :class:`LinearSystem` assembled densely, (N NX + 3 L)^2."""
    D, L = len(sys.g), len(sys.H_ll)
    pidx = pose_index(n_kf)
    H = np.zeros((D + 3 * L, D + 3 * L))
    H[:D, :D] = sys.H
    for j in range(L):
        sl = slice(D + 3 * j, D + 3 * j + 3)
        H[sl, sl] = sys.H_ll[j]
        H[pidx, sl] = sys.E[j]
        H[sl, pidx] = sys.E[j].T
    return H


def test_first_estimate_jacobians_keep_the_gauge_at_the_first_estimates(problem):
    """The unobservable directions (global position, yaw) follow the Jacobians' values.

    Without the prior, the window's information has them in its null space at the values of its Jacobians:
    the current ones by default, the first estimates with ``xs_lin`` (and then not the current ones).
    """
    xs, pts, f, w8 = problem
    f = dataclasses.replace(f, prior=None, prior_k=[], still=[], no_motion=[])
    best = _converged(problem)
    x_cur, p_cur = best.xs, best.pts
    for xs_lin, null_at in ((None, x_cur), (xs, xs)):
        H = _full_hessian(linearize(x_cur, p_cur, f, w8, xs_lin=xs_lin), len(xs))
        U = _gauge_basis(null_at, p_cur)
        ratio = np.linalg.norm(H @ U) / (np.linalg.norm(H) * np.linalg.norm(U))
        assert ratio < 1e-9, ratio
    H_fej = _full_hessian(linearize(x_cur, p_cur, f, w8, xs_lin=xs), len(xs))
    yaw_cur = _gauge_basis(x_cur, p_cur)[:, 3]
    assert np.linalg.norm(H_fej @ yaw_cur) / (np.linalg.norm(H_fej) * np.linalg.norm(yaw_cur)) > 1e-6


def test_default_budget_keeps_the_solve_bounded_on_a_run():
    """On a simulated run every keyframe solve stays within ``max_iterations`` trial steps."""
    from viotb.envs.run.replay import monitor_run
    from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream

    stream = synthesize_stream(StreamConfig(motion="circle", seconds=3.0, landmark_count=400), 1)
    prm = WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px, max_iterations=2)
    est = WindowEstimator(stream.calib_given, stream.noise, prm)
    monitor_run(est, stream.imu, stream.frames, stream.time_offset_s)
    assert len(est.solve_iterations) > 10
    assert max(est.solve_iterations) <= 2


def test_split_budget_bounds_every_frame_and_continues_on_the_next():
    """A keyframe's frame takes at most ``keyframe_frame_iterations`` steps; the next frames the rest.

    With 1 step on the keyframe's frame, 1 on each next frame and 3 in all, some solves continue on the
    following frames (one step each), no frame takes more, and the accuracy stays that of the unsplit 3-step
    budget.
    """
    from viotb.envs.run.replay import monitor_run
    from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream
    from viotb.vio.metrics import align_umeyama

    stream = synthesize_stream(StreamConfig(motion="circle", seconds=3.0, landmark_count=400), 1)
    runs = {}
    for k in (1, 3):
        budget = {"max_iterations": 3, "keyframe_frame_iterations": k, "frame_iterations": 1}
        prm = WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px, **budget)
        est = WindowEstimator(stream.calib_given, stream.noise, prm)
        per_frame = []
        real = est.feed_camera

        def feed(frame, est=est, real=real, per_frame=per_frame):
            n0, kf0 = len(est.solve_iterations), est.keyframes_added
            real(frame)
            per_frame.append((sum(est.solve_iterations[n0:]), est.keyframes_added > kf0))

        est.feed_camera = feed
        run = monitor_run(est, stream.imu, stream.frames, stream.time_offset_s)
        ok = [e for e in run.estimates if e is not None]
        t = np.array([e.t_s for e in ok])
        p = np.array([e.p_WB for e in ok])
        p_gt = np.stack([np.interp(t, stream.truth.t_s, stream.truth.p_WB[:, j]) for j in range(3)], axis=1)
        al = align_umeyama(p, p_gt, "posyaw")
        ate = float(np.sqrt(np.mean(np.linalg.norm(al.apply(p) - p_gt, axis=1) ** 2)))
        runs[k] = (per_frame, ate)
    per_frame, ate_split = runs[1]
    assert all(steps <= 1 for steps, is_kf in per_frame if is_kf)
    continued = [steps for steps, is_kf in per_frame if not is_kf and steps]
    assert continued and max(continued) <= 1  # frame_iterations
    assert ate_split < 0.05 and ate_split < 1.3 * runs[3][1]


def test_a_solve_spread_over_frames_ends_where_the_unsplit_solve_ends():
    """A solve spread over three frames ends where the solve on its keyframe's frame alone ends.

    Keyframes every 3rd frame; 1 step on the keyframe's frame and 2 on each of the next two (5 in all) make
    the 5-step solve's steps in parts: every solve ends at the same values, bit for bit.
    """
    from viotb.envs.run.replay import monitor_run
    from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream
    from viotb.vio.keyframing import KeyframeParams

    stream = synthesize_stream(StreamConfig(motion="circle", seconds=3.0, landmark_count=400), 1)
    every3 = KeyframeParams(every_n_frames=3, min_parallax_px=1e9, min_shared_fraction=0.0)
    ends = []
    for kfi, fi in ((5, 5), (1, 2)):
        prm = WindowParams(
            frontend="sim",
            pixel_sigma_px=stream.pixel_sigma_px,
            keyframing=every3,
            keyframe_frame_iterations=kfi,
            frame_iterations=fi,
        )
        est = WindowEstimator(stream.calib_given, stream.noise, prm)
        end: dict[int, np.ndarray] = {}  # newest keyframe's key -> the window's values when its solve ended
        real = est._finish_solve

        def finish(est=est, real=real, end=end):
            if est._solve is not None:
                R, rest = stack_values([kf.x for kf in est.keyframes])
                end[est.keyframes[-1].key] = np.concatenate([R.reshape(len(R), 9), rest], axis=1)
            real()

        est._finish_solve = finish
        monitor_run(est, stream.imu, stream.frames, stream.time_offset_s)
        ends.append(end)
    whole, parts = ends
    common = sorted(whole.keys() & parts.keys())
    assert len(common) > 10 and len(common) >= len(whole) - 1
    for key in common:
        np.testing.assert_array_equal(parts[key], whole[key])
