"""The headset rig with the estimator online: pose at IMU rate, display prediction, headset metrics.

``viotb headset`` runs this. The head follows a scenario's scripted trajectory (kinematic, as in recordings);
the IMU model turns the analytic truth into 1 kHz readings; the rig's cameras (``head_cam0``, and
``head_cam1`` with ``cameras=2``) are rendered at their exposure instants (or, with the ``sim`` front end,
the scene's landmarks are projected). Everything is fed to the estimator in IMU-clock order, as
:func:`viotb.envs.run.replay.replay` does: before IMU sample ``k``, every frame exposed before ``t_k`` is fed
(so all samples up to the frame came first); then sample ``k``, then the pose is read.

**Pose at IMU rate.** After each ``feed_imu`` the runner reads ``estimator.estimate()``, which every estimator
of this package propagates with the buffered IMU to the newest sample (MSCKF: the filter state propagated
without being changed; window: the newest keyframe propagated), so the 1 kHz pose is the estimator's own
propagated estimate; the runner does no propagation of its own. From it the
:class:`~viotb.vio.prediction.DisplayPosePredictor` predicts the pose at ``t + latency`` from the
bias-corrected gyro (``StateEstimate.omega_B_rad_s``), the velocity and the gravity-removed acceleration
``a_W = R_WB (f_B - b_a) + g_W`` of the latest accelerometer sample.

**World frame.** A headset defines its world at boot: gravity up, yaw and origin where it started. The
estimator initializes itself (static initializer on the scenario's still start); at that instant the runner
maps the estimator's frame to W with one yaw rotation and one translation (4 DoF, once, never refitted), so
tilt errors of the initializer, and all later drift, show in the metrics.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from viotb.envs.run.headset_estimators import (
    HEADSET_MSCKF,
    default_gyro_noise_inflation,
    estimator_imu_noise,
    headset_health_params,
)
from viotb.envs.run.loop_glue import FlightLoopClosure, LoopOptions, require_images
from viotb.envs.scenarios.registry import get_scenario
from viotb.envs.sim.camera_timing import frame_schedule
from viotb.envs.sim.imu_model import ImuModel, imu_preset
from viotb.models.constants import HEADSET_CAMERAS, VEHICLE_BODIES
from viotb.vio.display_pose import DisplayPoseFilter, DisplayPoseParams
from viotb.vio.factory import CALIBRATING_ESTIMATORS, make_estimator
from viotb.vio.headset_metrics import (
    interpolate_poses,
)
from viotb.vio.health import HealthMonitor
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.prediction import DisplayPosePredictor, MotionState, PredictionParams
from viotb.vio.types import CameraFrame, StateEstimate, gravity_W
from viotb.vio.window import WindowParams

ProgressFn = Callable[[float, float], None]


@dataclass(frozen=True)
class HeadsetOptions:
    """Settings of one headset run.

    Attributes:
        estimator: Estimator name (``msckf``, ``window``, ``imu-only``, ``ground-truth``).
        cameras: 1 (``head_cam0``) or 2 (``head_cam0`` + ``head_cam1``, stereo).
        latency_s: Display latency the pose is predicted to (s).
        seconds: Duration (s); None = the scenario's default.
        seed: Seeds the IMU, pixel noise and frame drops.
        frontend: ``klt`` (rendered images) or ``sim`` (projected scene landmarks, fast).
        sim_pixel_sigma_px: Pixel noise of the ``sim`` front end (px).
        prediction: Predictor settings (its ``latency_s`` is replaced by ``latency_s``).
        msckf: MSCKF settings (None: :data:`HEADSET_MSCKF`, a clone and an update at every frame).
        imu_preset: IMU part to simulate (:func:`~viotb.envs.sim.imu_model.imu_preset`); None: the
            scenario's (``icm42688-1khz``). ``icm42688-1khz-calibrated`` is the same part with factory-
            calibrated intrinsics (scale and misalignment residuals 10x smaller).
        gyro_noise_inflation: Factor on the gyro noise density the estimator is told (the sensor model's
            is unchanged); see :func:`estimator_imu_noise`. None (default): the factor of
            :func:`default_gyro_noise_inflation` (2 for an MSCKF that estimates the gyro intrinsics, as
            :data:`HEADSET_MSCKF` does; 10 otherwise); 1 tells the estimator the sensor's own density.
        window: Window-optimizer settings (None: defaults).
        display: Display pose filter (:mod:`viotb.vio.display_pose`); None renders with the estimator's pose.
        loop: Loop closure beside the estimator (``klt`` only; :class:`FlightLoopClosure`): the pose at IMU
            rate is the estimate with the closer's correction in force (a session started with
            ``loop.map_in`` continues in the saved room's frame once it recognizes it). None: off.
        time_offset_error_s: Error of the camera-IMU time offset the estimator is told (s): the rig's
            clocks are as before, the calibration given to the estimator (and the loop closer) has its
            ``time_offset_s`` plus this (a sync error to diagnose; the health monitor names it).
        online_calibration: Estimate the time offset and the extrinsics online (``msckf``:
            :meth:`~viotb.vio.msckf_params.MsckfParams.with_online_calibration`; ``window``: its own).
    """

    estimator: str = "msckf"
    cameras: int = 1
    latency_s: float = 0.020
    seconds: float | None = None
    seed: int = 0
    frontend: str = "klt"
    sim_pixel_sigma_px: float = 0.5
    prediction: PredictionParams = field(default_factory=PredictionParams)
    msckf: MsckfParams | None = None
    window: WindowParams | None = None
    imu_preset: str | None = None
    gyro_noise_inflation: float | None = None
    display: DisplayPoseParams | None = field(default_factory=DisplayPoseParams)
    loop: LoopOptions | None = None
    time_offset_error_s: float = 0.0
    online_calibration: bool = False


@dataclass
class HeadsetRun:
    """What a headset run produced (N poses at IMU rate from the first estimate; F frames).

    Attributes:
        scenario: Scenario name.
        options: The settings.
        t_s: Pose times (s, IMU clock), shape (N,).
        R_est: Estimated orientations in W, shape (N, 3, 3).
        p_est: Estimated positions in W (m), shape (N, 3).
        R_true: True orientations at ``t_s``, shape (N, 3, 3).
        p_true: True positions (m), shape (N, 3).
        R_disp: Display orientations (the estimator's, corrections smoothed; see
            :mod:`viotb.vio.display_pose`), shape (N, 3, 3); the estimator's own when ``display`` is None.
        p_disp: Display positions (m), shape (N, 3).
        speed_true_rad_s: True head angular speed at ``t_s`` (rad/s), shape (N,).
        t_pred_s: Times the predictions are for, ``t_s + latency`` (s), shape (M,), M <= N.
        R_pred: Predicted orientations, shape (M, 3, 3).
        p_pred: Predicted positions (m), shape (M, 3).
        R_true_pred: True orientations at ``t_pred_s``, shape (M, 3, 3).
        p_true_pred: True positions at ``t_pred_s`` (m), shape (M, 3).
        nees_pos: Position NEES at each frame after initialization, shape (F',).
        ms_per_frame: Wall time of each ``feed_camera`` (ms), shape (F,).
        frame_t_s: Frame exposure times (s, IMU clock), shape (F,).
        tracked: Tracked features per frame, shape (F,).
        wall_s: Wall time of the whole run (s).
        images: A few (t_s, image) samples of cam0 for the recording (every 10th frame).
        failure: Why the run stopped early ("" when it did not).
        loop: The loop closer's JSON keys (:meth:`FlightLoopClosure.finish`) and its ``loop_closures.csv``
            rows under ``loop_closure_rows``; empty without loop closure.
        closures: The accepted closures (for ``loop_closures.csv``).
        conditions: The health monitor's conditions (:meth:`~viotb.vio.health.HealthMonitor.report`).
        active: The monitor's condition names active after each frame, length F.
    """

    scenario: str
    options: HeadsetOptions
    t_s: np.ndarray
    R_est: np.ndarray
    p_est: np.ndarray
    R_true: np.ndarray
    p_true: np.ndarray
    R_disp: np.ndarray
    p_disp: np.ndarray
    speed_true_rad_s: np.ndarray
    t_pred_s: np.ndarray
    R_pred: np.ndarray
    p_pred: np.ndarray
    R_true_pred: np.ndarray
    p_true_pred: np.ndarray
    nees_pos: np.ndarray
    ms_per_frame: np.ndarray
    frame_t_s: np.ndarray
    tracked: np.ndarray
    wall_s: float
    images: list[tuple[float, np.ndarray]] = field(default_factory=list)
    failure: str = ""
    loop: dict = field(default_factory=dict)
    closures: list = field(default_factory=list)
    conditions: list = field(default_factory=list)
    active: list[tuple[str, ...]] = field(default_factory=list)


def _rotz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _yaw_anchor(est: StateEstimate, R_true: np.ndarray, p_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R_a, t_a)`` mapping the estimator's frame to W: ``x_W = R_a x_E + t_a``, R_a a yaw rotation.

    Chosen so the estimate's heading and position equal the truth's at the initialization instant.
    """
    fwd_t, fwd_e = R_true[:, 0], est.R_WB[:, 0]
    yaw = np.arctan2(fwd_t[1], fwd_t[0]) - np.arctan2(fwd_e[1], fwd_e[0])
    R_a = _rotz(float(yaw))
    return R_a, p_true - R_a @ est.p_WB


def _check(scenario, opts: HeadsetOptions) -> None:
    if scenario.vehicle != "headset" or scenario.trajectory is None:
        raise ValueError(
            f"viotb headset needs a headset scenario with a scripted motion, got {scenario.name!r}"
        )
    if opts.cameras not in (1, 2):
        raise ValueError(f"cameras must be 1 or 2, got {opts.cameras}")
    if not (np.isfinite(opts.time_offset_error_s) and abs(opts.time_offset_error_s) <= 0.1):
        ms = opts.time_offset_error_s * 1e3
        raise ValueError(f"time offset error must be within +-100 ms, got {ms} ms")
    if opts.online_calibration and opts.estimator not in CALIBRATING_ESTIMATORS:
        raise ValueError(f"online calibration needs --estimator msckf or window, got {opts.estimator!r}")
    if opts.frontend not in ("klt", "sim"):
        raise ValueError(f"unknown front end {opts.frontend!r}; allowed: klt, sim")
    right_sigma = None if opts.msckf is None else opts.msckf.right_pixel_sigma_px
    if right_sigma is not None and (opts.estimator, opts.cameras, opts.frontend) != ("msckf", 2, "klt"):
        raise ValueError(
            f"--right-pixel-sigma {right_sigma} needs --estimator msckf --cameras 2 --frontend klt (got "
            f"{opts.estimator!r}, {opts.cameras} camera(s), {opts.frontend!r}; the sim front end's cam1 "
            "noise is its own pixel noise)"
        )
    if opts.loop is not None:
        require_images(opts.frontend)
    if not (np.isfinite(opts.latency_s) and 0.0 <= opts.latency_s <= 0.2):
        raise ValueError(f"latency must be in [0, 200] ms, got {opts.latency_s * 1e3} ms")
    if opts.seconds is not None and not (np.isfinite(opts.seconds) and opts.seconds > 0.0):
        raise ValueError(f"seconds must be positive, got {opts.seconds}")


def run_headset(
    name: str, opts: HeadsetOptions = HeadsetOptions(), progress: ProgressFn | None = None
) -> HeadsetRun:
    """Run scenario ``name`` on the headset rig with ``opts.estimator`` online (see the module docstring).

    Raises:
        ValueError: Not a headset scenario, bad options, or stereo before the stereo estimators exist.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    from viotb.envs.sim.camera_rig import CameraRig  # (imports mujoco)
    from viotb.envs.sim.landmarks import project_landmarks, scene_landmarks
    from viotb.envs.sim.simulation import Simulation

    wall0 = time.perf_counter()
    scenario = get_scenario(name)
    _check(scenario, opts)
    duration_s = float(scenario.default_seconds if opts.seconds is None else opts.seconds)
    trajectory = scenario.make_trajectory(duration_s)
    cam = scenario.camera
    imu_params = imu_preset(scenario.imu_preset if opts.imu_preset is None else opts.imu_preset)
    imu_seq, drop_seq, pix0_seq, lm_seq, pix1_seq = np.random.SeedSequence(opts.seed).spawn(5)

    # Truth and IMU at the IMU rate.
    n_imu = int(np.floor(duration_s * imu_params.rate_hz + 1e-9)) + 1
    t_imu = np.arange(n_imu) / imu_params.rate_hz
    truth = trajectory.sample_many(t_imu)
    imu_model = ImuModel(imu_params, np.random.default_rng(imu_seq))
    imu, bias_g, bias_a = imu_model.measure_series_with_biases(t_imu, truth.omega_B, truth.specific_force_B)

    # Cameras.
    sim = Simulation(scenario.vehicle, scenario.scene)
    names = (scenario.camera_names or HEADSET_CAMERAS)[: opts.cameras]
    rngs = [np.random.default_rng(pix0_seq), np.random.default_rng(pix1_seq)]
    rig = CameraRig(sim.model, names, VEHICLE_BODIES["headset"], cam, rngs, render=opts.frontend == "klt")
    landmarks_W = (
        scene_landmarks(sim.model, np.random.default_rng(lm_seq)) if opts.frontend == "sim" else None
    )
    schedule = frame_schedule(cam, duration_s, np.random.default_rng(drop_seq))
    kept = schedule.kept_indices
    feat_rng = np.random.default_rng(pix0_seq.spawn(1)[0])

    def place_at(t_s: float) -> None:
        s = trajectory.sample(t_s)
        sim.set_pose(s.R_WB, s.p_WB, s.v_WB, s.omega_B, a_W=s.a_WB)

    def make_frame(i: int) -> CameraFrame:
        t_exp = float(schedule.t_exposure_imu_s[i])
        t_cam = float(schedule.t_stamp_cam_s[i])
        if opts.frontend == "klt":
            images = rig.render(sim.data, place_at, t_exp)
            if opts.cameras == 2:
                return CameraFrame(t_s=t_cam, image=images[0], image_right=images[1])
            return CameraFrame(t_s=t_cam, image=images[0])
        s = trajectory.sample(t_exp)
        obs = [
            project_landmarks(
                landmarks_W,
                s.R_WB @ c.R_BC,
                s.p_WB + s.R_WB @ c.p_BC,
                c.camera,
                feat_rng,
                opts.sim_pixel_sigma_px,
            )
            for c in rig.calibs
        ]
        if opts.cameras == 2:
            return CameraFrame(t_s=t_cam, features=obs[0], features_right=obs[1])
        return CameraFrame(t_s=t_cam, features=obs[0])

    # Estimator (the stereo keyword only on a stereo run).
    msckf = opts.msckf if opts.msckf is not None else HEADSET_MSCKF
    window = opts.window if opts.window is not None else WindowParams()
    if opts.frontend == "sim":
        msckf = replace(msckf, pixel_sigma_px=opts.sim_pixel_sigma_px)
        window = replace(window, pixel_sigma_px=opts.sim_pixel_sigma_px)
    if opts.online_calibration:
        msckf, window = msckf.with_online_calibration(), window.with_online_calibration()
    err = opts.time_offset_error_s
    told = [replace(c, time_offset_s=c.time_offset_s + err) for c in rig.calibs]
    stereo = {"calib_right": told[1]} if opts.cameras == 2 else {}
    inflation = opts.gyro_noise_inflation
    if inflation is None:
        inflation = default_gyro_noise_inflation(opts.estimator, msckf)
    est = make_estimator(
        opts.estimator,
        told[0],
        estimator_imu_noise(imu_params.noise, inflation),
        frontend=opts.frontend,
        params=msckf,
        window_params=window,
        **stereo,
    )
    predictor = DisplayPosePredictor(replace(opts.prediction, latency_s=opts.latency_s))
    display = DisplayPoseFilter(opts.display) if opts.display is not None else None
    lc = None if opts.loop is None else FlightLoopClosure(opts.loop, told[0], opts.frontend)
    last_image: np.ndarray | None = None
    monitor = HealthMonitor(headset_health_params(opts.estimator, opts.frontend))
    active: list = []  # the monitor's conditions, as `viotb eval` reports them

    g_W = gravity_W()
    rows_t, rows_R, rows_p, pred_R, pred_p, disp_R, disp_p = [], [], [], [], [], [], []
    nees, ms, frame_t, tracked, images = [], [], [], [], []
    anchor: tuple[np.ndarray, np.ndarray] | None = None
    failure = ""
    f = 0
    try:
        for k in range(n_imu):
            t_k = float(t_imu[k])
            new_frame = False
            sample = imu.sample(k)  # first: a frame waits for the IMU to pass it (replay.imu_end_for_frame)
            est.feed_imu(sample)
            monitor.observe_imu(sample)
            while f < len(kept) and schedule.t_exposure_imu_s[kept[f]] + cam.latency_s <= t_k:
                frame = make_frame(int(kept[f]))
                if opts.estimator == "ground-truth":
                    s = trajectory.sample(float(schedule.t_exposure_imu_s[kept[f]]))
                    j = min(int(np.searchsorted(t_imu, s.t_s)), n_imu - 1)  # the oracle knows the biases too
                    est.feed_truth(
                        StateEstimate(
                            t_s=s.t_s,
                            R_WB=s.R_WB,
                            p_WB=s.p_WB,
                            v_WB=s.v_WB,
                            gyro_bias_rad_s=bias_g[j],
                            accel_bias_m_s2=bias_a[j],
                        )
                    )
                t0 = time.perf_counter()
                est.feed_camera(frame)
                ms.append((time.perf_counter() - t0) * 1e3)
                frame_t.append(float(schedule.t_exposure_imu_s[kept[f]]))
                tracked.append(est.health().tracked_features)
                monitor.observe_frame(frame_t[-1], est.health(), est.estimate())
                active.append(tuple(sorted(monitor.active())))
                last_image = frame.image
                if frame.image is not None and f % 10 == 0:
                    images.append((frame_t[-1], frame.image))
                f += 1
                new_frame = True
                if progress is not None:
                    progress(f, len(kept))
            if est.health().diverged:
                failure = f"estimator diverged: {est.health().reason}"
                break
            e = est.estimate()
            if lc is not None and new_frame:
                true_k = StateEstimate(t_s=t_k, R_WB=truth.R_WB[k], p_WB=truth.p_WB[k], v_WB=truth.v_WB[k])
                lc.on_frame(t_k, last_image, e, tracked[-1], true_k)
            if lc is not None:
                e = lc.correct(t_k, e)
            if e is None:
                continue
            if anchor is None:
                anchor = _yaw_anchor(e, truth.R_WB[k], truth.p_WB[k])
            R_a, t_a = anchor
            R_WB, p_WB, v_WB = R_a @ e.R_WB, R_a @ e.p_WB + t_a, R_a @ e.v_WB
            omega = np.asarray(e.omega_B_rad_s, dtype=float)
            predictor.add_gyro(t_k, omega)
            a_W = R_WB @ (np.asarray(sample.accel_B_m_s2) - e.accel_bias_m_s2) + g_W
            R_d, p_d, v_d = (
                display.update(t_k, R_WB, p_WB, v_WB, omega, a_W)
                if display is not None
                else (R_WB, p_WB, v_WB)
            )
            pred = predictor.predict(MotionState(t_k, R_d, p_d, v_d, omega, a_W))
            rows_t.append(t_k)
            rows_R.append(R_WB)
            rows_p.append(p_WB)
            disp_R.append(R_d)
            disp_p.append(p_d)
            pred_R.append(pred.R_WB)
            pred_p.append(pred.p_WB)
            if new_frame:
                err = p_WB - truth.p_WB[k]
                P = R_a @ e.cov_position_W_m2 @ R_a.T
                if np.all(np.isfinite(P)) and np.linalg.det(P) > 0.0:
                    nees.append(float(err @ np.linalg.solve(P, err)))
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        failure = f"{type(exc).__name__}: {exc}"
    finally:
        rig.close()

    t_s = np.asarray(rows_t)
    idx = np.searchsorted(t_imu, t_s)
    t_pred = t_s + opts.latency_s
    m = int(np.searchsorted(t_pred, t_imu[-1], side="right"))
    if m >= 2:
        R_tp, p_tp = interpolate_poses(t_pred[:m], t_imu, truth.R_WB, truth.p_WB)
    else:
        R_tp, p_tp = np.zeros((0, 3, 3)), np.zeros((0, 3))
    return HeadsetRun(
        scenario=name,
        options=opts,
        t_s=t_s,
        R_est=np.asarray(rows_R).reshape(-1, 3, 3),
        p_est=np.asarray(rows_p).reshape(-1, 3),
        R_true=truth.R_WB[idx],
        p_true=truth.p_WB[idx],
        R_disp=np.asarray(disp_R).reshape(-1, 3, 3),
        p_disp=np.asarray(disp_p).reshape(-1, 3),
        speed_true_rad_s=np.linalg.norm(truth.omega_B[idx], axis=1) if len(idx) else np.zeros(0),
        t_pred_s=t_pred[:m],
        R_pred=np.asarray(pred_R).reshape(-1, 3, 3)[:m],
        p_pred=np.asarray(pred_p).reshape(-1, 3)[:m],
        R_true_pred=R_tp,
        p_true_pred=p_tp,
        nees_pos=np.asarray(nees),
        ms_per_frame=np.asarray(ms),
        frame_t_s=np.asarray(frame_t),
        tracked=np.asarray(tracked),
        wall_s=time.perf_counter() - wall0,
        images=images,
        failure=failure,
        loop=lc.finish() if lc is not None else {},
        closures=list(lc.closer.run_closures) if lc is not None else [],
        conditions=monitor.report(),
        active=active,
    )
