"""Build estimators by name (the names of DESIGN.md's CLI contract)."""

from __future__ import annotations

from dataclasses import replace

from viotb.vio.baselines import GroundTruthEstimator, ImuOnlyEstimator
from viotb.vio.camera import CameraCalibration
from viotb.vio.msckf import MsckfEstimator, MsckfParams
from viotb.vio.types import Estimator, ImuNoise
from viotb.vio.window import WindowEstimator, WindowParams

ESTIMATOR_NAMES = ("msckf", "window", "imu-only", "ground-truth")
FRONTEND_NAMES = ("klt", "sim")
CALIBRATING_ESTIMATORS = ("msckf", "window")
"""Estimators that estimate the camera-IMU time offset and extrinsics online (``with_online_calibration``)."""


def make_estimator(
    name: str,
    calib: CameraCalibration,
    noise: ImuNoise,
    *,
    frontend: str = "klt",
    params: MsckfParams | None = None,
    window_params: WindowParams | None = None,
    calib_right: CameraCalibration | None = None,
) -> Estimator:
    """Create the estimator ``name`` (one of :data:`ESTIMATOR_NAMES`).

    Args:
        name: Estimator name.
        calib: Cam0 calibration (intrinsics, ``R_BC``, ``p_BC``, time offset).
        noise: IMU noise densities.
        frontend: ``"klt"`` or ``"sim"`` (MSCKF and window; overrides the front end of their settings).
        params: MSCKF settings.
        window_params: Sliding-window optimizer settings.
        calib_right: Cam1 calibration of a stereo rig (its own ``R_BC``, ``p_BC``), or None for mono. The
            MSCKF and the window use it; ``imu-only`` and ``ground-truth`` ignore it.

    Raises:
        ValueError: for an unknown name or front end, listing the allowed ones.
    """
    if frontend not in FRONTEND_NAMES:
        raise ValueError(f"unknown front end {frontend!r}; allowed: {', '.join(FRONTEND_NAMES)}")
    if name == "msckf":
        p = params if params is not None else MsckfParams()
        return MsckfEstimator(calib, noise, replace(p, frontend=frontend), calib_right=calib_right)
    if name == "window":
        w = window_params if window_params is not None else WindowParams()
        return WindowEstimator(calib, noise, replace(w, frontend=frontend), calib_right=calib_right)
    if name == "imu-only":
        return ImuOnlyEstimator(calib, noise)
    if name == "ground-truth":
        return GroundTruthEstimator(calib, noise)
    raise ValueError(f"unknown estimator {name!r}; allowed: {', '.join(ESTIMATOR_NAMES)}")
