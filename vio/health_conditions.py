"""The health monitor's vocabulary: condition names, their thresholds (:class:`HealthParams`), the record.

The monitor (:class:`viotb.vio.health.HealthMonitor`) raises these named conditions (lesson 000, "VIO fails in
characteristic, recognizable ways"):

1. ``insufficient_excitation`` -- while the platform translates (estimated speed above
   ``min_excitation_speed_m_s``), over a sliding window the world-frame acceleration (the accelerometer
   rotated by the latest estimated attitude, propagated with the gyro between frames, bias and gravity
   removed, averaged over ``excitation_block_s`` blocks against the noise) and the gyro norm stay below
   thresholds. A quadrotor turns its specific force with its thrust, so a body-frame test misses a
   coordinated turn (measured: body-axis std 0.094 m/s^2 on a figure-8 with 1.3 m/s^2 accelerations).
   Scale is only observable through acceleration, so an error in it is never corrected and the position
   error grows with the distance flown ("drifts at constant velocity -> no excitation"). At rest (before
   initialization, on the ground, in a still hover) there is nothing to scale, so the flag waits for motion.
2. ``feature_poverty`` -- fewer than ``min_tracked_features`` tracked for ``poverty_frames`` frames in a row.
3. ``imu_saturation`` -- samples flagged ``saturated`` by the sensor (count and first time in the evidence).
4. ``time_sync_or_extrinsic_suspected`` -- while the platform moves, the mean normalized innovation
   squared per degree of freedom (``HealthStatus.nis_per_dof_all``, every triangulated feature of an update,
   rejected ones included) over a window of updates stays above ``max_nis_per_dof`` times its consistent value
   1 ("worsens with speed -> time-sync / extrinsics"). A camera-IMU time offset ``dt`` moves the features by
   ``~ f (|omega| + |v| / Z) dt`` and a rotation error of the extrinsics rotates every ray; both vanish at
   rest, hence the motion gate. The two causes are *not* told apart: measured on the figure-8 streams of
   :mod:`viotb.envs.scenarios.failures`, the Pearson correlation over the window between the NIS and the
   angular or linear speed is near zero or negative for both (the filter absorbs the part of the error that is
   constant over its window -- a time offset on uniform motion is a rigid shift of the trajectory -- and what
   is left follows the *changes* of the motion), so the correlations are only reported in the evidence, and
   the condition is named for both causes. A least-squares fit of the per-update NIS on ``a + b |omega| + c
   |v|`` over the whole 8 s run (seeds 0-3, 10 ms offset vs 2 deg extrinsic) does not split them either: the
   angular-rate slope ``b`` is negative for *both* causes (offset -0.53 / -0.07 / -1.21 / -0.60, extrinsic
   -0.31 / -0.09 / -0.25 / -0.06 per rad/s), so the expected "offset grows with the rate" signature is absent;
   the speed slope ``c`` is 0.36 / -0.09 /
   0.64 / 0.29 per m/s with the offset and 0.06 / -0.01 / 0.04 / 0.02 with the extrinsic error (nominal
   0.00 / -0.00 / -0.01), so a threshold on ``c`` misnames seed 1 of the offset; and the extrinsic error's
   NIS does persist in the slowest third of the updates (1.32-1.47) but so does the offset's (1.61-2.18).
   What does tell them apart is the fix itself: with online calibration of both the time offset and the
   extrinsics on, the estimate that moves names the cause (conditions 7 and 8), so the evidence of this
   condition says to turn both on.
5. ``initialization_failure`` -- no state after ``init_timeout_s`` of IMU data, or the first estimate's
   specific force at rest disagrees with 9.81 m/s^2 (gravity norm check), or the first gyro bias estimate
   is far beyond the prior.
6. ``divergence`` -- ``health.diverged``, a non-finite estimate/covariance, a position sigma growing
   beyond ``max_position_sigma_m`` (the covariance "balloons"), or images the state cannot explain: for
   ``max_unused_s`` the platform moves (estimated speed above ``min_sync_speed_m_s``) past at least
   ``min_tracked_features`` tracked features and not one enters an update (they fail triangulation or the
   gate). Measured: an in-flight start with a confident wrong state (3 deg of tilt, 20 % scale, 0.2 deg /
   1 % sigmas) keeps ~100 tracks and uses none while it drifts 20 m on the IMU; nothing else fired.
7. ``time_offset_miscalibrated`` -- the estimator calibrates the time offset online
   (``HealthStatus.calibration``) and its estimate has moved from the given value by more than
   ``calib_min_sigmas`` of its own sigma and more than ``min_time_offset_change_s``: the given offset is
   wrong (the filter is fixing it; store the estimate).
8. ``extrinsic_miscalibrated`` -- the same for the camera-IMU rotation (``min_rotation_change_rad``) or
   translation (``min_translation_change_m``). Measured on the 8 s figure-8 streams (seed 0) with both
   calibrations on: a 10 ms offset gives 10.05 +- 0.08 ms and 0.06 deg of rotation; a 2 deg rotation error
   gives (-1.43, 0.00, -1.35) +- 0.02-0.03 deg (truth (-1.41, 0, -1.41)) and 0.05 ms; nominal 0.05 ms and
   0.06 deg.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CONDITION_NAMES = (
    "insufficient_excitation",
    "feature_poverty",
    "imu_saturation",
    "time_sync_or_extrinsic_suspected",
    "initialization_failure",
    "divergence",
    "time_offset_miscalibrated",
    "extrinsic_miscalibrated",
)
"""Every name :class:`viotb.vio.health.HealthMonitor` can raise."""


@dataclass(frozen=True)
class HealthParams:
    """Thresholds of :class:`viotb.vio.health.HealthMonitor` (units in the names).

    Attributes:
        excitation_window_s: Sliding window (s) of the excitation test.
        excitation_block_s: Block length (s) over which the world acceleration is averaged (the noise of a
            block mean is the sample noise over sqrt(samples per block)).
        min_accel_m_s2: Excitation needs the RMS over the window of the block-mean world acceleration norm
            above this (m/s^2).
        min_gyro_norm_rad_s: ...or a mean gyro norm above this (rad/s) while the accel test also fails
            (rotation alone does not make scale observable, so both must be low to raise the flag).
        min_excitation_speed_m_s: The flag is raised only while the latest estimated speed (m/s) exceeds
            this (a scale error moves the position only in proportion to the distance flown).
        excitation_hold_s: The test must fail continuously for this long (s) before the flag is raised.
        excitation_check_s: The excitation test runs every this many seconds of IMU time (each run reads
            the whole window; at every 200 Hz sample it cost the monitor ~0.3 ms per sample).
        min_tracked_features: Tracked-feature count below which a frame counts as poor.
        poverty_frames: Consecutive poor frames that raise ``feature_poverty``.
        min_saturated_samples: Saturated IMU samples that raise ``imu_saturation``.
        speed_window_frames: Updates (frames with a finite ``nis_per_dof_all``) in the NIS window.
        max_nis_per_dof: Mean NIS per dof over the window above which a time-sync / extrinsic error is
            suspected (1 for a consistent filter; measured window means 0.92-1.03 on nominal hover, circle
            and figure-8 streams, up to 1.53 with a 2 deg extrinsic error and 2.49 with a 10 ms offset on a
            figure-8 at 2x speed, and up to 1.15-1.2 on a nominal aggressive 5 rad/s, 4 m/s manoeuvre, whose
            few fast-moving features leave the filter mildly inconsistent: 1.15 raised a false alarm there;
            1.25 names the extrinsic error 0.1-0.5 s later, seeds 0-2).
        min_sync_speed_m_s: The window's mean linear speed (m/s) must exceed this...
        min_sync_rate_rad_s: ...or its mean angular speed (rad/s) this (the errors vanish at rest).
        sync_min_features: Updates with fewer gated features (used + rejected) are ignored.
        nis_per_dof_expected: NIS per dof of a consistent run; the window mean is divided by it before the
            ``max_nis_per_dof`` test. 1 when the filter is told the front end's real pixel noise;
            ``(sigma_real / sigma_told)^2`` when not (``viotb eval`` runs the MSCKF at 1 px on KLT tracks of
            ~0.3 px: :func:`viotb.envs.data.diagnosis.expected_nis_per_dof`).
        init_timeout_s: Seconds of IMU data without an estimate that raise ``initialization_failure``.
        gravity_norm_tol_m_s2: Largest allowed difference (m/s^2) between the mean accelerometer norm in the
            first still second and 9.81 when the estimator initializes (a miscalibrated accelerometer or a
            moving start makes the init gravity wrong).
        max_init_gyro_bias_rad_s: A gyro bias (rad/s) estimated at init beyond this is implausible.
        max_position_sigma_m: Position sigma (m) beyond which the covariance is said to balloon.
        max_unused_s: Seconds of motion past enough tracked features without any used in an update that
            count as divergence.
        calib_min_sigmas: An online calibration estimate must move by more than this many of its sigmas...
        min_time_offset_change_s: ...and by more than this (s) to raise ``time_offset_miscalibrated``;
        min_rotation_change_rad: ...by more than this (rad, norm) or...
        min_translation_change_m: ...this (m, norm) to raise ``extrinsic_miscalibrated``.
    """

    excitation_window_s: float = 2.0
    excitation_block_s: float = 0.25
    min_accel_m_s2: float = 0.1
    min_gyro_norm_rad_s: float = 0.2
    min_excitation_speed_m_s: float = 0.2
    excitation_hold_s: float = 0.5
    excitation_check_s: float = 0.05
    min_tracked_features: int = 20
    poverty_frames: int = 5
    min_saturated_samples: int = 1
    speed_window_frames: int = 30
    max_nis_per_dof: float = 1.25
    min_sync_speed_m_s: float = 0.3
    min_sync_rate_rad_s: float = 0.3
    sync_min_features: int = 5
    nis_per_dof_expected: float = 1.0
    init_timeout_s: float = 5.0
    gravity_norm_tol_m_s2: float = 0.3
    max_init_gyro_bias_rad_s: float = 0.2
    max_position_sigma_m: float = 10.0
    max_unused_s: float = 2.0
    calib_min_sigmas: float = 5.0
    min_time_offset_change_s: float = 0.002
    min_rotation_change_rad: float = float(np.deg2rad(0.5))
    min_translation_change_m: float = 0.02


@dataclass(frozen=True)
class Condition:
    """A named condition raised by the monitor.

    Attributes:
        name: One of :data:`CONDITION_NAMES`.
        t_s_first: Time (s, IMU clock) it was first raised.
        evidence: Human-readable numbers behind it.
    """

    name: str
    t_s_first: float
    evidence: str
