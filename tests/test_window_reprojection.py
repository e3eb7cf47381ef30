"""Tests of vio/window_reprojection.py and the marginalization's reuse of a solve's blocks.

The correlated (KLT) track noise against a dense generalized-least-squares system built independently here:
finite-difference Jacobians of the projection, the views' covariance ``I + q min(n_u, n_v)`` from a plain
loop over each track's pixel path, and one dense inverse. The white-noise system against the same
reference with ``q = 0``; the marginalization's landmark subsystem against a fresh linearization of the
subset's factors.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from viotb.vio.lie import exp_so3
from viotb.vio.state import ImuValues
from viotb.vio.types import ImuNoise
from viotb.vio.window_factors import NX, project, retract
from viotb.vio.window_map import observations
from viotb.vio.window_marginalize import landmark_subsystem
from viotb.vio.window_solver import Factors, FactorWeights, linearize

FOCAL_PX = 120.0
SIGMA_PX = 1.0


def _problem(seed: int = 0, n_kf: int = 5, n_lm: int = 9):
    """Keyframes moving along x, a tilted camera, landmarks 3-6 m ahead seen in 2..N keyframes each.

    Returns ``(xs, pts, obs, R_BC, p_BC)``; the observations are the projections plus 0.4 px noise (all
    well inside the Huber threshold, so the systems are plain least squares).
    """
    rng = np.random.default_rng(seed)
    R_BC = exp_so3(np.array([0.1, -0.2, 0.05]))
    p_BC = np.array([0.05, 0.0, 0.02])
    xs = [
        ImuValues(
            exp_so3(0.05 * rng.normal(size=3)),
            np.array([0.3 * k, 0.02 * rng.normal(), 0.02 * rng.normal()]),
            np.zeros(3),
            np.zeros(3),
            np.zeros(3),
        )
        for k in range(n_kf)
    ]
    pts = np.column_stack([rng.uniform(-1, 2, n_lm), rng.uniform(-1, 1, n_lm), rng.uniform(3, 6, n_lm)])
    pts = pts @ R_BC.T  # roughly in front of the tilted camera
    kf_i, lm_i = [], []
    for k in range(n_kf):
        for lm in range(n_lm):
            first = lm % (n_kf - 1)  # every landmark starts at some keyframe and stays seen
            if k >= first:
                kf_i.append(k)
                lm_i.append(lm)
    kf_i, lm_i = np.array(kf_i), np.array(lm_i)
    R = np.stack([xs[k].R_WB for k in kf_i])
    p = np.stack([xs[k].p_WB for k in kf_i])
    xy = project(R, p, pts[lm_i], R_BC, p_BC) + 0.4 / FOCAL_PX * rng.normal(size=(len(kf_i), 2))
    return xs, pts, (kf_i, lm_i, xy), R_BC, p_BC


def _weights(R_BC, p_BC, q: float) -> FactorWeights:
    noise = ImuNoise(1e-3, 1e-2, 1e-5, 1e-4)
    return FactorWeights(noise, R_BC, p_BC, SIGMA_PX / FOCAL_PX, 3.0, 0.01, track_q=q, focal_px=FOCAL_PX)


def _factors(obs) -> Factors:
    return Factors(imu=[], prior=None, prior_k=[], still=[], no_motion=[], obs=obs)


def track_views(kf_i: np.ndarray, lm_i: np.ndarray, lm: int) -> list[int]:
    """The observations of landmark ``lm`` in keyframe order."""
    return sorted(np.nonzero(lm_i == lm)[0], key=lambda m: kf_i[m])


def track_covariance(xy: np.ndarray, ms: list[int], q: float) -> np.ndarray:
    """Covariance (units of sigma^2) of one track's views ``ms``, axes interleaved: ``I + q min(n_u, n_v)``.

    ``n`` is the pixel path along the track since its first view (straight lines between consecutive views).
    """
    path = [0.0]
    for a, b in zip(ms[:-1], ms[1:], strict=True):
        path.append(path[-1] + FOCAL_PX * float(np.linalg.norm(xy[b] - xy[a])))
    C = np.eye(2 * len(ms))
    for iu in range(len(ms)):
        for iv in range(len(ms)):
            for axis in range(2):
                C[2 * iu + axis, 2 * iv + axis] += q * min(path[iu], path[iv])
    return C


def _reference(xs, pts, obs, R_BC, p_BC, q: float):
    """Dense ``(H, g, cost)`` over ``[poses (6 N), points (3 L)]`` of the GLS reprojection cost."""
    kf_i, lm_i, xy = obs
    N, L, M = len(xs), len(pts), len(kf_i)
    s = FOCAL_PX / SIGMA_PX  # 1 / sigma in normalized coordinates

    def residuals(xs_, pts_):
        R = np.stack([xs_[k].R_WB for k in kf_i])
        p = np.stack([xs_[k].p_WB for k in kf_i])
        return ((project(R, p, pts_[lm_i], R_BC, p_BC) - xy) * s).ravel()

    r0 = residuals(xs, pts)
    J = np.zeros((2 * M, 6 * N + 3 * L))
    eps = 1e-6
    for k in range(N):
        for d in range(6):
            dx = np.zeros(NX)
            dx[d] = eps
            plus = [retract(x, dx) if j == k else x for j, x in enumerate(xs)]
            minus = [retract(x, -dx) if j == k else x for j, x in enumerate(xs)]
            J[:, 6 * k + d] = (residuals(plus, pts) - residuals(minus, pts)) / (2 * eps)
    for lm in range(L):
        for d in range(3):
            dp = np.zeros_like(pts)
            dp[lm, d] = eps
            J[:, 6 * N + 3 * lm + d] = (residuals(xs, pts + dp) - residuals(xs, pts - dp)) / (2 * eps)
    # Covariance of the residuals (units of sigma^2): per landmark and axis I + q min(n_u, n_v), n the
    # pixel path along the track since its first view (straight lines between consecutive views).
    C = np.eye(2 * M)
    for lm in range(L):
        ms = track_views(kf_i, lm_i, lm)
        rows = (2 * np.array(ms)[:, None] + np.arange(2)).ravel()
        C[np.ix_(rows, rows)] = track_covariance(xy, ms, q)
    Lam = np.linalg.inv(C)
    return J.T @ Lam @ J, J.T @ Lam @ r0, 0.5 * float(r0 @ Lam @ r0)


@pytest.mark.parametrize("q", [0.0, 0.05])
def test_reprojection_system_is_generalized_least_squares(q):
    """H, E, H_ll, both gradients and the cost equal the dense GLS system (q = 0: white noise)."""
    xs, pts, obs, R_BC, p_BC = _problem()
    sys = linearize(xs, pts, _factors(obs), _weights(R_BC, p_BC, q))
    H_ref, g_ref, cost_ref = _reference(xs, pts, obs, R_BC, p_BC, q)
    N, L = len(xs), len(pts)
    pose = (np.arange(N)[:, None] * NX + np.arange(6)).ravel()
    tol = {"rtol": 1e-5, "atol": 1e-3}  # information of order 1e4-1e6; central differences to ~1e-8
    np.testing.assert_allclose(sys.H[np.ix_(pose, pose)], H_ref[: 6 * N, : 6 * N], **tol)
    np.testing.assert_allclose(sys.g[pose], g_ref[: 6 * N], **tol)
    for lm in range(L):
        c = slice(6 * N + 3 * lm, 6 * N + 3 * lm + 3)
        np.testing.assert_allclose(sys.H_ll[lm], H_ref[c, c], **tol)
        np.testing.assert_allclose(sys.E[lm], H_ref[: 6 * N, c], **tol)
        np.testing.assert_allclose(sys.g_l[lm], g_ref[c], **tol)
    np.testing.assert_allclose(sys.cost, cost_ref, rtol=1e-9)
    # Correlated views couple different keyframes (not a track's first view: its error is white alone).
    off = sys.H[NX : NX + 6, 2 * NX : 2 * NX + 6]
    assert (np.abs(off).max() > 1.0) == (q > 0.0)


def test_track_noise_lowers_the_information():
    """Correlated views carry less information than white ones: the GLS H is below the white H."""
    xs, pts, obs, R_BC, p_BC = _problem(seed=1)
    H_w = linearize(xs, pts, _factors(obs), _weights(R_BC, p_BC, 0.0))
    H_t = linearize(xs, pts, _factors(obs), _weights(R_BC, p_BC, 0.05))
    for lm in range(len(pts)):
        assert np.all(np.linalg.eigvalsh(H_w.H_ll[lm] - H_t.H_ll[lm]) > -1e-6)
    assert np.trace(H_t.H) < np.trace(H_w.H)


@pytest.mark.parametrize("q", [0.0, 0.05])
def test_landmark_subsystem_matches_a_fresh_linearization(q):
    """The subsystem of some landmarks taken from a full linearization's blocks equals linearizing them."""
    xs, pts, obs, R_BC, p_BC = _problem(seed=2)
    w8 = _weights(R_BC, p_BC, q)
    full = linearize(xs, pts, _factors(obs), w8)
    rows = np.array([1, 4, 6])
    keep = np.isin(obs[1], rows)
    remap = {int(r): j for j, r in enumerate(rows)}
    sub_obs = (obs[0][keep], np.array([remap[int(i)] for i in obs[1][keep]]), obs[2][keep])
    fresh = linearize(xs, pts[rows], _factors(sub_obs), w8)
    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
    base = linearize(xs, np.zeros((0, 3)), _factors(empty), w8)
    sub = landmark_subsystem(full, rows, base)
    for name in ("H", "g", "H_ll", "g_l", "E"):
        np.testing.assert_allclose(getattr(sub, name), getattr(fresh, name), rtol=1e-10, atol=1e-8)


def test_observations_feed_the_track_noise_in_time_order():
    """``observations`` lists keyframe by keyframe, so each landmark's views are in time order."""
    from viotb.vio.window_map import Keyframe

    xs, pts, obs, _, _ = _problem(seed=3)
    kfs = [Keyframe(k, float(k), x, {}) for k, x in enumerate(xs)]
    for k, lm, xy in zip(*obs, strict=True):
        kfs[k].obs[int(lm)] = xy
    kf_i, lm_i, xy = observations(kfs, list(range(len(pts))))
    assert np.all(np.diff(kf_i) >= 0)
    order = np.lexsort((obs[1], obs[0]))
    np.testing.assert_array_equal(np.lexsort((lm_i, kf_i)), np.arange(len(kf_i)))
    np.testing.assert_allclose(xy[np.lexsort((lm_i, kf_i))], obs[2][order])


def test_second_camera_gets_its_own_track_noise():
    """Cam1 with cam0's geometry and observations doubles the system: its tracks are whitened on their own."""
    xs, pts, obs, R_BC, p_BC = _problem(seed=4)
    w8 = _weights(R_BC, p_BC, 0.05)
    stereo = dataclasses.replace(w8, R_BC1=R_BC, p_BC1=p_BC, sigma_norm1=w8.sigma_norm, focal_px1=FOCAL_PX)
    mono = linearize(xs, pts, _factors(obs), w8)
    both = linearize(xs, pts, dataclasses.replace(_factors(obs), obs_right=obs), stereo)
    for name in ("H", "g", "H_ll", "g_l", "E"):
        np.testing.assert_allclose(getattr(both, name), 2.0 * getattr(mono, name), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(both.cost, 2.0 * mono.cost, rtol=1e-12)


@pytest.mark.parametrize("track_noise", [False, True])
def test_marginalization_from_the_solve_equals_a_new_linearization(track_noise):
    """The prior built from the solve's stored blocks equals the one from linearizing the factors again.

    On a 3 s simulated circle (the sim front end; the track noise forced through the factor weights): the
    estimator's window after a solve, marginalized both ways from copies.
    """
    import copy

    from viotb.envs.run.replay import monitor_run
    from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream
    from viotb.vio.window import WindowEstimator, WindowParams
    from viotb.vio.window_marginalize import marginalize_oldest

    stream = synthesize_stream(StreamConfig(motion="circle", seconds=3.0, landmark_count=400), 2)
    est = WindowEstimator(stream.calib_given, stream.noise, WindowParams(frontend="sim"))
    if track_noise:
        est._weights = dataclasses.replace(est._weights, track_q=0.05, focal_px=est._focal_px)
    monitor_run(est, stream.imu, stream.frames, stream.time_offset_s)
    est._finish_solve()  # the run's last solve, if its frames did not finish it
    est._start_solve()  # a solve at the window's values, as before a marginalization
    est._solve_steps(2, True)
    est._finish_solve()  # where its 2 steps reached (a full window: nothing is marginalized yet)
    assert len(est.prior.keys) > 5 and est._solved is not None
    a, b = copy.deepcopy(est), copy.deepcopy(est)
    args = lambda e: (e.keyframes, e.links, e.landmarks, e.prior, e._weights, False)  # noqa: E731
    prior_new, _, _ = marginalize_oldest(*args(a), None)
    prior_reuse, _, _ = marginalize_oldest(*args(b), b._solved)
    assert prior_new.keys == prior_reuse.keys
    scale = np.abs(prior_new.H).max()
    np.testing.assert_allclose(prior_reuse.H, prior_new.H, rtol=1e-9, atol=1e-10 * scale)
    np.testing.assert_allclose(prior_reuse.g, prior_new.g, rtol=1e-9, atol=1e-10 * np.abs(prior_new.g).max())


def test_compiled_white_reprojection_equals_the_numpy_reference():
    """``FactorWeights.kernels``: the numba loop and the numpy path give the same system to round-off."""
    xs, pts, obs, R_BC, p_BC = _problem()
    w_nb = dataclasses.replace(_weights(R_BC, p_BC, 0.0), kernels="numba")
    w_np = dataclasses.replace(_weights(R_BC, p_BC, 0.0), kernels="numpy")
    a = linearize(xs, pts, _factors(obs), w_nb)
    b = linearize(xs, pts, _factors(obs), w_np)
    for name in ("H", "g", "H_ll", "E", "g_l"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        scale = max(float(np.abs(y).max()), 1.0)
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-10 * scale, err_msg=name)
    assert abs(a.cost - b.cost) <= 1e-10 * max(abs(b.cost), 1.0)
