"""Recovery in flight (``viotb.vio.recovery``): coast through a loss of tracking, re-initialize in the air.

Open loop on a simulated-feature stream (a hover with its 3-axis excitation) whose features vanish for 4 s,
as when the lights go out: the wrapped MSCKF coasts, re-initializes when the features return, and its
published position neither jumps nor drifts away afterwards. The coast is checked against an independent
path: the plain MSCKF, which also just propagates the IMU while it sees nothing. Closed loop:
``fly-lights-out`` really darkens the render, and the drone coasts through the dark and re-initializes in
the air. Relocalization after a blackout while hovering: on images of real texture seen from a known
trajectory (the scene of ``test_loop_closer``), the closer relocalizes the returning frames against the map
within a few frames and measures the coasted odometry's drift rate; the coasted velocity takes it as an EKF
measurement (checked against the closed-form gain) before the hand-over, which waits for it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_loop_closer import PARAMS, RATE_HZ, _err, render, scene, true_body  # noqa: F401 (fixture)
from viotb.envs.run.fly import fly
from viotb.envs.run.loop_glue import FlightLoopClosure, LoopOptions
from viotb.envs.run.replay import replay
from viotb.envs.scenarios.streams import StreamConfig, synthesize_stream
from viotb.vio.factory import make_estimator
from viotb.vio.loop import LoopClosureParams, RigidTransform
from viotb.vio.msckf import MsckfParams
from viotb.vio.recovery import OdometryReset, RecoveringEstimator, RecoveryParams
from viotb.vio.state import IMU_BLOCK, marginal_covariance
from viotb.vio.types import ImuSample, StateEstimate

DARK_S = (6.0, 10.0)


@pytest.fixture(scope="module")
def dark_stream():
    return synthesize_stream(StreamConfig(motion="hover", seconds=11.0, blackout_s=DARK_S), seed=0)


def _make(stream):
    params = MsckfParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px)
    return lambda: make_estimator("msckf", stream.calib_given, stream.noise, frontend="sim", params=params)


def _positions(run) -> np.ndarray:
    return np.array([e.p_WB if e is not None else np.full(3, np.nan) for e in run.estimates])


def _truth_at(stream, t_s: np.ndarray) -> np.ndarray:
    return stream.truth.p_WB[np.searchsorted(stream.truth.t_s, t_s - 1e-9)]


def test_the_dark_is_coasted_and_the_filter_reinitializes_when_the_light_returns(dark_stream):
    st = dark_stream
    rec = RecoveringEstimator(_make(st), st.calib_given, st.noise)
    run = replay(rec, st.imu, st.frames, st.time_offset_s)
    plain = replay(_make(st)(), st.imu, st.frames, st.time_offset_s)
    t = run.frame_t_imu_s
    p, p_plain = _positions(run), _positions(plain)
    p_true = _truth_at(st, t)
    k0 = int(np.flatnonzero(np.isfinite(p[:, 0]))[0])
    err = np.linalg.norm((p - p[k0]) - (p_true - p_true[k0]), axis=1)

    # One loss, declared feature_loss_s into the dark; the hand-over on the return_frames-th lit frame.
    prm = RecoveryParams()
    assert len(rec.events) == 1
    ev = rec.events[0]
    assert ev.reason.startswith("no feature tracked")
    assert DARK_S[0] + prm.feature_loss_s - 0.051 <= ev.t_lost_s <= DARK_S[0] + prm.feature_loss_s + 0.051
    assert ev.t_reinit_s == pytest.approx(DARK_S[1] + (prm.return_frames - 1) * 0.05, abs=0.026)
    dark = (t > ev.t_lost_s) & (t < DARK_S[1])
    assert all("coasting" in h.conditions for h, d in zip(run.health, dark, strict=True) if d)
    assert not any(h.diverged for h in run.health)

    # The coast is the plain filter's own IMU propagation (it also sees nothing): the same state.
    k_end = int(np.flatnonzero(dark)[-1])
    assert np.linalg.norm(p[k_end] - p_plain[k_end]) < 1e-4
    # ... and the same covariance, grown by the IMU noise (the filter's marginal; the coaster starts from it).
    sig, sig_plain = run.estimates[k_end].position_sigma_W_m, plain.estimates[k_end].position_sigma_W_m
    assert float(np.min(sig)) > 0.03  # grown from < 1 cm at the loss
    np.testing.assert_allclose(sig, sig_plain, rtol=1e-3)

    # No jump at the hand-over: the published step matches the true one within 5 mm.
    k_h = int(np.searchsorted(t, ev.t_reinit_s - 1e-9))
    for k in (k_h, k_h + 1):
        step_err = (p[k] - p[k - 1]) - (p_true[k] - p_true[k - 1])
        assert np.linalg.norm(step_err) < 5e-3
    # The new filter keeps the coasted frame (the drift of the coast is unobservable and stays) and does not
    # run away from it. Measured: 10.5 cm at the hand-over, up to 13.3 cm while the fresh filter waits for
    # its first updates (its tracks all start together), 7.8 cm at the end.
    after = t > ev.t_reinit_s
    assert np.max(err[after]) < err[k_h] + 0.05
    assert err[-1] < err[k_h] + 0.01


def test_declared_divergence_coasts_from_the_last_good_state_and_hands_over_with_features(dark_stream):
    st = dark_stream
    rec = RecoveringEstimator(_make(st), st.calib_given, st.noise)
    frames = [f for f in st.frames if f.t_s + st.time_offset_s < 5.0]
    run = replay(rec, st.imu, frames, st.time_offset_s)
    t_lost = float(run.frame_t_imu_s[-1])
    last = run.estimates[-1]
    rec.declare_lost(t_lost, "health monitor: test")
    assert rec.mode == "coasting" and rec.events[0].t_coast_start_s <= t_lost
    # Features are there: the hand-over comes on the return_frames-th next frame, in the same frame.
    nxt = [f for f in st.frames if 5.0 <= f.t_s + st.time_offset_s < 6.0]
    i = int(np.searchsorted(st.imu.t_s, t_lost, side="right"))
    run2 = replay(rec, st.imu, nxt, st.time_offset_s, imu_start_s=float(st.imu.t_s[i]))
    assert rec.mode == "tracking" and rec.events[0].t_reinit_s is not None
    assert rec.events[0].t_reinit_s == pytest.approx(float(run2.frame_t_imu_s[2]))
    # Continuity: no jump at the loss or the hand-over (the published steps follow the true ones within
    # 5 mm), and over the second after the loss the displacement error stays that of a short coast from the
    # last updated state (measured 2.3 cm: the bias is 3.5 s after a static start, still poorly known).
    ests = [last, *run2.estimates]
    p_est = np.array([e.p_WB for e in ests])
    p_true = _truth_at(st, np.array([e.t_s for e in ests]))
    drift = np.linalg.norm((p_est - p_est[0]) - (p_true - p_true[0]), axis=1)
    assert np.max(drift) < 0.03
    steps = np.linalg.norm(np.diff(p_est, axis=0) - np.diff(p_true, axis=0), axis=1)
    assert np.max(steps[:5]) < 5e-3  # loss, coast, hand-over (frame 2), first frame after; later: updates


def _coast_to_the_light(st, wait_s: float):
    rec = RecoveringEstimator(_make(st), st.calib_given, st.noise)
    rec.expect_velocity_fixes(wait_s)
    dark = [f for f in st.frames if f.t_s + st.time_offset_s < DARK_S[1]]
    run = replay(rec, st.imu, dark, st.time_offset_s)
    return rec, float(run.frame_t_imu_s[-1])


def _eager_coast(rec):
    """The coast predicted to the newest IMU sample the former way: one span, ``Phi P Phi^T + Q`` at once."""
    co = rec._coaster
    st = co.state
    t_new = co._last_imu.t_s
    vals, phi, q = co.propagator.predict(st.imu, st.t_s, t_new)
    P = marginal_covariance(st, [st.block(IMU_BLOCK)])
    cov = phi @ P @ phi.T + q
    return vals, 0.5 * (cov + cov.T)


def test_the_coast_is_predicted_per_imu_sample_as_the_eager_span_prediction_did(dark_stream):
    """The coaster's ``estimate()`` equals the former eager prediction over the whole span since the frame.

    The coaster now predicts as the filters do (:class:`PredictionChain`: the mean per sample, the
    covariance batched when read); against ``Phi P Phi^T + Q`` of one span: the same mean and covariance to
    round-off, read at every sample, every third one, across frames and across a velocity fix (which
    changes the coasted values in place: an estimate made before it and read after must not see it).
    """
    st = dark_stream
    rec = RecoveringEstimator(_make(st), st.calib_given, st.noise)
    run = replay(rec, st.imu, [f for f in st.frames if f.t_s + st.time_offset_s < 8.0], st.time_offset_s)
    t_last = float(run.frame_t_imu_s[-1])  # coasting since 6.5 s, in the dark until 10 s
    i = int(np.searchsorted(st.imu.t_s, t_last, side="right"))
    frames = iter([f for f in st.frames if f.t_s + st.time_offset_s > t_last])
    nxt = next(frames)
    ests, refs, n_frames = [], [], 0
    for k in range(i, i + 60):
        while nxt.t_s + st.time_offset_s < st.imu.t_s[k]:
            rec.feed_camera(nxt)
            n_frames, nxt = n_frames + 1, next(frames)
        rec.feed_imu(st.imu.sample(k))
        if k == i + 31:
            assert rec.velocity_fix(np.array([0.03, -0.02, 0.01]), np.eye(3) * 0.02**2)
        assert rec.mode == "coasting"
        est = rec.estimate()
        if k % 3 == 0 or k < i + 12:  # read at once (per tick), else later (batched intervals)
            _ = est.cov
        ests.append(est)
        refs.append(_eager_coast(rec))
    assert n_frames >= 2  # the chains restarted at frames (and at the fix)
    for est, (vals, cov) in zip(ests, refs, strict=True):
        np.testing.assert_allclose(est.p_WB, vals.p_WB, rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.v_WB, vals.v_WB, rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.R_WB, vals.R_WB, rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.gyro_bias_rad_s, vals.gyro_bias_rad_s, rtol=0, atol=1e-12)
        np.testing.assert_allclose(est.cov, cov, rtol=1e-9, atol=1e-12 * np.max(np.abs(cov)))


def _light(rec, st, t_last: float) -> None:
    lit = [f for f in st.frames if DARK_S[1] <= f.t_s + st.time_offset_s < DARK_S[1] + 1.5]
    i = int(np.searchsorted(st.imu.t_s, t_last, side="right"))
    replay(rec, st.imu, lit, st.time_offset_s, imu_start_s=float(st.imu.t_s[i]))


def test_a_velocity_fix_corrects_the_coast_with_the_kalman_gain_and_the_hand_over_waits_for_it(dark_stream):
    st = dark_stream
    rec, t_last = _coast_to_the_light(st, wait_s=1.0)
    assert rec.mode == "coasting" and rec.wants_velocity_fix
    before = rec.estimate()
    P_vv = before.cov_velocity_W_m2_s2
    dv, R = np.array([0.05, -0.08, 0.02]), np.diag([0.02, 0.03, 0.01]) ** 2
    assert rec.velocity_fix(dv, R)
    after = rec.estimate()
    # The closed form of a velocity measurement: the velocity moves by P (P + R)^-1 dv and its covariance
    # becomes P - P (P + R)^-1 P (the coasted state is at the last frame, estimate() predicts ~1 ms on).
    K = P_vv @ np.linalg.inv(P_vv + R)
    np.testing.assert_allclose(after.v_WB - before.v_WB, K @ dv, atol=1e-4)
    np.testing.assert_allclose(after.cov_velocity_W_m2_s2, P_vv - K @ P_vv, rtol=0.02, atol=1e-7)
    assert not rec.velocity_fix(dv, R) and not rec.wants_velocity_fix  # once per coast
    # The fix moved the position too (through the coasted correlations): reported as an odometry jump.
    (jump,) = rec.odometry_resets
    assert jump.reason == "velocity fix" and jump.t_s == after.t_s
    np.testing.assert_array_equal(jump.p_WB_before, before.p_WB)
    np.testing.assert_array_equal(jump.p_WB_after, after.p_WB)
    assert np.linalg.norm(after.p_WB - before.p_WB) > 1e-3
    with pytest.raises(ValueError, match="velocity_fix"):
        rec.velocity_fix(np.full(3, np.nan), R)
    # Fixed: the hand-over comes on the return_frames-th lit frame, as without a map.
    _light(rec, st, t_last)
    assert rec.events[0].t_reinit_s == pytest.approx(
        DARK_S[1] + (RecoveryParams().return_frames - 1) * 0.05, abs=0.026
    )
    # The hand-over is another odometry (seeded at the coasted pose: no jump of the pose itself).
    hand_over = rec.odometry_resets[-1]
    assert hand_over.reason == "hand-over" and len(rec.odometry_resets) == 2
    assert np.linalg.norm(hand_over.p_WB_after - hand_over.p_WB_before) < 1e-6
    # Expected but never given: it waits the whole 1 s for one, then hands over all the same.
    rec, t_last = _coast_to_the_light(st, wait_s=1.0)
    _light(rec, st, t_last)
    assert rec.mode == "tracking" and rec.events[0].t_reinit_s == pytest.approx(DARK_S[1] + 1.0, abs=0.026)
    with pytest.raises(ValueError, match="max_wait_s"):
        rec.expect_velocity_fixes(-1.0)


def _hover_with_a_blackout(
    scene_data,
    params: LoopClosureParams,
    jump: RigidTransform,
    drift_m_s: np.ndarray,
    fix_jump_m: np.ndarray | None = None,
    follow: bool = True,
):
    """Map while moving (9 s), hover at the pose of t = 9 s, dark 11-12.5 s, then the coasted odometry.

    The odometry is off by ``jump`` from the light on and drifts at ``drift_m_s`` until 13.5 s (a coast
    until its velocity is fixed and the filter re-initialized, ``vio.recovery``); the truth stays put.
    ``fix_jump_m``: the fix at 13.5 s also moves the odometry position by this much (m), reported as an
    :class:`OdometryReset` that the glue follows when ``follow``.
    Returns the glue, its ``drift_velocity()`` at 13.3 s and ``(t, truth, odometry)`` after the light.
    """
    texture, calib = scene_data
    lc = FlightLoopClosure(LoopOptions(params=params), calib, "klt")
    resets: list[OdometryReset] = []
    if follow:
        lc.follow_odometry_resets(resets)
    hover = true_body(9.0, calib)
    out, fix = [], None
    for t_s in np.arange(0.0, 15.5, 1.0 / RATE_HZ):
        truth = true_body(t_s, calib) if t_s < 9.0 else hover
        dark = 11.0 <= t_s < 12.5
        odom = truth
        if t_s >= 11.0:
            odom = RigidTransform(jump.R, jump.p + drift_m_s * (min(t_s, 13.5) - 11.0)) @ truth
        if fix_jump_m is not None and t_s >= 13.5 - 1e-9:
            if not resets and follow:
                resets.append(OdometryReset(t_s, "velocity fix", odom.R, odom.p, odom.R, odom.p + fix_jump_m))
            odom = RigidTransform(odom.R, odom.p + fix_jump_m)
        est = StateEstimate(t_s=t_s, R_WB=odom.R, p_WB=odom.p, v_WB=np.zeros(3))
        image = np.zeros_like(texture[0]) if dark else render(texture, calib, truth)
        lc.on_frame(t_s, image, est, 0 if dark else 150)
        if t_s >= 12.5:
            out.append((t_s, truth, odom))
        if abs(t_s - 13.3) < 1e-6:
            fix = lc.drift_velocity()
    return lc, fix, out


def test_relocalization_after_a_blackout_while_hovering(scene):  # noqa: F811 (the imported fixture)
    jump = RigidTransform.from_yaw(np.deg2rad(3.0), np.array([0.2, -0.15, 0.05]))
    drift = np.array([0.08, 0.05, -0.02])
    lc, fix, after = _hover_with_a_blackout(scene, PARAMS, jump, drift)
    relocs = [c for c in lc.closer.run_closures if c.relocalization]
    assert len(relocs) == 1 and lc.closer.localized
    # The dense keyframes after the loss: the query at the first lit frame, its confirmation a keyframe later.
    t_reloc = relocs[0].t_query_s
    assert t_reloc - 12.5 <= 0.25
    # The drift rate from the loops: the true velocity in the odometry frame is v_odom - drift.
    dv, cov = fix
    assert np.linalg.norm(dv + drift) < 3.0 * np.sqrt(np.max(np.diag(cov))) + 0.01, (dv, cov)
    # From the end of the relocalization's blend on, the corrected pose is within 3 cm of the truth (the
    # odometry: 0.25-0.45 m off). Measured: 1.1-2.2 cm, closures at every keyframe (0.1 s).
    errs = np.array(
        [
            _err(RigidTransform(*lc.closer.corrected_pose(t, o.R, o.p)), tr)
            for t, tr, o in after
            if t > t_reloc + 1.0
        ]
    )
    assert len(errs) >= 10
    assert errs[:, 0].max() < 0.03 and errs[:, 1].max() < 1.0, errs
    # Without the dense rule (a keyframe only by motion or every 2 s) the hover waits seconds for it.
    sparse = replace(PARAMS, relocalization_keyframe_interval_s=1e9)
    lc_sparse, _, _ = _hover_with_a_blackout(scene, sparse, jump, drift)
    later = [c.t_query_s for c in lc_sparse.closer.run_closures if c.relocalization]
    assert not later or later[0] - 12.5 >= 1.5


def test_an_odometry_jump_is_carried_into_the_correction_and_relocalized_afresh(scene):  # noqa: F811
    """A velocity fix that moves the coasted position by 20 cm (``OdometryReset``) at 13.5 s.

    Followed, the corrected pose (causal: ``lc.online``) does not move with it and the next frame's new
    segment relocalizes at once; not followed (the former bookkeeping), the corrected pose jumps by the
    20 cm and the loops that would put it back are refused as too large a drift to the end
    (``fly-lights-out`` KLT seed 5, README "Recovery in flight").
    """
    jump = RigidTransform.from_yaw(np.deg2rad(3.0), np.array([0.2, -0.15, 0.05]))
    drift, fix_jump = np.array([0.08, 0.05, -0.02]), np.array([0.12, 0.14, -0.06])
    errors = {}
    for follow in (True, False):
        lc, _, after = _hover_with_a_blackout(scene, PARAMS, jump, drift, fix_jump, follow)
        online = {round(e.t_s, 6): RigidTransform(e.R_WB, e.p_WB) for e in lc.online}
        errors[follow] = np.array([(t, _err(online[round(t, 6)], tr)[0]) for t, tr, _ in after])
        relocs = [c.t_query_s for c in lc.closer.run_closures if c.relocalization]
        if follow:
            assert len(relocs) == 2 and 13.5 <= relocs[1] <= 13.75, relocs  # the new segment's, at once
    # Measured: 18.2 cm just before the jump (the relocalization's correction still blending in), 17.4 cm
    # just after; 2.1 cm at the end. Not followed: 33.9 cm after it, 22.2 cm at the end (60 loops refused).
    for follow, (t, err) in ((f, e.T) for f, e in errors.items()):
        k = int(np.flatnonzero(t >= 13.5 - 1e-9)[0])
        if follow:
            assert err[k] <= err[k - 1] + 0.01 and err[-1] < 0.03, errors[True]
        else:
            assert err[k] > err[k - 1] + 0.1 and err[-1] > 0.15, errors[False]


def test_a_failed_imu_is_not_recovered_it_raises(dark_stream):
    st = dark_stream
    rec = RecoveringEstimator(_make(st), st.calib_given, st.noise)
    rec.feed_imu(st.imu.sample(0))
    nan3 = np.full(3, np.nan)
    with pytest.raises(ValueError, match="not finite"):
        rec.feed_imu(ImuSample(float(st.imu.t_s[1]), nan3, nan3))


def test_bad_settings_and_estimators_without_a_front_end_are_refused(dark_stream):
    with pytest.raises(ValueError, match="RecoveryParams.feature_loss_s"):
        RecoveryParams(feature_loss_s=0.0)
    with pytest.raises(ValueError, match="RecoveryParams.return_frames"):
        RecoveryParams(return_frames=0)
    st = dark_stream
    with pytest.raises(ValueError, match="imu-only"):
        RecoveringEstimator(
            lambda: make_estimator("imu-only", st.calib_given, st.noise), st.calib_given, st.noise
        )


def test_lights_out_really_darkens_the_render_and_the_light_comes_back():
    from viotb.envs.sim.render import OffscreenRenderer, SceneLights
    from viotb.envs.sim.simulation import Simulation
    from viotb.models.constants import ONBOARD_CAMERA

    sim = Simulation("quadrotor", "textured_room")
    sim.set_pose(np.eye(3), np.array([0.0, 0.0, 1.0]))
    with OffscreenRenderer(sim.model, 160, 120, ONBOARD_CAMERA) as renderer:
        lights = SceneLights(sim.model)
        lit = renderer.render_gray(sim.data)
        lights.set_on(False)
        dark = renderer.render_gray(sim.data)
        lights.set_on(True)
        again = renderer.render_gray(sim.data)
    assert lit.mean() > 30.0 and int(dark.max()) == 0
    np.testing.assert_array_equal(again, lit)


def _lights_out(
    seconds: float, seed: int, dark_s: tuple[float, float] | None = None, frontend: str = "sim", **kw
):
    edit = None if dark_s is None else (lambda r: replace(r, lights_off_intervals_s=(dark_s,)))
    return fly("fly-lights-out", "msckf", seconds=seconds, seed=seed, frontend=frontend, edit_rig=edit, **kw)


def _check_recovered(metrics: dict, dark_s: tuple[float, float], seconds: float) -> None:
    assert not metrics["crashed"] and not metrics["diverged"], metrics["reason"]
    assert metrics["seconds"] == pytest.approx(seconds)
    (ev,) = metrics["recoveries"]
    assert dark_s[0] < ev["t_lost_s"] < dark_s[0] + 1.0
    # The hand-over waits up to 1 s for the relocalized drift rate (measured: 0.65-0.8 s after the light);
    # without loop closure it comes on the third lit frame.
    wait_s = 1.05 if metrics.get("loop_closures") is not None else 0.2
    assert dark_s[1] < ev["t_reinit_s"] < dark_s[1] + wait_s


def _relocalized_after(metrics: dict, t_s: float) -> bool:
    return any(r["relocalization"] and r["t_query_s"] > t_s for r in metrics["loop_closure_rows"])


def test_short_lights_out_flight_coasts_relocalizes_and_is_back_at_the_hold_point():
    """2 s of darkness at 11 s while hovering, simulated features (the lights-out frames carry none), 16 s.

    The scenario flies with loop closure (the closer on the rendered images): the returning frames
    relocalize against the map of the hold point. Issue target: no crash, back within 10 cm of the hold point
    within 3 s of the light returning. Measured (seed 0): largest excursion 3.3 cm (4.7 cm without loop
    closure), 28 closures.
    """
    dark = (11.0, 13.0)
    metrics, log = _lights_out(16.0, 0, dark)
    _check_recovered(metrics, dark, 16.0)
    assert _relocalized_after(metrics, dark[1])
    assert metrics["lights_out_back_s"] is not None and metrics["lights_out_back_s"] <= 3.0
    assert metrics["lights_out_excursion_m"] < 0.10
    conds = [
        c for t, c in zip(log.frame_t_s, log.frame_conditions, strict=True) if dark[0] + 0.6 < t < dark[1]
    ]
    assert conds and all("coasting" in c for c in conds)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(10))
def test_lights_out_flight_over_ten_seeds_is_back_at_the_hold_point_within_3_s(seed):
    """Simulated features, 4 s dark. Measured: back after 0-2.5 s (10 / 10), excursion 6-23 cm."""
    metrics, _ = _lights_out(22.0, seed)
    _check_recovered(metrics, (13.0, 17.0), 22.0)
    assert _relocalized_after(metrics, 17.0)
    assert metrics["lights_out_back_s"] is not None and metrics["lights_out_back_s"] <= 3.0


@pytest.mark.slow
def test_lights_out_flight_with_klt_over_ten_seeds_never_crashes_and_is_mostly_back_within_3_s():
    """KLT on the renders (the default front end), 4 s dark, seeds 0-9.

    Measured (session 13, ``7acd7ae``): no crash, relocalized 10 / 10 (and again after the hand-over, a new
    odometry segment), back within 10 cm after 0-2.3 s on all 10 (seeds 10-19 too, after 0-2.2 s). On
    older mains seed 8 never came back (its velocity fix was wrong: README "Recovery in flight"), and
    before the odometry resets were followed seeds 2 and 5 did not.
    """
    back = []
    for seed in range(10):
        metrics, _ = _lights_out(22.0, seed, frontend="klt")
        _check_recovered(metrics, (13.0, 17.0), 22.0)
        assert _relocalized_after(metrics, 17.0), seed
        back.append(metrics["lights_out_back_s"])
    assert all(b is not None and b <= 3.0 for b in back), back
