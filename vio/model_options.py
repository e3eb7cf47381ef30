"""The estimators' settings for the command line's model options (``viotb eval`` / ``viotb fly``).

One place for the rules that ``--sensor-model``, ``--klt-noise``, ``--imu-intrinsics`` and ``--calibrate``
follow: which estimators and front ends each needs and which combinations exclude each other, so the CLI
and :func:`viotb.envs.run.fly.fly` build the same settings and name the same conflicts.
"""

from __future__ import annotations

from dataclasses import replace

from viotb.vio.factory import CALIBRATING_ESTIMATORS
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.window_params import WindowParams


def model_settings(
    estimator: str,
    frontend: str,
    sensor_model: str = "default",
    klt_noise: str = "default",
    imu_intrinsics: str = "none",
    calibrate: bool = False,
    msckf: MsckfParams | None = None,
    window: WindowParams | None = None,
) -> tuple[MsckfParams | None, WindowParams | None]:
    """``(msckf, window)`` settings with the model options applied (None where nothing changes).

    Args:
        estimator: Estimator name.
        frontend: ``"klt"`` or ``"sim"``.
        sensor_model: ``"default"`` or ``"render"`` (``with_render_sensor_model`` of either estimator).
        klt_noise: ``"default"`` (1 px) or ``"render"`` (``with_render_klt_noise``).
        imu_intrinsics: ``"none"``, ``"gyro"`` or ``"gyro+accel"`` (``imu_intrinsics`` of either).
        calibrate: Whether the camera-IMU calibration is estimated online as well.
        msckf: The MSCKF settings to start from (None: the defaults).
        window: The window's settings to start from (None: the defaults).

    Raises:
        ValueError: An option for an estimator or front end without it, or two options that each set the
            same thing; the message names the options and values.
    """
    models = sensor_model != "default" or klt_noise != "default" or imu_intrinsics != "none"
    if models and estimator not in CALIBRATING_ESTIMATORS:
        raise ValueError(
            "the sensor model, KLT noise and IMU intrinsics options need the msckf or window, "
            f"got {estimator!r}"
        )
    if (sensor_model != "default" or klt_noise != "default") and frontend != "klt":
        raise ValueError(
            f"sensor model {sensor_model!r} / KLT noise {klt_noise!r} are models of the klt front end, "
            f"got {frontend!r}"
        )
    if sensor_model != "default" and (imu_intrinsics != "none" or klt_noise != "default"):
        raise ValueError(f"sensor model {sensor_model!r} sets the KLT noise and the IMU intrinsics itself")
    if estimator == "window" and calibrate and (sensor_model != "default" or klt_noise != "default"):
        raise ValueError(
            "the window told the render KLT noise cannot calibrate online: its camera terms need white "
            "track noise (WindowParams.track_noise=False)"
        )
    if not models:
        return msckf, window
    if estimator == "msckf":
        m = (msckf or MsckfParams()).with_sensor_model(sensor_model)
        m = m if imu_intrinsics == "none" else replace(m, imu_intrinsics=imu_intrinsics)
        return (m.with_render_klt_noise() if klt_noise == "render" else m), window
    w = (window or WindowParams()).with_sensor_model(sensor_model)
    w = w if imu_intrinsics == "none" else replace(w, imu_intrinsics=imu_intrinsics)
    return msckf, (w.with_render_klt_noise() if klt_noise == "render" else w)
