"""Tests of the sliding-window optimizer (vio/window.py) and the Schur marginalization it uses."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest
from data_paths import EUROC_MICRO
from random_states import random_imu_values
from viotb.vio.lie import exp_so3
from viotb.vio.marginalization import schur_complement
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.state import ImuValues
from viotb.vio.types import ImuNoise, ImuSample
from viotb.vio.window import (
    NX,
    WindowEstimator,
    WindowParams,
    boxminus,
    imu_factor,
    reprojection,
    retract,
)


# ------------------------------------------------------------------------------------- marginalization
def test_schur_prior_is_inverse_of_marginal_covariance():
    """Schur prior on a random linear-Gaussian problem against the closed-form marginal.

    The prior's information is the inverse of the exact marginal covariance block ``(H^-1)_rr`` and its
    gradient gives the same kept solution as the full system.
    """
    rng = np.random.default_rng(0)
    J = rng.normal(size=(60, 20))
    H = J.T @ J + 0.1 * np.eye(20)
    g = rng.normal(size=20)
    marg = np.array([3, 0, 7, 8, 15])
    H_p, g_p, keep = schur_complement(H, g, marg)
    np.testing.assert_array_equal(keep, np.setdiff1d(np.arange(20), marg))
    cov = np.linalg.inv(H)
    np.testing.assert_allclose(np.linalg.inv(H_p), cov[np.ix_(keep, keep)], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(-np.linalg.solve(H_p, g_p), (-cov @ g)[keep], rtol=1e-9, atol=1e-12)


def test_schur_rejects_bad_shapes_and_indices():
    """Mismatched shapes and out-of-range indices are named."""
    with pytest.raises(ValueError, match="do not agree"):
        schur_complement(np.eye(3), np.zeros(2), [0])
    with pytest.raises(ValueError, match="out of range"):
        schur_complement(np.eye(3), np.zeros(3), [5])


# ----------------------------------------------------------------------------------------- Jacobians


def _numeric_jacobian(fun, x: ImuValues, eps: float = 1e-6) -> np.ndarray:
    """Central differences of ``fun`` on the manifold, perturbing ``x`` by ``retract(x, +-eps e_k)``."""
    cols = []
    for k in range(NX):
        d = np.zeros(NX)
        d[k] = eps
        cols.append((fun(retract(x, d)) - fun(retract(x, -d))) / (2 * eps))
    return np.stack(cols, axis=1)


def test_imu_factor_jacobians_match_central_differences():
    """Analytic IMU-factor Jacobians (all rows) against central differences on the manifold.

    The biases are away from the preintegration's linearization point (first-order bias update active).
    """
    rng = np.random.default_rng(0)
    noise = ImuNoise()
    pre = ImuPreintegration(np.array([0.01, -0.02, 0.005]), np.array([0.1, 0.0, -0.05]), noise)
    for _ in range(40):
        pre.integrate(rng.normal(size=3) + [0, 0, 9.81], rng.normal(size=3), 0.005)
    xi, xj = random_imu_values(rng), random_imu_values(rng)
    r, J_i, J_j, cov = imu_factor(pre, xi, xj, noise)
    assert r.shape == (15,) and cov.shape == (15, 15)
    num_i = _numeric_jacobian(lambda x: imu_factor(pre, x, xj, noise)[0], xi)
    num_j = _numeric_jacobian(lambda x: imu_factor(pre, xi, x, noise)[0], xj)
    np.testing.assert_allclose(J_i, num_i, atol=1e-6)
    np.testing.assert_allclose(J_j, num_j, atol=1e-6)


def test_imu_factor_residual_zero_at_prediction():
    """The state predicted with the preintegration (Forster eq. 33) has a zero IMU residual."""
    rng = np.random.default_rng(1)
    noise = ImuNoise()
    pre = ImuPreintegration(np.zeros(3), np.zeros(3), noise)
    for _ in range(20):
        pre.integrate(rng.normal(size=3) + [0, 0, 9.81], rng.normal(size=3), 0.005)
    xi = random_imu_values(rng)
    R, p, v = pre.predict(
        xi.R_WB, xi.p_WB, xi.v_WB, np.array([0.0, 0.0, -9.81]), xi.gyro_bias_rad_s, xi.accel_bias_m_s2
    )
    xj = ImuValues(R, p, v, xi.gyro_bias_rad_s, xi.accel_bias_m_s2)
    r, *_ = imu_factor(pre, xi, xj, noise)
    np.testing.assert_allclose(r, 0.0, atol=1e-10)


def test_reprojection_jacobians_match_central_differences():
    """Reprojection Jacobians w.r.t. [dtheta, dp] (right perturbation) and the point, central differences."""
    rng = np.random.default_rng(2)
    R_BC = exp_so3(rng.normal(size=3))
    p_BC = np.array([0.07, 0.01, -0.02])
    R_WB = exp_so3(rng.normal(size=3))
    p_WB = rng.normal(size=3)
    # Points 2-6 m in front of the camera.
    R_WC, p_WC = R_WB @ R_BC, p_WB + R_WB @ p_BC
    p_C = np.column_stack([rng.uniform(-1, 1, 5), rng.uniform(-1, 1, 5), rng.uniform(2, 6, 5)])
    p_W = p_C @ R_WC.T + p_WC
    M = len(p_W)

    def proj(R, p, pts):
        return reprojection(np.repeat(R[None], M, 0), np.repeat(p[None], M, 0), pts, R_BC, p_BC)

    z, depth, J_pose, J_pt = proj(R_WB, p_WB, p_W)
    np.testing.assert_allclose(depth, p_C[:, 2], rtol=1e-12)
    np.testing.assert_allclose(z, p_C[:, :2] / p_C[:, 2:], rtol=1e-12)
    eps = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        num_th = (proj(R_WB @ exp_so3(d), p_WB, p_W)[0] - proj(R_WB @ exp_so3(-d), p_WB, p_W)[0]) / (2 * eps)
        num_p = (proj(R_WB, p_WB + d, p_W)[0] - proj(R_WB, p_WB - d, p_W)[0]) / (2 * eps)
        num_l = (proj(R_WB, p_WB, p_W + d)[0] - proj(R_WB, p_WB, p_W - d)[0]) / (2 * eps)
        np.testing.assert_allclose(J_pose[:, :, k], num_th, atol=1e-7)
        np.testing.assert_allclose(J_pose[:, :, 3 + k], num_p, atol=1e-7)
        np.testing.assert_allclose(J_pt[:, :, k], num_l, atol=1e-7)


def test_retract_boxminus_roundtrip():
    """``retract(x0, x [-] x0) == x``."""
    rng = np.random.default_rng(3)
    x0, x = random_imu_values(rng), random_imu_values(rng)
    back = retract(x0, boxminus(x, x0))
    np.testing.assert_allclose(back.R_WB, x.R_WB, atol=1e-12)
    np.testing.assert_allclose(back.p_WB, x.p_WB, atol=1e-12)


# ------------------------------------------------------------------------------------- the estimator
def _stream(seed: int, seconds: float):
    from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream

    return synthesize_stream(StreamConfig(motion="figure8", seconds=seconds, landmark_count=600), seed)


def _run_window(stream, params: WindowParams | None = None) -> tuple[WindowEstimator, float, dict]:
    """Window estimator over a stream: (estimator, ATE after a yaw+translation alignment (m), run info)."""
    from viotb.envs.run.replay import monitor_run
    from viotb.vio.metrics import align_umeyama, positions_at

    prm = params if params is not None else WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px)
    est = WindowEstimator(stream.calib_given, stream.noise, prm)
    t0 = time.perf_counter()
    run = monitor_run(est, stream.imu, stream.frames, stream.time_offset_s)
    wall = time.perf_counter() - t0
    ok = [e for e in run.estimates if e is not None]
    t = np.array([e.t_s for e in ok])
    p = np.array([e.p_WB for e in ok])
    gt = stream.truth
    p_gt = positions_at(gt, t)
    al = align_umeyama(p, p_gt, "posyaw")
    ate = float(np.sqrt(np.mean(np.linalg.norm(al.apply(p) - p_gt, axis=1) ** 2)))
    return est, ate, {"run": run, "wall_s": wall, "estimates": ok}


def test_window_figure8_accuracy_against_msckf():
    """8 s simulated-feature figure-8 (seed 0): the window optimizer's ATE (yaw+translation alignment).

    Measured: window 1.8 cm, MSCKF 2.1 cm (``run_stream``) on this stream; seeds 1-7:
    1.6 / 2.6 / 1.3 / 1.4 / 1.5 / 1.5 / 1.2 cm against 2.5 / 2.6 / 1.8 / 1.7 / 2.2 / 1.5 / 1.8 cm.
    Bound: 3 cm and at most 1.25x the MSCKF's ATE on the same stream.
    Also checks the window stays bounded (marginalization runs), no divergence, and a symmetric
    positive-definite reported covariance.
    """
    from viotb.envs.run.failure_runner import run_stream

    stream = _stream(0, 8.0)
    est, ate, info = _run_window(stream)
    ate_msckf = run_stream(stream).metrics["ate_m"]
    assert ate < 0.03, f"window ATE {ate:.4f} m"
    assert ate < 1.25 * ate_msckf, f"window ATE {ate:.4f} m vs MSCKF {ate_msckf:.4f} m"
    health = info["run"].health
    assert not any(h.diverged for h in health)
    assert health[-1].initialized and health[-1].tracked_features > 20 and health[-1].updated_features > 20
    assert len(est.keyframes) == est.params.window_size
    # The prior spans every kept keyframe (landmarks seen in the marginalized one connect them all).
    assert est.prior is not None and len(est.prior.keys) == est.params.window_size
    cov = info["estimates"][-1].cov
    np.testing.assert_allclose(cov, cov.T, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(cov) > 0.0)


def test_same_seed_same_estimates():
    """Two runs over the same stream give identical estimates."""
    stream = _stream(5, 2.0)
    _, ate_a, a = _run_window(stream)
    _, ate_b, b = _run_window(stream)
    assert len(a["estimates"]) == len(b["estimates"]) > 10
    for ea, eb in zip(a["estimates"], b["estimates"], strict=True):
        np.testing.assert_array_equal(ea.p_WB, eb.p_WB)
        np.testing.assert_array_equal(ea.R_WB, eb.R_WB)
        np.testing.assert_array_equal(ea.cov, eb.cov)
    assert ate_a == ate_b


def test_divergence_reported_through_health_not_raised():
    """A 300 m/s^2 accelerometer fault from t = 2.5 s: no exception, ``health().diverged`` with a reason.

    Measured: every gated feature is an outlier from the fault on; declared at 3.6 s (5 keyframes later).
    """
    from viotb.envs.run.replay import monitor_run
    from viotb.vio.types import Estimator, ImuSeries

    stream = _stream(0, 3.0)
    accel = stream.imu.accel_B_m_s2.copy()
    accel[stream.imu.t_s > 2.5] += [300.0, 0.0, 0.0]
    imu = ImuSeries(stream.imu.t_s, stream.imu.gyro_B_rad_s, accel, stream.imu.saturated)
    est = WindowEstimator(
        stream.calib_given, stream.noise, WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px)
    )
    assert isinstance(est, Estimator)
    run = monitor_run(est, imu, stream.frames, stream.time_offset_s)
    h = run.health[-1]
    assert h.diverged and "outliers" in h.reason
    assert 2.5 < h.t_s < 4.0
    assert not any(x.diverged for x in run.health if x.t_s < 2.5)


def _calib():
    from viotb.vio.camera import CameraCalibration, PinholeCamera

    return CameraCalibration(PinholeCamera.from_fovy(320, 240, 90.0), np.eye(3), np.zeros(3))


def test_bad_inputs_raise_value_errors_naming_the_value():
    """NaN IMU, non-increasing IMU time and an unknown front end raise ValueError naming the value."""
    est = WindowEstimator(_calib(), ImuNoise(), WindowParams(frontend="sim"))
    est.feed_imu(ImuSample(0.0, np.zeros(3), np.array([0.0, 0.0, 9.81])))
    with pytest.raises(ValueError, match="gyro_B_rad_s"):
        est.feed_imu(ImuSample(0.005, np.array([np.nan, 0.0, 0.0]), np.array([0.0, 0.0, 9.81])))
    with pytest.raises(ValueError, match="t=0.000000000 s after t=0.000000000 s"):
        est.feed_imu(ImuSample(0.0, np.zeros(3), np.array([0.0, 0.0, 9.81])))
    with pytest.raises(ValueError, match="'bogus'"):
        WindowEstimator(_calib(), ImuNoise(), WindowParams(frontend="bogus"))
    with pytest.raises(ValueError, match="window_size"):
        WindowEstimator(_calib(), ImuNoise(), WindowParams(frontend="sim", window_size=1))


def test_initialize_reports_the_initial_covariance_and_state():
    """Right after ``initialize`` the estimate is the init state with ``diag(cov_diag)`` (closed form)."""
    from viotb.vio.initialization import InitResult

    cov_diag = np.arange(1, 16) * 1e-4
    init = InitResult(
        1.0,
        exp_so3(np.array([0.1, -0.2, 0.3])),
        np.array([1.0, 2.0, 3.0]),
        np.zeros(3),
        np.zeros(3),
        np.zeros(3),
        "static",
        cov_diag,
    )
    uncoupled = WindowParams(frontend="sim", static_tilt_bias_sigma_m_s2=None)
    est = WindowEstimator(_calib(), ImuNoise(), uncoupled)
    est.initialize(init)
    e = est.estimate()
    assert e is not None and e.t_s == 1.0
    np.testing.assert_array_equal(e.p_WB, init.p_WB)
    np.testing.assert_allclose(e.cov, np.diag(cov_diag), rtol=1e-12)
    # By default a static start couples the tilt and the horizontal accelerometer bias; the rest is as given.
    coupled = WindowEstimator(_calib(), ImuNoise(), WindowParams(frontend="sim"))
    coupled.initialize(init)
    c = coupled.estimate().cov
    np.testing.assert_allclose(c[:12, :12], np.diag(cov_diag[:12]), rtol=1e-12)
    assert np.abs(c[12:15, 0:3]).max() > 1e-6
    dynamic = WindowEstimator(_calib(), ImuNoise(), WindowParams(frontend="sim"))
    dynamic.initialize(replace(init, method="dynamic"))
    np.testing.assert_allclose(dynamic.estimate().cov, np.diag(cov_diag), rtol=1e-12)
    with pytest.raises(ValueError, match="cov_diag"):
        est.initialize(
            InitResult(
                1.0, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), "static", np.zeros(15)
            )
        )


MICRO = EUROC_MICRO


def _euroc_drift_m(params: WindowParams) -> tuple[float, int]:
    """Largest position change (m) of the estimates over the still EuRoC micro cut (KLT on real images)."""
    from viotb.envs.data.euroc import load_image, read_euroc
    from viotb.vio.types import CameraFrame

    ds = read_euroc(MICRO)
    est = WindowEstimator(ds.calib, ds.imu_noise, params)
    t_frames = ds.cam_t_s + ds.calib.time_offset_s
    i = int(np.searchsorted(ds.imu.t_s, t_frames[0] - 1.0))
    p = []
    for k, t in enumerate(t_frames):
        while ds.imu.t_s[i] <= t:
            est.feed_imu(ds.imu.sample(i))
            i += 1
        est.feed_camera(CameraFrame(t_s=float(ds.cam_t_s[k]), image=load_image(ds, k)))
        e = est.estimate()
        if e is not None:
            p.append(e.p_WB)
    assert not est.health().diverged
    p = np.array(p)
    return float(np.max(np.linalg.norm(p - p[0], axis=1))), len(p)


@pytest.mark.skipif(not MICRO.exists(), reason="EuRoC micro dataset not present")
def test_real_euroc_at_rest_holds_position_with_zero_velocity_factor():
    """Real EuRoC V1_01 images (KLT) at rest (truth moves < 2 mm over the cut's 4.7 s).

    Nothing triangulates without parallax, so only the zero-velocity factor holds the velocity. Measured:
    3.6 mm largest drift with it, 4.1 cm without it (the MSCKF with its ZUPT: 0.9 mm) over 65 estimates.
    """
    drift, n = _euroc_drift_m(WindowParams(frontend="klt"))
    assert n > 50
    assert drift < 0.01, drift
    no_zv = replace(WindowParams().zero_velocity, enabled=False)
    drift_off, _ = _euroc_drift_m(WindowParams(frontend="klt", zero_velocity=no_zv))
    assert drift_off > 0.02, drift_off


@pytest.mark.slow
def test_window_figure8_multi_seed_against_msckf(tmp_path):
    """Seeds 0-7, 8 s figure-8, through the sweep engine: every window ATE below 4 cm, mean below the MSCKF's.

    Measured (window / MSCKF, cm): 1.8/2.1, 1.6/2.5, 2.6/2.6, 1.3/1.8, 1.4/1.7, 1.5/2.2, 1.5/1.5, 1.2/1.8;
    mean 1.6 vs 2.0.
    """
    import pandas as pd
    from viotb.envs.tools.sweep import run_sweep

    spec = {
        "fixed": {
            "mode": "stream",
            "frontend": "sim",
            "scenario": "figure8",
            "seconds": 8.0,
            "stream.landmark_count": 600,
            "msckf.pixel_sigma_px": 0.5,
        },
        "grid": {"estimator": ["msckf", "window"]},
        "seeds": list(range(8)),
    }
    df = pd.read_parquet(run_sweep(spec, tmp_path / "sweep", workers=2).results)
    assert (df.status == "ok").all(), df[["status", "error"]]
    ates = df[df["config/estimator"] == "window"].sort_values("seed")["ate_m"].to_numpy()
    ates_msckf = df[df["config/estimator"] == "msckf"].sort_values("seed")["ate_m"].to_numpy()
    assert max(ates) < 0.04, ates
    assert np.mean(ates) < np.mean(ates_msckf), (ates, ates_msckf)


def test_spin_in_place_does_not_make_every_frame_a_keyframe():
    """3 s simulated 3 rad/s spin (1.5 s of it still): rotation-compensated parallax (the default) vs raw.

    Measured: 20 keyframe solves of 89 frames against 43 without the compensation. Fewer keyframes cost
    accuracy in a spin: over seeds 0-4 the ATE is 15-26 mm (mean 21.4) against 11-18 mm (mean 14.2) raw
    (seed 0, this test: 18.2 vs 14.0 mm); the issue's p99 per frame is why the compensation is the default.
    """
    from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream
    from viotb.vio.keyframing import KeyframeParams

    stream = synthesize_stream(StreamConfig(motion="fast-rotation", seconds=3.0, landmark_count=600), 0)
    raw = KeyframeParams(every_n_frames=3, min_parallax_px=10.0)
    est_c, ate_c, _ = _run_window(stream)
    est_r, ate_r, _ = _run_window(stream, replace(est_c.params, keyframing=raw))
    assert est_c.params.keyframing.rotation_compensated
    assert est_c.keyframes_added < 0.6 * est_r.keyframes_added
    assert ate_c < 0.025 and ate_r < 0.025


def _anchored_position_nees(motion: str, seed: int) -> float:
    """Mean position NEES of the window on an 8 s simulated-feature run, anchored at the first pose.

    The covariance refers to the frame the initialization fixed (position and yaw of the first keyframe):
    ``vio.metrics.anchor_first_pose``, as ``nees_pos_anchored_mean`` of ``viotb eval``.
    """
    from viotb.envs.run.replay import monitor_run
    from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream
    from viotb.vio.lie import rotmat_to_quat_wxyz
    from viotb.vio.metrics import evaluate_trajectory
    from viotb.vio.types import TrajectoryArrays

    stream = synthesize_stream(StreamConfig(motion=motion, seconds=8.0, landmark_count=600), seed)
    prm = WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px)
    est = WindowEstimator(stream.calib_given, stream.noise, prm)
    ok = [
        e
        for e in monitor_run(est, stream.imu, stream.frames, stream.time_offset_s).estimates
        if e is not None
    ]
    traj = TrajectoryArrays(
        np.array([e.t_s for e in ok]),
        np.array([e.p_WB for e in ok]),
        np.array([rotmat_to_quat_wxyz(e.R_WB) for e in ok]),
    )
    pos_covs = np.array([e.cov_position_W_m2 for e in ok])
    rot_covs = np.array([e.cov_orientation_rad2 for e in ok])
    return evaluate_trajectory(traj, stream.truth, pos_covs, rot_covs)["nees_pos_anchored_mean"]


def test_position_covariance_consistent_on_a_simulated_circle():
    """Simulated features with exactly the assumed white noise, 8 s circle (seed 0): anchored NEES 1-5.

    Measured 2.6 (seed 1: 1.3); 3 is consistent for 3 dof. A guard against a change that makes the
    covariance over- or underconfident where it is right today.
    """
    assert 1.0 < _anchored_position_nees("circle", 0) < 5.0


@pytest.mark.xfail(strict=True, reason="known: the window is overconfident on this stream (issue 13)")
def test_position_covariance_consistent_on_a_simulated_figure8():
    """The same on an 8 s figure-8 (seed 0): measured 7.1 (the MSCKF's 1.4 on the 10 s stream).

    Not the KLT track correlation (the features are white here), nor the prior's linearization point
    (first-estimate Jacobians leave it), nor the Huber weights (README, "Where the window's overconfidence
    comes from"). Strict: it fails loudly once fixed.
    """
    assert _anchored_position_nees("figure8", 0) < 5.0
