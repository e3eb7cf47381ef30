"""Settings of the sliding-window optimizer: :class:`WindowParams` (one frozen record; units in the names)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from viotb.vio.frontend import KltParams
from viotb.vio.keyframing import KeyframeParams
from viotb.vio.msckf_params import (
    RENDER_KLT_PIXEL_SIGMA_PX,
    RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX,
    SENSOR_MODELS,
)
from viotb.vio.stereo import StereoMatchParams
from viotb.vio.triangulation import TriangulationParams
from viotb.vio.zero_velocity import ZeroVelocityParams


@dataclass(frozen=True)
class WindowParams:
    """Sliding-window optimizer settings.

    Attributes:
        window_size: Keyframes in the window (8-10 as VINS-Mono / OKVIS).
        keyframing: Which frames become keyframes (:mod:`viotb.vio.keyframing`; at least every 3rd frame,
            or 10 px of parallax with the rotation since the last keyframe removed). Without the rotation
            compensation a spin made every frame a keyframe (fast-rotation recording: 77 % of the frames,
            51 ms median per frame; with it 29 % and 7-9 ms, ATE 2.73 -> 2.74 cm).
        min_track_length: Keyframes that must see a feature before it is triangulated into a landmark.
        max_landmarks: Most landmarks in the window (longest tracks first).
        pixel_sigma_px: Feature measurement noise (px).
        huber_threshold: Huber threshold on the whitened reprojection error norm (sigmas).
        outlier_threshold: Landmarks with any whitened reprojection error above this (sigmas) after the
            optimization are removed.
        outlier_chi2: Also remove, after the optimization, the landmarks whose whitened cost over all
            their views (generalized least squares under ``track_noise``) exceeds this quantile of
            chi-square with ``2 M - 3`` degrees of freedom (:class:`viotb.vio.window_reprojection.
            LandmarkOutlierTest`); None: the per-view rule only.
        max_iterations: Levenberg-Marquardt trial steps per keyframe (the solve's budget, counted in steps
            so the same seed gives the same estimate; a solve cut short continues from its values at the
            next keyframe). 4 steps in all moved the head-walk recording's ATE from 3.3 to 3.8 cm and 3
            aggressive's from 3.4 to 4.1 cm.
        keyframe_frame_iterations: Of those steps, the most the keyframe's own frame takes; a solve that has
            not converged by then goes on over the next frames that are not keyframes (``frame_iterations``
            steps each, from the values, damping and linearization it reached: taken in parts it makes the
            same steps as in one go, :func:`viotb.vio.window_solver.solve_steps`); its values are the
            estimate meanwhile, and its outliers and the marginalization of the oldest keyframe wait for its
            end. A keyframe that comes first ends it where it is and takes ``keyframe_frame_iterations +
            frame_iterations`` steps on its own frame (keyframes in a row would leave each solve one step).
            5 (all of ``max_iterations``: the solve ends on its keyframe's frame, the frames between
            keyframes only track and test). Session 13, quiet 2-core machine, 20 s KLT recordings at
            320x240, seed 0, wall time of ``feed_camera`` (``viotb eval`` ``ms_per_frame_*``), 1 step on
            the keyframe's frame and 2 on each next frame (the default before) -> 5: median / p99
            ``figure8`` 8.5 / 14.0 -> 5.1 / 22.2 ms, ``aggressive`` 10.8 / 21.2 -> 6.1 / 24.8, ``circle``
            9.1 / 15.0 -> 5.3 / 23.1, ``hover`` 8.9 / 14.8 -> 4.9 / 19.9, ``head-fast-turns`` 9.9 / 16.4 ->
            6.1 / 24.1; ATE equal or lower (1.47 -> 1.44, 2.39 -> 2.37, 1.28 -> 1.27, 0.25 -> 0.24, 3.39 ->
            3.38 cm), position NEES within 2 %. Split, 31-42 % of the frames being keyframes, nearly every
            frame carried some of a solve; whole, a frame between keyframes costs its front end and 0.4
            ms. Session 11 chose 1 on a loaded machine (p99 41-53 -> 25-43 ms in CPU time, median +2-8
            ms); there 3 steps and 1 per frame gave a p99 only 3-30 % lower; 2 and 1: head-look-around
            seed 1 3.17 -> 5.26 cm (solves cut by the next keyframe); 1 and 1: figure8 2.21 -> 2.86 cm,
            aggressive 1.35 -> 1.86 cm.
        frame_iterations: The most steps of that solve each following frame takes (above).
        initial_damping: Initial LM damping, relative to the diagonal.
        relative_tolerance: The iterations stop once a kept step lowers the cost by less than this fraction
            of it. 1e-4 rather than 1e-6: on the 12 s KLT recordings (figure-8, aggressive, fast rotation,
            circle, head walk) the ATE moved by at most 0.4 mm and the slowest frames (p99) took ~20 % less.
        min_cost_decrease: The iterations also stop, without taking the step, when its predicted cost
            decrease (``0.5 chi^2`` units, :func:`viotb.vio.window_solver.predicted_decrease`) is below this:
            the last linearization of a converged solve, which confirmed a negligible decrease, is saved.
            0.05 saved more but moved the head-walk ATE from 3.3 to 3.9 cm.
        first_estimate_jacobians: Evaluate the Jacobians of every factor on a keyframe that the
            marginalization prior holds at the keyframe's values when the prior first took it
            (:func:`viotb.vio.window_solver.linearize`), so the window gains no spurious information on
            global position and yaw. Off: on the 12 s KLT recordings it left the position NEES where it
            was and moved the head-walk ATE from 3.3 to 4.7 cm.
        repropagate_gyro_bias_rad_s: Re-integrate a preintegration when the gyro bias moved this far (rad/s)
            from its linearization point (first-order correction otherwise, Forster eq. 44).
        repropagate_accel_bias_m_s2: Same for the accelerometer bias (m/s^2).
        zero_velocity: When a keyframe is still (:mod:`viotb.vio.zero_velocity`: no speed gate, a chi-square
            gate of 16.92, two failed IMU tests in a row mean motion). It then gets a zero-velocity factor
            (sigma ``velocity_sigma_m_s``) and, after a still one, a no-motion factor on the positions (sigma
            ``velocity_sigma_m_s * dt``): at rest nothing triangulates. EuRoC V1_01 at rest, KLT, 3.2 s:
            4.1 cm drift without, 3.6 mm at most with both (MSCKF's ZUPT 0.9 mm).
        excitation_accel_bias_sigma_m_s2: Above this horizontal accelerometer-bias sigma (m/s^2) of the
            newest keyframe the estimator asks for excitation (:meth:`WindowEstimator.wants_excitation`).
        frontend: ``"klt"`` (images) or ``"sim"`` (``frame.features``).
        klt: KLT settings.
        stereo: Left-right matching settings of a stereo rig (:mod:`viotb.vio.frontend_stereo`). A 15 px
            window on 2 pyramid levels: each track starts from its previous stereo depth, and on the rendered
            headset look-around (320x240) it keeps the accuracy of 21 px / 3 levels (ATE 13.8 vs 13.5 mm)
            for 4 ms less CPU per frame.
        stereo_landmarks: On a stereo rig, triangulate a feature into a landmark as soon as one keyframe
            sees it in both cameras (its depth from the stereo baseline) instead of waiting for
            ``min_track_length`` keyframes.
        triangulation: Triangulation settings.
        max_cost_per_residual: Final cost of the IMU and reprojection residuals (prior excluded) per residual
            above which a keyframe counts as a cost blow-up.
        runaway_reject_ratio: A keyframe also counts as a blow-up when more than this fraction of its gated
            features (landmarks plus new candidates) were outliers or failed the triangulation's reprojection
            gate.
        runaway_min_features: Fewest gated features for that rule.
        blowup_keyframes: Consecutive blow-up keyframes that declare divergence.
        max_position_sigma_m: Position sigma (m) beyond which divergence is declared.
        midpoint_rotation: Turn each midpoint specific force of the preintegration by half its step's
            rotation (exact in a steady turn, ``tests/test_window_batch.py``; without it a body-frame error
            of 1/2 [w dt]x a per step). On 20 s KLT renders (seeds 0 / 1, ATE cm, off -> on): aggressive
            4.36 -> 3.09 / 3.46 -> 2.57 (NEES 30 -> 16 / 13 -> 8), head-look-around 2.66 -> 2.29 / 15.7 ->
            9.2, figure8 2.78 -> 2.63 / 3.25 -> 2.99, hover 0.44 -> 0.41 / 0.40 -> 0.37, circle 3.39 ->
            3.23 / 3.64 -> 3.98, head-fast-turns 2.62 -> 2.74 / 2.68 -> 2.73. On simulated streams (4
            seeds, mean mm) aggressive 25.2 -> 21.5, figure8 18.1 -> 17.5, circle 26.4 -> 28.4, fast
            rotation 22.0 -> 24.6.
        track_noise: Model each KLT track's error as white noise (``pixel_sigma_px``) plus a random walk
            clocked by its image motion (``klt.track_random_walk_px2_per_px``, the MSCKF's model): the views
            of a landmark are correlated and the reprojection factors are generalized least squares
            (:mod:`viotb.vio.window_reprojection`). Only with the ``klt`` front end. Off: on 12 s KLT
            renders (seed 0, ``keyframe_frame_iterations`` 4; position NEES / ATE cm, off -> on, 1 px
            white) aggressive 8.8 / 2.19 -> 3.1 / 2.19, head-look-around 4.0 / 1.25 -> 2.1 / 1.52, circle
            2.5 / 2.55 -> 1.6 / 2.57, figure8 1.9 / 2.35 -> 1.2 / 2.33, head-fast-turns 1.8 / 1.51 -> 1.0 /
            2.02, hover 0.27 / 0.41 -> 0.22 / 0.44; with 0.5 px white (thresholds kept in px) aggressive
            3.6 / 2.07, head-look-around 2.9 / 1.13, circle 2.2 / 2.61, figure8 1.8 / 2.45, head-fast-turns
            1.5 / 2.05, hover 0.28 / 0.36. It fixes aggressive's overconfidence, but the ATE of the fast
            turns grows by 0.5 cm and each linearization costs about 1.5-2x (the pose blocks of every pair
            of views).
        static_tilt_bias_sigma_m_s2: After a static initialization, couple the first prior's tilt and
            horizontal accelerometer bias (the static solve reads the bias as tilt,
            :mod:`viotb.vio.window_init`) and leave this 1-sigma (m/s^2) of the horizontal bias independent
            of the tilt; None: the initializer's independent variances (hover position NEES 0.12).
        estimate_extrinsics: Estimate every camera's ``R_BC``, ``p_BC`` online (:mod:`viotb.vio.window_calib`;
            variables of the window that marginalization keeps, with a prior of the sigmas below).
        extrinsic_sigma_rad: Prior sigma (rad) of the extrinsic rotation (per axis; the MSCKF's).
        extrinsic_sigma_m: Prior sigma (m) of the extrinsic translation (per axis).
        estimate_time_offset: Estimate the camera-IMU time offset online (one for all cameras).
        time_offset_sigma_s: Prior sigma (s) of the time offset.
        calibration_start_keyframes: The calibration's variables (and their prior) enter the window once it
            holds this many keyframes after an initialization; before, the files' calibration is fixed.
        imu_intrinsics: Estimate the IMU's correction matrices online (the MSCKF's model,
            :mod:`viotb.vio.imu_intrinsics`): ``"none"`` (default), ``"gyro"`` (``T_g``) or ``"gyro+accel"``
            (both). Variables of the window's calibration (:mod:`viotb.vio.window_calib`) entering the IMU
            factors through the preintegration's first-order Jacobians; with ``track_noise`` too.
        imu_intrinsic_sigma: Prior sigma of every entry of an estimated correction matrix (the MSCKF's).
    """

    window_size: int = 10
    keyframing: KeyframeParams = field(
        default_factory=lambda: KeyframeParams(
            every_n_frames=3, min_parallax_px=10.0, rotation_compensated=True
        )
    )
    min_track_length: int = 3
    max_landmarks: int = 150
    pixel_sigma_px: float = 1.0
    huber_threshold: float = 3.0
    outlier_threshold: float = 8.0
    outlier_chi2: float | None = None
    max_iterations: int = 5
    keyframe_frame_iterations: int = 5
    frame_iterations: int = 2
    initial_damping: float = 1e-4
    relative_tolerance: float = 1e-4
    min_cost_decrease: float = 0.01
    first_estimate_jacobians: bool = False
    repropagate_gyro_bias_rad_s: float = 0.01
    repropagate_accel_bias_m_s2: float = 0.2
    zero_velocity: ZeroVelocityParams = field(
        default_factory=lambda: ZeroVelocityParams(
            max_speed_m_s=float("inf"), chi2_gate=16.92, imu_failures_to_move=2
        )
    )
    excitation_accel_bias_sigma_m_s2: float = 0.02
    frontend: str = "klt"
    klt: KltParams = field(default_factory=KltParams)
    stereo: StereoMatchParams = field(default_factory=lambda: StereoMatchParams(win_size_px=15, max_level=2))
    stereo_landmarks: bool = True
    triangulation: TriangulationParams = field(default_factory=TriangulationParams)
    max_cost_per_residual: float = 100.0
    runaway_reject_ratio: float = 0.7
    runaway_min_features: int = 5
    blowup_keyframes: int = 5
    max_position_sigma_m: float = 100.0
    midpoint_rotation: bool = True
    track_noise: bool = False
    static_tilt_bias_sigma_m_s2: float | None = 0.01
    estimate_extrinsics: bool = False
    extrinsic_sigma_rad: float = 0.005
    extrinsic_sigma_m: float = 0.005
    estimate_time_offset: bool = False
    time_offset_sigma_s: float = 0.005
    calibration_start_keyframes: int = 10
    imu_intrinsics: str = "none"
    imu_intrinsic_sigma: float = 0.005

    def __post_init__(self) -> None:
        """Reject a track-test quantile outside (0, 1) (ValueError naming the field and value)."""
        if self.outlier_chi2 is not None and not 0.0 < self.outlier_chi2 < 1.0:
            raise ValueError(f"WindowParams.outlier_chi2 must be in (0, 1) or None, got {self.outlier_chi2}")

    def with_render_klt_noise(self) -> WindowParams:
        """These settings with the KLT noise model measured on this project's renders (white and walk).

        The MSCKF's model (:data:`~viotb.vio.msckf_params.RENDER_KLT_PIXEL_SIGMA_PX`, 0.035 px, and
        :data:`~viotb.vio.msckf_params.RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX`, as generalized least squares
        over each landmark's views: ``track_noise``); the Huber and outlier thresholds stay in sigmas. For
        the KLT front end on rendered recordings with the right calibration. Measured (README "Consistency
        per scenario", 20 s KLT renders at 320x240, seeds 0-2): more accurate on 12 of 15 runs (``figure8``
        ATE 1.44 / 1.32 / 2.25 -> 0.72 / 0.69 / 1.49 cm) and overconfident (position NEES 1.4-60, against
        0.07-8.9 told 1 px). ``aggressive``'s part is the IMU's scale and misalignment, which the window
        does not estimate: recorded without them, its NEES is 3.2 (ATE 0.47 cm). Slower: p99 33-43 ms per
        frame (17-26 ms told 1 px), the views of a landmark being correlated. Not a default, for that and
        the MSCKF's reasons, and not with :meth:`with_online_calibration` (whose factors need white track
        noise).
        """
        return replace(
            self,
            pixel_sigma_px=RENDER_KLT_PIXEL_SIGMA_PX,
            track_noise=True,
            klt=replace(self.klt, track_random_walk_px2_per_px=RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX),
        )

    def with_sensor_model(self, name: str) -> WindowParams:
        """``"default"``: these settings; ``"render"``: :meth:`with_render_sensor_model` (else ValueError)."""
        if name not in SENSOR_MODELS:
            raise ValueError(f"unknown sensor model {name!r}; allowed: {', '.join(SENSOR_MODELS)}")
        return self if name == "default" else self.with_render_sensor_model()

    def with_render_sensor_model(self) -> WindowParams:
        """These settings with the sensor model measured on this project's rendered recordings.

        The MSCKF's model (:meth:`viotb.vio.msckf_params.MsckfParams.with_render_sensor_model`) where the
        window has its parts: the KLT noise of the renders (:meth:`with_render_klt_noise`, white and
        random walk) and both IMU correction matrices estimated online (``imu_intrinsics="gyro+accel"``;
        the window's keyframes are already rotation-compensated and it has no update gap); and the
        landmarks whose views err by more than 5 sigmas (``outlier_threshold``, 0.18 px) leave the window:
        8 sigmas, 0.28 px at this noise, kept the KLT tracks the model does not describe; so do those
        whose whole track fails its chi-square test at 95 % (``outlier_chi2``, the MSCKF's per-feature
        gate): under the correlated track noise a single view measured against the white part cannot
        tell a drifting track from a bad one (40 s KLT, seeds 0-4: ``hover`` position NEES 5.04 -> 2.49,
        ``head-look-around`` 838 -> 576; README session 18); and a keyframe at least every 10th frame
        instead of every 3rd (``keyframing.every_n_frames``): on a head turning in place every 3rd frame
        was a keyframe, so the 10 keyframes spanned 1 s and about 2 cm of camera travel, and the window
        was sure of a scale the motion does not show (``head-look-around`` 576 -> 2.64, ATE 4.88 -> 0.95
        cm; ``head-fast-turns`` ATE 0.86 -> 1.15 cm, ``hover`` NEES 2.49 -> 1.27). Told the render noise
        alone the window is overconfident where the motion is fast, by the simulated IMU's 0.2 % scale
        and 0.05 deg misalignment (``aggressive`` position NEES 126 on a 40 s seed; 2.8 recorded without
        those errors; 2.1 with the matrices estimated: README "Consistency per scenario", session 17). For
        the renders with the right calibration only, and not with :meth:`with_online_calibration` (its
        camera terms need white track noise).
        """
        model = replace(self.with_render_klt_noise(), imu_intrinsics="gyro+accel")
        spaced = replace(model.keyframing, every_n_frames=10)
        return replace(model, outlier_threshold=5.0, outlier_chi2=0.95, keyframing=spaced)

    def with_online_calibration(
        self,
        time_offset_sigma_s: float = 0.02,
        extrinsic_sigma_rad: float = 0.05,
        extrinsic_sigma_m: float | None = None,
    ) -> WindowParams:
        """These settings with the time offset and the extrinsics estimated online (the MSCKF's wide priors).

        :meth:`viotb.vio.msckf_params.MsckfParams.with_online_calibration`'s defaults (the translation keeps
        its 5 mm prior unless ``extrinsic_sigma_m`` is given: 2 cm off in the file is then only half found,
        ``tests/test_window_calib_streams.py``); the calibration that moves names the cause
        (:class:`viotb.vio.health.HealthMonitor`).
        """
        return replace(
            self,
            estimate_time_offset=True,
            time_offset_sigma_s=time_offset_sigma_s,
            estimate_extrinsics=True,
            extrinsic_sigma_rad=extrinsic_sigma_rad,
            extrinsic_sigma_m=self.extrinsic_sigma_m if extrinsic_sigma_m is None else extrinsic_sigma_m,
        )


def track_noise_q(p: WindowParams) -> float:
    """``FactorWeights.track_q``: the KLT track random walk per px over the white variance (0 when off).

    ``p.klt.track_random_walk_px2_per_px / p.pixel_sigma_px^2`` with ``p.track_noise`` and the ``klt`` front
    end (the MSCKF's rule, :func:`viotb.vio.msckf_update.track_random_walk_px2_per_px`), else 0.
    """
    if not p.track_noise or p.frontend != "klt":
        return 0.0
    return p.klt.track_random_walk_px2_per_px / p.pixel_sigma_px**2
