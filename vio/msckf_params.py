"""MSCKF settings: :class:`MsckfParams` (one frozen record; units in the field names)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from viotb.vio.frontend import KltParams
from viotb.vio.keyframing import KeyframeParams
from viotb.vio.propagator import Integration
from viotb.vio.stereo import StereoMatchParams
from viotb.vio.triangulation import TriangulationParams
from viotb.vio.zero_velocity import ZeroVelocityParams

RENDER_KLT_PIXEL_SIGMA_PX = 0.035
"""White pixel noise (px) of the anchored KLT tracks on this project's renders (320x240), for the MSCKF.

Measured by ``benchmarks/klt_track_error.py`` (``fit_core``: the robust, MAD-based variance of each track's
error against the true projection of its first 3-D point, in windows of up to 40 frames, fitted as
``2 s_w^2 + q p`` over the image path ``p``) on 20 s recordings, seed 0: ``s_w`` 0.032 / 0.030 / 0.032 /
0.027 px on ``figure8`` / ``circle`` / ``aggressive`` / ``hover``; 0.035 px is the largest, rounded up. The
errors are heavy tailed (4-12 % of the samples beyond 5 model sigmas: corners on occluding contours, which
are no 3-D point, and tracks that slip); the filter's chi-square gate removes most of those features.
Checked in the filter (seeds 0-2): the mean NIS per dof of the gated features is 0.5-0.65 with this model
(under 1: not overconfident), told 1 px 0.005-0.013. Not a default: real images and other image sizes
were not measured, and on the renders a wrong calibration in the file (``fail-extrinsic``: 2 deg,
``fail-time-offset``: 10 ms, 10 s) makes the filter reject most features and declare divergence within
seconds, where told 1 px it flies on and the health monitor names the cause (its NIS reference,
``viotb.envs.data.diagnosis``, is for 1 px). :meth:`MsckfParams.with_render_klt_noise` applies it.
"""

RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX = 0.0003
"""Random walk (px^2 per px of image motion) of the anchored KLT tracks on the renders, with the above.

Between two measurements of it: the robust fit above gives 0.00012 / 0.00008 / 0.00004 / 0.00003 px^2/px
on ``figure8`` / ``circle`` / ``aggressive`` / ``hover`` (the typical track); the second moments of the
tracks away from depth edges (less than 2 % depth change 3 px around the first point; the largest 0.5 %
cut) 0.0004 / 0.0002 / 0.0001 / 0.0000, which includes the moderately wrong tracks that pass the gate. With
the robust value alone (0.03 px, 0.0001) the filter diverged on one of 20 recordings (``figure8`` seed 4:
its first update, 0.5 s after the static initialization, moved the velocity by 4 cm/s against a 1 cm/s
sigma, and 10 frames of rejected features followed); with 0.035 px and 0.0003 it does not (ATE 1.0 cm,
NEES 3.4). Over all tracks and without a cut the fit is 0.11 on ``figure8``: the tail the gate removes.
"""

SENSOR_MODELS = ("default", "render")
"""Sensor models of :meth:`MsckfParams.with_sensor_model` (``viotb eval / fly --sensor-model``)."""


@dataclass(frozen=True)
class MsckfParams:
    """MSCKF settings (defaults near open_vins' EuRoC configuration).

    Attributes:
        max_clones: Clones in the sliding window (10-15).
        excitation_accel_bias_sigma_m_s2: Above this horizontal accelerometer-bias sigma (m/s^2) the filter
            asks for excitation (:meth:`MsckfEstimator.wants_excitation`).
        keyframing: Which frames become clones (and update); the front end still tracks every frame
            (:mod:`viotb.vio.keyframing`; at least every 6th frame, or 3 px of parallax).
            ``rotation_compensated=True`` measures the parallax with the rotation since the newest clone
            removed (from the propagated attitude); off by default: on 40 s KLT recordings it halves the
            mono ``head-look-around`` drift but costs ``hover`` and ``head-fast-turns`` a third more ATE
            (README "Consistency per scenario", session 15).
        max_features_per_update: Most features used in one update (longest tracks first).
        min_track_length: Fewest observations (views of every camera, on a stereo rig) for a feature to be
            used.
        pixel_sigma_px: Feature measurement noise (px), white part. 1 px: real images, unmeasured (the KLT
            renders: :data:`RENDER_KLT_PIXEL_SIGMA_PX`, 0.035 px, :meth:`with_render_klt_noise`).
        chi2_multiplier: Multiplier on the 95 % chi-square gate of each feature.
        integration: IMU integration method.
        use_fej: First-estimates Jacobians (FEJ) in the IMU propagation.
        update_linearization: Where the MSCKF update's Jacobians are evaluated. ``"current_oc"`` (default):
            at the current clone estimates (where the residual is), then projected so that they annihilate
            the four unobservable directions at the clones' first estimates (observability-constrained
            update, Hesch et al. TRO 2014). ``"first_estimates"``: at the first estimates (open_vins
            ``do_fej``); measured overconfident here: clones move 1-7 cm and 0.1-0.8 deg from their first
            estimates within the window, and with ~1000 rows per update that Jacobian mismatch exceeds the
            claimed precision. Position ANEES over 20 seeds x 20 s of ``tests/test_msckf.py``'s synthetic
            flight (95 % band [2.02, 4.16], 3 expected): 4.53 first estimates, 3.37 current, 3.21
            current_oc; over 12 seeds x 60 s (band [1.77, 4.53]): 3.97, 4.35 (orientation NEES 10.1: yaw
            becomes spuriously observable) and 3.52. ``"current"``: plain EKF Jacobians. Only used when
            ``use_fej`` is True; otherwise ``"current"``.
        frontend: ``"klt"`` (images) or ``"sim"`` (``frame.features``).
        klt: KLT settings.
        stereo: Left-right matching settings of a stereo rig (:mod:`viotb.vio.frontend_stereo`). A 15 px
            window on 2 pyramid levels: each track starts from its previous stereo depth, and on the rendered
            headset look-around (320x240) it keeps the accuracy of 21 px / 3 levels (ATE 13.8 vs 13.5 mm)
            for 4 ms less CPU per frame.
        triangulation: Triangulation settings.
        zero_velocity: When a zero-velocity update (ZUPT) is made (:mod:`viotb.vio.zero_velocity`; only
            until the platform first moves, speed gate 0.2 m/s, chi-square gate from ``chi2_multiplier``).
        zupt_update_accel: Let the ZUPT's accelerometer rows update tilt and accelerometer bias (they always
            take part in the stillness test).
        estimate_extrinsics: Estimate ``R_BC, p_BC`` online.
        extrinsic_sigma_rad: Prior sigma (rad) of the extrinsic rotation.
        extrinsic_sigma_m: Prior sigma (m) of the extrinsic translation.
        estimate_time_offset: Estimate the camera-IMU time offset online.
        time_offset_sigma_s: Prior sigma (s) of the time offset.
        imu_intrinsics: Online IMU intrinsics (:mod:`viotb.vio.imu_intrinsics`): ``"none"`` (default),
            ``"gyro"`` (the 3x3 gyro correction, 9 states) or ``"gyro+accel"`` (and the accelerometer's, 18).
            On by default in the headset runner (``envs/run/headset.py``). Measured on the drone's
            ``aggressive`` (rendered KLT, 20 s, seeds 0 / 1 / 2, the raw part's 1 % scale and 0.5 deg
            misalignment): with :meth:`with_render_klt_noise` ATE 1.8 / 2.2 / 1.4 cm and position NEES
            57 / 76 / 11 without, 0.60 / 0.48 / 0.67 cm and 3.3 / 2.1 / 3.4 with ``"gyro"`` (``"gyro+accel"``
            0.61 / 0.47 / 0.51 cm, 3.4 / 2.3 / 1.4); told 1 px, 2.2 / 2.9 / 1.6 cm (NEES 3.9 / 7.3 / 1.5) ->
            1.1 / 1.1 / 1.1 cm (0.61 / 0.50 / 0.49); the gentler ``figure8`` / ``hover`` (seed 0, render
            noise) 0.94 / 0.35 cm, NEES 3.9 / 1.9 -> 0.84 / 0.39 cm, 2.8 / 1.8. Off by default so that the
            drone baselines stay put; the covariance grows by 9 states (the update costs ~10-15 % more).
        imu_intrinsic_sigma: Prior sigma of every entry of an estimated correction matrix (dimensionless;
            0.005: 0.5 % scale factor, 0.29 deg misalignment), about the identity.
        max_position_sigma_m: Position sigma (m) beyond which the filter declares divergence.
        runaway_frames: Consecutive frames with most features failing the gate that declare divergence.
        runaway_min_features: Fewest gated features for a frame to count towards ``runaway_frames``.
        runaway_reject_ratio: Rejected fraction above which a frame counts as runaway.
        max_slam_features: Most persistent (SLAM) landmarks kept in the state (:mod:`viotb.vio.slam_features`;
            tracks longer than the window, with a cam1 view on a stereo rig). 0 (default): pure MSCKF.
            Measured (README, headset section): 15-25 % off the stereo headset world lock with simulated
            features, no change with KLT, and overconfident on a mono KLT drone figure-8 (seed 1: ATE 2.6
            -> 4.9 cm, NEES 1.2 -> 12.7), so it is off everywhere.
        slam_max_init_sigma_ratio: A track becomes a landmark only if its initial position sigma (largest
            axis) is below this fraction of its distance from the newest camera. A poorly conditioned depth
            (stereo only, little parallax) is far from Gaussian as a point in W and its linearized updates
            make the filter overconfident (why open_vins prefers an anchored inverse depth). Headset
            look-around, simulated features, 8 s, 25 landmarks, world lock (mm) on seeds 0 / 1 with the
            calibrated IMU: no gate 4.1 / 6.0 (NEES 2.6 / 5.0), 0.1: 4.4 / 5.9, 0.05: 4.0 / 4.4 (2.3 /
            3.1); without landmarks 5.2 / 5.2. Not a general rule: on a mono KLT drone figure-8 (20 s)
            the gate makes it worse (ATE 2.8 cm, NEES 2.6 without; 4.2 cm, NEES 7.1 with).
        update_kernels: How the MSCKF update's per-feature stages run: ``"numba"`` (compiled loops,
            :mod:`viotb.vio.msckf_kernels` and :mod:`viotb.vio.msckf_kernels_tri`: triangulation,
            residuals, Jacobians, whitening, null space and chi-square gate in two calls) or ``"numpy"``
            (the batched reference). They agree to round-off (README "MSCKF per frame", session 10).
        right_pixel_sigma_px: White pixel noise (px) of cam1's observations on a stereo rig; None (default):
            ``pixel_sigma_px``. Cam1's observation of a track is matched from cam0's at every frame
            (:mod:`viotb.vio.frontend_stereo`), so its error is cam0's plus the left-right match's. The
            track walk of cam1's rows scales with it (``klt.track_random_walk_px2_per_px`` times
            ``(right_pixel_sigma_px / pixel_sigma_px)^2``); SLAM landmarks' cam1 rows use it too
            (:func:`viotb.vio.msckf_update.right_row_weight`).
        max_update_gap_s: Longest time (s) without an update (ZUPT or features) after which the features
            seen in the oldest clone are used although the window is not full. None (default): only when a
            clone leaves, as open_vins does. With clones spaced by translation (``rotation_compensated``)
            a slow start fills the window in seconds, and the first update after the still phase then
            comes late and too strong (README "Loop closure against its targets", session 16).
        static_tilt_bias_sigma_m_s2: After a static initialization, couple the filter's tilt and horizontal
            accelerometer-bias errors (:func:`viotb.vio.window_init.couple_static_tilt_bias`, as the window
            optimizer does) and leave this 1-sigma (m/s^2) of the horizontal bias independent of the tilt.
            None (default): the independent variances the initializer reports.
    """

    max_clones: int = 11
    keyframing: KeyframeParams = field(default_factory=KeyframeParams)
    excitation_accel_bias_sigma_m_s2: float = 0.02
    max_features_per_update: int = 50
    min_track_length: int = 3
    pixel_sigma_px: float = 1.0
    chi2_multiplier: float = 1.0
    integration: Integration = Integration.RK4
    use_fej: bool = True
    update_linearization: str = "current_oc"
    frontend: str = "klt"
    klt: KltParams = field(default_factory=KltParams)
    stereo: StereoMatchParams = field(default_factory=lambda: StereoMatchParams(win_size_px=15, max_level=2))
    triangulation: TriangulationParams = field(default_factory=TriangulationParams)
    zero_velocity: ZeroVelocityParams = field(default_factory=ZeroVelocityParams)
    zupt_update_accel: bool = False
    estimate_extrinsics: bool = False
    extrinsic_sigma_rad: float = 0.005
    extrinsic_sigma_m: float = 0.005
    estimate_time_offset: bool = False
    time_offset_sigma_s: float = 0.005
    imu_intrinsics: str = "none"
    imu_intrinsic_sigma: float = 0.005
    max_position_sigma_m: float = 100.0
    runaway_frames: int = 10
    runaway_min_features: int = 5
    runaway_reject_ratio: float = 0.7
    max_slam_features: int = 0
    slam_max_init_sigma_ratio: float = 0.05
    update_kernels: str = "numba"
    right_pixel_sigma_px: float | None = None
    static_tilt_bias_sigma_m_s2: float | None = None
    max_update_gap_s: float | None = None

    def __post_init__(self) -> None:
        """Reject an unknown ``update_kernels`` (ValueError naming the allowed ones)."""
        if self.right_pixel_sigma_px is not None and not self.right_pixel_sigma_px > 0.0:
            raise ValueError(
                f"MsckfParams.right_pixel_sigma_px must be > 0, got {self.right_pixel_sigma_px!r}"
            )
        if self.update_kernels not in ("numba", "numpy"):
            raise ValueError(
                f"MsckfParams.update_kernels must be 'numba' or 'numpy', got {self.update_kernels!r}"
            )

    def with_render_klt_noise(self) -> MsckfParams:
        """These settings with the KLT noise model measured on this project's renders (white and walk).

        :data:`RENDER_KLT_PIXEL_SIGMA_PX` and :data:`RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX`; for the KLT
        front end on rendered recordings with the right calibration (README "Consistency per scenario").
        """
        return replace(
            self,
            pixel_sigma_px=RENDER_KLT_PIXEL_SIGMA_PX,
            klt=replace(self.klt, track_random_walk_px2_per_px=RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX),
        )

    def with_sensor_model(self, name: str) -> MsckfParams:
        """``"default"``: these settings; ``"render"``: :meth:`with_render_sensor_model` (else ValueError)."""
        if name not in SENSOR_MODELS:
            raise ValueError(f"unknown sensor model {name!r}; allowed: {', '.join(SENSOR_MODELS)}")
        return self if name == "default" else self.with_render_sensor_model()

    def with_render_sensor_model(self) -> MsckfParams:
        """These settings with the sensor model measured on this project's rendered recordings.

        Four parts, three for a cause of the inconsistency on the renders (README "Consistency per
        scenario", session 16): the KLT noise the tracks have there (:meth:`with_render_klt_noise`; the
        default 1 px is ~30x it, so the filter is underconfident); both IMU correction matrices estimated
        online (``imu_intrinsics="gyro+accel"``: the simulated IMU's 0.2 % scale and 0.05 deg
        misalignment, which make the filter overconfident on fast motion once it is told the true pixel
        noise); and clones spaced by translation (``keyframing.rotation_compensated``: a head turning in
        place otherwise makes every frame a clone and the window too short to triangulate), with a clone
        whenever 15 % of the last one's features are gone (``min_shared_fraction`` 0.85, which fast turns
        need once rotation no longer makes clones), and the oldest clone's features used after 0.5 s
        without an update (``max_update_gap_s``: spaced clones fill the window slowly after a still start,
        and the first update then came late and too strong: a divergence at takeoff in the pillars scene).
        On 40 s KLT recordings (seeds 0-4 of seven scenarios) the mean position NEES per scenario is
        1.77-2.73 on six and 5.68 on ``head-look-around``, where the defaults give 0.36-6.63, and the ATE
        is 1.9-6.3x lower. For the renders with the right calibration only: a 10 ms time offset in the file
        makes it reject most features and declare divergence (the defaults fly on and the health monitor
        names the cause; with online calibration it finds and names both errors).
        """
        return replace(
            self.with_render_klt_noise(),
            imu_intrinsics="gyro+accel",
            keyframing=replace(self.keyframing, rotation_compensated=True, min_shared_fraction=0.85),
            max_update_gap_s=0.5,
        )

    def with_online_calibration(
        self, time_offset_sigma_s: float = 0.02, extrinsic_sigma_rad: float = 0.05
    ) -> MsckfParams:
        """These settings with the time offset and the extrinsics estimated online (wide priors).

        The fix of the time-sync / extrinsic failure mode; with both on, the calibration that moves names
        the cause (:class:`viotb.vio.health.HealthMonitor`).
        """
        return replace(
            self,
            estimate_time_offset=True,
            time_offset_sigma_s=time_offset_sigma_s,
            estimate_extrinsics=True,
            extrinsic_sigma_rad=extrinsic_sigma_rad,
        )
