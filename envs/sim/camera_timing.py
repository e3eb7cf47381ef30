"""Camera timing model: frame rate, camera-IMU clock offset, latency, random drops and blackouts.

Clocks: the camera stamps frame k at ``t_cam = k / rate_hz``; the image was exposed at
``t_imu = t_cam + time_offset_s`` on the IMU clock (as in :class:`viotb.vio.camera.CameraCalibration`)
and reaches the estimator ``latency_s`` later, at ``t_imu + latency_s``. A frame is dropped with probability
``drop_probability`` (one uniform draw per frame, always drawn so the stream does not depend on the value)
or when its exposure falls in a blackout interval ``[start, end)`` on the IMU clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraModelParams:
    """Camera sensor parameters (units in names).

    Attributes:
        rate_hz: Frame rate (Hz).
        width: Image width (px).
        height: Image height (px).
        time_offset_s: Clock offset (s): ``t_imu = t_cam + time_offset_s``.
        latency_s: Delay (s) between exposure and arrival at the estimator (used by the closed-loop runner).
        pixel_noise_std: Std of additive Gaussian pixel noise (grey levels, 0-255 scale).
        drop_probability: Probability that a frame is lost, in [0, 1].
        blackout_intervals_s: ``((start, end), ...)`` on the IMU clock (s) with no frames (lens covered).
        exposure_s: Shutter open time (s), centred on the exposure instant; 0 renders an instant. Longer
            exposures integrate the motion into the image (motion blur; open-loop recordings only).
        blur_samples: Renders averaged over the exposure when ``exposure_s > 0``.
    """

    rate_hz: float = 20.0
    width: int = 320
    height: int = 240
    time_offset_s: float = 0.0
    latency_s: float = 0.0
    pixel_noise_std: float = 0.0
    drop_probability: float = 0.0
    blackout_intervals_s: tuple[tuple[float, float], ...] = ()
    exposure_s: float = 0.0
    blur_samples: int = 9

    def __post_init__(self) -> None:
        """Validate every field with a message naming it."""
        if not (self.rate_hz > 0.0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"CameraModelParams.rate_hz must be positive and finite, got {self.rate_hz}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not (isinstance(value, int | np.integer) and value > 0):
                raise ValueError(f"CameraModelParams.{name} must be a positive integer, got {value!r}")
        if not math.isfinite(self.time_offset_s):
            raise ValueError(f"CameraModelParams.time_offset_s must be finite, got {self.time_offset_s}")
        if not (self.latency_s >= 0.0 and math.isfinite(self.latency_s)):
            raise ValueError(f"CameraModelParams.latency_s must be finite and >= 0, got {self.latency_s}")
        if not (self.pixel_noise_std >= 0.0 and math.isfinite(self.pixel_noise_std)):
            raise ValueError(f"CameraModelParams.pixel_noise_std must be >= 0, got {self.pixel_noise_std}")
        if not 0.0 <= self.drop_probability <= 1.0:
            raise ValueError(
                f"CameraModelParams.drop_probability must be in [0, 1], got {self.drop_probability}"
            )
        if not (self.exposure_s >= 0.0 and self.exposure_s < 1.0 / self.rate_hz):
            raise ValueError(
                f"CameraModelParams.exposure_s must be in [0, 1 / rate_hz), got {self.exposure_s}"
            )
        if not (isinstance(self.blur_samples, int | np.integer) and self.blur_samples >= 2):
            raise ValueError(
                f"CameraModelParams.blur_samples must be an integer >= 2, got {self.blur_samples!r}"
            )
        for i, interval in enumerate(self.blackout_intervals_s):
            if len(interval) != 2 or not interval[0] < interval[1]:
                raise ValueError(
                    f"CameraModelParams.blackout_intervals_s[{i}] must be (start, end) with start < end, "
                    f"got {interval!r}"
                )


@dataclass(frozen=True)
class FrameSchedule:
    """When frames are exposed, stamped and delivered (F candidate frames).

    Attributes:
        t_exposure_imu_s: Exposure instants on the IMU clock (s), shape (F,).
        t_stamp_cam_s: Stamps on the camera clock (s), shape (F,): ``t_exposure_imu_s - time_offset_s``.
        t_arrival_imu_s: Arrival at the estimator on the IMU clock (s), shape (F,).
        kept: False for dropped or blacked-out frames, shape (F,) bool.
    """

    t_exposure_imu_s: np.ndarray
    t_stamp_cam_s: np.ndarray
    t_arrival_imu_s: np.ndarray
    kept: np.ndarray

    def __len__(self) -> int:
        """Number of candidate frames (kept or not)."""
        return int(self.t_exposure_imu_s.shape[0])

    @property
    def kept_indices(self) -> np.ndarray:
        """Indices of the delivered frames, shape (K,)."""
        return np.flatnonzero(self.kept)


def frame_schedule(params: CameraModelParams, duration_s: float, rng: np.random.Generator) -> FrameSchedule:
    """Frames whose exposure lies in ``[0, duration_s]`` on the IMU clock.

    Args:
        params: Camera parameters.
        duration_s: Length of the recording on the IMU clock (s), > 0.
        rng: Random generator for the drops (exactly F uniforms are drawn).

    Returns:
        The schedule; camera stamps are ``k / rate_hz`` for integer k.
    """
    if not (duration_s > 0.0 and math.isfinite(duration_s)):
        raise ValueError(f"frame_schedule: duration_s must be positive and finite, got {duration_s}")
    eps = 1e-9
    k_first = math.ceil(-params.time_offset_s * params.rate_hz - eps)
    k_last = math.floor((duration_s - params.time_offset_s) * params.rate_hz + eps)
    k = np.arange(k_first, k_last + 1, dtype=np.int64)
    t_cam = k / params.rate_hz
    t_imu = t_cam + params.time_offset_s
    kept = rng.random(k.shape[0]) >= params.drop_probability
    for start, end in params.blackout_intervals_s:
        kept &= ~((t_imu >= start) & (t_imu < end))
    return FrameSchedule(t_imu, t_cam, t_imu + params.latency_s, kept)
