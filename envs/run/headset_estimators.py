"""What the headset's estimators are told: the MSCKF's settings, the IMU noise, the monitor's NIS reference.

:data:`HEADSET_MSCKF` (a clone at every frame, the KLT noise and the gyro intrinsics, chosen on the stereo
look-around), :func:`default_gyro_noise_inflation` / :func:`estimator_imu_noise` (the gyro noise an
estimator that does not model the part's scale and misalignment is told), and
:func:`headset_health_params` (the health monitor's reference NIS on the headset's KLT renders).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from viotb.vio.frontend import KltParams
from viotb.vio.health import HealthParams
from viotb.vio.keyframing import KeyframeParams
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.types import ImuNoise

# The MSCKF's default keyframe rule (a clone every 6th frame unless the view moved 3 px) suits a drone; on a
# headset it starves the filter: a seated head moves < 3 px, so a clone comes every 0.2 s, no feature is
# lost, the 11-clone window takes 2.2 s to fill before the first update (the still rig drifted 45 mm, then
# jumped back 70 mm), and afterwards every update lands on a 5 Hz saw-tooth the 1 kHz pose shows as jitter.
# A clone at every frame updates at 30 Hz after 11 frames (headset-still, 8 s, stereo: ATE 16.8 -> 4.2 mm,
# max 68 -> 6.7 mm, jitter 6.3 -> 0.9 mm).
#
# The KLT noise the headset's filter is told starts from the one measured on the anchored tracks of this
# project's renders (``benchmarks/klt_track_error.py``, robust core fit, 20 s drone recordings: white
# 0.027-0.032 px, walk 0.00003-0.00012 px^2/px; the drone model built on it, with its margins, is
# ``msckf_params.RENDER_KLT_PIXEL_SIGMA_PX`` / ``RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX``). The headset's
# own margin was chosen on the stereo look-around, seeds 0-2: 0.05 px and 0.0002 px^2/px (0.1 px with
# 0.0005 held seed 2 to 7.2 mm; 0.05 px with 0.001 to 7.4 mm). Told 0.5 px and 0.005 px^2/px (before), the
# filter weighted its cameras far below what they deliver and drifted on the IMU: the stereo look-around
# (20 s, seeds 0 / 1 / 2) held the world to 6.6 / 9.8 / 16.7 mm, now 4.9 / 4.3 / 4.2 mm (NEES 0.34 / 0.85
# / 1.79 -> 2.5 / 2.6 / 2.4; README "Headset tracking").
#
# The gyro's 3x3 scale/misalignment matrix is estimated online (``imu_intrinsics="gyro"``,
# :mod:`viotb.vio.imu_intrinsics`, prior sigma 0.005 per entry). On the stereo KLT look-around (20 s, seeds
# 0 / 1 / 2) the world lock / max error went from 4.9 / 11.1, 4.3 / 8.1, 4.2 / 8.5 mm (NEES 3.0 / 2.6 / 2.4,
# 10x gyro noise, no intrinsics) to 3.6 / 6.8, 4.3 / 7.7, 3.1 / 7.3 mm (NEES 2.6 / 5.0 / 2.5, 2x gyro noise);
# without the intrinsics the 2x noise alone gives 4.3 / 9.9 mm on seed 0 (NEES 4.2). Estimating the
# accelerometer's matrix as well (``"gyro+accel"``) was worse (seed 1: 4.9 / 16.3 mm, drift 0.5 %).
#
# The still start reads the accelerometer's horizontal turn-on bias (0.2 m/s^2 for this part) as tilt, so
# the two errors are one: the filter starts with them coupled (``static_tilt_bias_sigma_m_s2``, the prior
# the window optimizer has, :mod:`viotb.vio.window_init`). Stereo KLT, seed 0 (world lock / max mm, NEES):
# look-around 4.97 / 7.76, 3.61 -> 4.91 / 7.72, 3.42 (seeds 1, 2: 3.82 -> 3.73, 2.82 -> 2.84); walk 18.2 /
# 31.3, 29.2 -> 17.9 / 31.1, 28.4; crouch 2.36 -> 2.42; with 0.05 px simulated features the walk's max
# error 11.2 -> 3.9 mm (NEES 11.8 -> 9.5; with no turn-on bias at all 2.4). Telling the initializer the
# part's 0.2 m/s^2 (0.02 rad of tilt) instead of 0.1 as well made the KLT look-around worse (6.9 mm).
HEADSET_MSCKF = MsckfParams(
    keyframing=KeyframeParams(every_n_frames=1),
    pixel_sigma_px=0.05,
    klt=KltParams(track_random_walk_px2_per_px=0.0002),
    imu_intrinsics="gyro",
    static_tilt_bias_sigma_m_s2=0.01,
)


def default_gyro_noise_inflation(estimator: str, msckf: MsckfParams) -> float:
    """The gyro noise factor a headset run tells ``estimator`` when none is given (see HeadsetOptions).

    10 covers the raw part's scale and misalignment errors for an estimator that does not model them
    (:func:`estimator_imu_noise`); an MSCKF that estimates the gyro matrix needs 2 (look-around, seed 0,
    20 s: told 1x the world lock / max error are 4.6 / 8.5 mm and the NEES 4.0, at 2x 3.6 / 6.8 mm and 2.6;
    seed 1 at 3x 4.7 / 7.6 mm, NEES 5.1, against 4.3 / 7.7 mm, 5.0 at 2x). The remaining factor covers what
    is still unmodeled (the accelerometer's matrix, the quantization): a tuning, measured on these seeds.
    """
    if estimator == "msckf" and msckf.imu_intrinsics != "none":
        return 2.0
    return 10.0


def estimator_imu_noise(noise: ImuNoise, gyro_noise_inflation: float) -> ImuNoise:
    """The IMU noise the estimator is told: ``noise`` with the gyro white-noise density times the factor.

    The headset IMU preset (``icm42688-1khz``) draws gyro scale factors (sigma 2e-3) and axis misalignments
    (sigma 0.1 deg) that only the MSCKF's online intrinsics model (:data:`HEADSET_MSCKF`). At head rates up
    to 3.5 rad/s they are a gyro error of ~1e-2 rad/s that follows the motion, some 30 times the white
    noise per 1 kHz sample; told only the white noise and not modeling them, the stereo MSCKF (four times
    the rows of the mono one) becomes overconfident (look-around, 8 s: position NEES 8.5, 16 with a clone
    at every frame; 2.4 without the scale and misalignment errors). A factor 10 (1e-3 rad/s/sqrtHz) makes
    it consistent again (NEES 2.4); with the gyro intrinsics estimated 2 does
    (:func:`default_gyro_noise_inflation`).
    """
    if not (np.isfinite(gyro_noise_inflation) and gyro_noise_inflation > 0.0):
        raise ValueError(f"gyro_noise_inflation must be positive, got {gyro_noise_inflation}")
    return replace(
        noise, gyro_noise_density_rad_s_sqrthz=noise.gyro_noise_density_rad_s_sqrthz * gyro_noise_inflation
    )


HEADSET_KLT_NIS_PER_DOF = 1.6
"""NIS per dof the headset's MSCKF (:data:`HEADSET_MSCKF`, told 0.05 px) shows on its nominal KLT renders.

The health monitor's time-sync test divides its windowed mean (30 updates) by this before the 1.25 factor.
Measured (session 14, README "Headset tracking"), windowed maxima, nominal: mono walk 1.71 / 1.41 / 1.34
(seeds 0-2), crouch 1.45 / 1.39, fast turns 0.97 / 0.85 / 0.88, look-around 0.71 / 0.73; stereo walk 1.86,
crouch 1.69, fast turns 1.47 / 1.50, look-around 0.92. Told 1 (the value for a filter told its true noise),
the monitor raised ``time_sync_or_extrinsic_suspected`` on every nominal walk and crouch: the KLT errors
of those motions are above 0.05 px (the walk's NEES is 20-28). With a 2 ms camera-IMU offset the maxima
are 4.45 / 4.48 (mono look-around, seeds 0 / 1), 4.20 (mono fast turns), 2.86 (stereo look-around) and
2.10 (stereo fast turns), all above 1.25 x 1.6 = 2.0; on the walk and the crouch a 2 ms offset leaves the
innovations as they are (1.71, 1.45) and is not seen. A measured reference for a filter that is
overconfident in some motions, not a noise model.
"""


def headset_health_params(estimator: str, frontend: str) -> HealthParams:
    """The health monitor's settings for a headset run: the measured NIS reference for the MSCKF on KLT.

    Args:
        estimator: The estimator's name.
        frontend: ``"klt"`` or ``"sim"`` (projected landmarks with the noise the filter is told: 1).
    """
    if estimator == "msckf" and frontend == "klt":
        return HealthParams(nis_per_dof_expected=HEADSET_KLT_NIS_PER_DOF)
    return HealthParams()
