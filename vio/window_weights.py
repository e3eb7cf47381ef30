"""The window factors' noise models and camera extrinsics: :class:`FactorWeights` (besides the variables)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.types import ImuNoise


@dataclass(frozen=True)
class FactorWeights:
    """What the factors need besides the variables (noise models and the camera extrinsics).

    Attributes:
        noise: IMU noise densities.
        R_BC: Camera-to-body rotation, shape (3, 3).
        p_BC: Camera origin in B (m), shape (3,).
        sigma_norm: Feature measurement sigma in normalized image coordinates (pixel sigma / focal length).
        huber_threshold: Huber threshold on the whitened reprojection error norm (sigmas).
        zero_velocity_sigma_m_s: Sigma (m/s) of the zero-velocity factor (and, times ``dt``, of the
            no-motion factor).
        R_BC1: Cam1-to-body rotation of a stereo rig, shape (3, 3), or None (mono).
        p_BC1: Cam1 origin in B (m), shape (3,), or None.
        sigma_norm1: Cam1 measurement sigma in its normalized coordinates (pixel sigma / its focal length).
        track_q: Correlated track noise ``track_random_walk_px2_per_px / pixel_sigma_px^2`` (per px of image
            motion; :mod:`viotb.vio.window_reprojection`), 0 for white noise.
        focal_px: Cam0's focal length (px), the clock of the track noise.
        focal_px1: Cam1's.
        kernels: ``"numba"``: the white-noise reprojection blocks by the compiled loop of
            :mod:`viotb.vio.window_kernels`; ``"numpy"``: by array operations (the reference).
    """

    noise: ImuNoise
    R_BC: np.ndarray
    p_BC: np.ndarray
    sigma_norm: float
    huber_threshold: float
    zero_velocity_sigma_m_s: float
    R_BC1: np.ndarray | None = None
    p_BC1: np.ndarray | None = None
    sigma_norm1: float | None = None
    track_q: float = 0.0
    focal_px: float = 1.0
    focal_px1: float = 1.0
    kernels: str = "numba"


def stereo_weights(
    calib_right: CameraCalibration | None, pixel_sigma_px: float
) -> tuple[np.ndarray | None, np.ndarray | None, float | None]:
    """``(R_BC1, p_BC1, sigma_norm1)`` of :class:`FactorWeights` for cam1 (all None for a mono rig)."""
    if calib_right is None:
        return None, None, None
    cam = calib_right.camera
    return (
        np.asarray(calib_right.R_BC, dtype=float),
        np.asarray(calib_right.p_BC, dtype=float),
        pixel_sigma_px / (0.5 * (cam.fx + cam.fy)),
    )
