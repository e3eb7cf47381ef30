"""EuRoC ASL dataset folders: the writer (``viotb record``), in the layout that :mod:`.euroc` reads.

A stereo rig writes ``cam1`` beside ``cam0`` exactly as the stereo EuRoC folders do: the same stamps, its own
``sensor.yaml`` with its own ``T_BS``.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
from viotb.envs.data.euroc import CAM_HEADER, GT_HEADER, IMU_HEADER, LANDMARK_HEADER, NS_PER_S
from viotb.vio.camera import CameraCalibration, camera_to_kalibr
from viotb.vio.types import ImuNoise, ImuSeries, TrajectoryArrays


def _to_ns(t_s: np.ndarray, what: str) -> np.ndarray:
    t_s = np.asarray(t_s, dtype=np.float64)
    if t_s.ndim != 1 or not np.all(np.isfinite(t_s)):
        raise ValueError(f"write_euroc: {what} times must be a finite 1-D array, got shape {t_s.shape}")
    if np.any(t_s < 0.0):
        raise ValueError(f"write_euroc: {what} times must be >= 0 s, got min {t_s.min()}")
    t_ns = np.rint(t_s * NS_PER_S).astype(np.int64)
    bad = np.flatnonzero(np.diff(t_ns) <= 0)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"write_euroc: {what} times must strictly increase: [{i}]={t_s[i]}, [{i + 1}]={t_s[i + 1]}"
        )
    return t_ns


def _fmt(values: np.ndarray) -> str:
    return ",".join(repr(float(v)) for v in values)


def _yaml_list(values: Iterable[float]) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _write_camera_yaml(path: Path, calib: CameraCalibration, exposure_s: float | None = None) -> None:
    fields = camera_to_kalibr(calib.camera)
    T = np.eye(4)
    T[:3, :3] = calib.R_BC
    T[:3, 3] = calib.p_BC
    rows = ",\n         ".join(", ".join(repr(float(v)) for v in T[i]) for i in range(4))
    text = (
        "%YAML:1.0\n"
        "# General sensor definitions.\n"
        "sensor_type: camera\n"
        "comment: vio-testbed simulated camera (MuJoCo offscreen render)\n\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        f"  data: [{rows}]\n\n"
        "# Camera specific definitions.\n"
        f"rate_hz: {float(calib.rate_hz)!r}\n"
        f"resolution: [{fields['resolution'][0]}, {fields['resolution'][1]}]\n"
        f"camera_model: {fields['camera_model']}\n"
        f"intrinsics: {_yaml_list(fields['intrinsics'])} #fu, fv, cu, cv\n"
        f"distortion_model: {fields['distortion_model']}\n"
        f"distortion_coefficients: {_yaml_list(fields['distortion_coefficients'])}\n"
        "# Clock offset (Kalibr convention): t_imu = t_cam + timeshift_cam_imu [s]\n"
        f"timeshift_cam_imu: {float(calib.time_offset_s)!r}\n"
    )
    if exposure_s is not None:
        text += (
            "# Global shutter; every pixel integrates over the exposure, centred on the stamp [s]\n"
            "shutter: global\n"
            f"exposure_time_s: {float(exposure_s)!r}\n"
        )
    path.write_text(text)


TRUE_CAMERA_YAML = "sim_calibration0/cam0_sensor.yaml"
"""Where a recording keeps the *true* cam0 calibration (our extension, relative to ``mav0``).

``cam0/sensor.yaml`` holds what the estimator is told, which a failure recording writes wrong on purpose;
this copy lets the ``sim`` front end project with the truth and lets a benchmark score online calibration.
"""


def write_true_calibration(mav0: Path, calib: CameraCalibration) -> Path:
    """Write the true cam0 calibration to ``mav0/``:data:`TRUE_CAMERA_YAML` (``sensor.yaml``'s format)."""
    path = Path(mav0) / TRUE_CAMERA_YAML
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_camera_yaml(path, calib)
    return path


def _write_imu_yaml(path: Path, noise: ImuNoise, rate_hz: float) -> None:
    text = (
        "%YAML:1.0\n"
        "sensor_type: imu\n"
        "comment: vio-testbed simulated IMU\n\n"
        "# Sensor extrinsics wrt. the body-frame (the body frame is the IMU frame).\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [1.0, 0.0, 0.0, 0.0,\n         0.0, 1.0, 0.0, 0.0,\n"
        "         0.0, 0.0, 1.0, 0.0,\n         0.0, 0.0, 0.0, 1.0]\n"
        f"rate_hz: {float(rate_hz)!r}\n\n"
        "# inertial sensor noise model parameters (static)\n"
        f"gyroscope_noise_density: {noise.gyro_noise_density_rad_s_sqrthz!r}     # [ rad / s / sqrt(Hz) ]\n"
        f"gyroscope_random_walk: {noise.gyro_random_walk_rad_s2_sqrthz!r}       # [ rad / s^2 / sqrt(Hz) ]\n"
        f"accelerometer_noise_density: {noise.accel_noise_density_m_s2_sqrthz!r}  # [ m / s^2 / sqrt(Hz) ]\n"
        f"accelerometer_random_walk: {noise.accel_random_walk_m_s3_sqrthz!r}    # [ m / s^3 / sqrt(Hz) ]\n"
    )
    path.write_text(text)


def write_euroc(
    out_dir: Path | str,
    imu: ImuSeries,
    frames: Iterable[tuple],
    calib: CameraCalibration,
    imu_noise: ImuNoise,
    groundtruth: TrajectoryArrays | None = None,
    gt_gyro_bias: np.ndarray | None = None,
    gt_accel_bias: np.ndarray | None = None,
    landmarks_W: np.ndarray | None = None,
    imu_rate_hz: float | None = None,
    calib_right: CameraCalibration | None = None,
    exposure_s: float | None = None,
) -> Path:
    """Write a EuRoC ASL tree under ``out_dir/mav0`` and return the ``mav0`` path.

    Args:
        out_dir: Output folder (created).
        imu: IMU readings (times >= 0 s, strictly increasing).
        frames: ``(t_cam_s, image)`` pairs in time order; images (H, W) uint8 of the calibration's size.
            Consumed lazily, so a generator can render frame by frame. With ``calib_right``:
            ``(t_cam_s, image_left, image_right)`` triples, written to ``cam0`` and ``cam1`` with one stamp.
        calib: Camera calibration (cam0 ``sensor.yaml``).
        imu_noise: Densities for ``imu0/sensor.yaml``.
        groundtruth: Poses of B in W with velocities (zeros are written when ``v_WB`` is None).
        gt_gyro_bias: True gyro bias at the ground-truth times (rad/s), shape (M, 3); zeros if None.
        gt_accel_bias: True accelerometer bias (m/s^2), shape (M, 3); zeros if None.
        landmarks_W: Landmark positions (m), shape (L, 3), written to ``sim_landmarks0/data.csv``.
        imu_rate_hz: Nominal IMU rate; default from the median sample spacing.
        calib_right: Calibration of the right camera (``cam1/sensor.yaml``); None = mono.
        exposure_s: Shutter time (s) written to the cameras' ``sensor.yaml`` (``exposure_time_s``); None =
            not recorded.
    """
    mav0 = Path(out_dir) / "mav0"
    imu_dir = mav0 / "imu0"
    imu_dir.mkdir(parents=True, exist_ok=True)

    imu_t_ns = _to_ns(imu.t_s, "IMU")
    n = len(imu_t_ns)
    if imu.gyro_B_rad_s.shape != (n, 3) or imu.accel_B_m_s2.shape != (n, 3):
        raise ValueError(f"write_euroc: IMU arrays must be ({n}, 3)")
    values = np.hstack([imu.gyro_B_rad_s, imu.accel_B_m_s2])
    if not np.all(np.isfinite(values)):
        row = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
        raise ValueError(f"write_euroc: IMU row {row} is not finite: {values[row].tolist()}")
    with (imu_dir / "data.csv").open("w", newline="") as handle:
        handle.write(IMU_HEADER + "\n")
        handle.writelines(f"{t},{_fmt(row)}\n" for t, row in zip(imu_t_ns, values, strict=True))
    if imu_rate_hz is None:
        imu_rate_hz = float(1.0 / np.median(np.diff(imu.t_s))) if n > 1 else 200.0
    _write_imu_yaml(imu_dir / "sensor.yaml", imu_noise, imu_rate_hz)
    calibs = [calib] if calib_right is None else [calib, calib_right]
    cam_dirs = [mav0 / f"cam{k}" for k in range(len(calibs))]
    for c, d in zip(calibs, cam_dirs, strict=True):
        (d / "data").mkdir(parents=True, exist_ok=True)
        _write_camera_yaml(d / "sensor.yaml", c, exposure_s)

    last_ns = -1
    handles = [(d / "data.csv").open("w", newline="") for d in cam_dirs]
    try:
        for handle in handles:
            handle.write(CAM_HEADER + "\n")
        for i, item in enumerate(frames):
            t_s, images = item[0], item[1:]
            if len(images) != len(calibs):
                raise ValueError(
                    f"write_euroc: frame {i} carries {len(images)} image(s) for {len(calibs)} camera(s)"
                )
            t_ns = int(_to_ns(np.array([t_s]), "camera")[0])
            if t_ns <= last_ns:
                raise ValueError(f"write_euroc: camera times must strictly increase, frame {i} at {t_s} s")
            for k, (image, c, d, handle) in enumerate(zip(images, calibs, cam_dirs, handles, strict=True)):
                image = np.asarray(image)
                cam = c.camera
                if image.dtype != np.uint8 or image.shape != (cam.height, cam.width):
                    raise ValueError(
                        f"write_euroc: frame {i}{' of cam1' if k else ''} must be uint8 of shape "
                        f"({cam.height}, {cam.width}), got {image.dtype} {image.shape}"
                    )
                name = f"{t_ns}.png"
                if not cv2.imwrite(str(d / "data" / name), image):
                    raise ValueError(f"write_euroc: could not write {d / 'data' / name}")
                handle.write(f"{t_ns},{name}\n")
            last_ns = t_ns
    finally:
        for handle in handles:
            handle.close()

    if groundtruth is not None:
        gt_dir = mav0 / "state_groundtruth_estimate0"
        gt_dir.mkdir(parents=True, exist_ok=True)
        m = len(groundtruth)
        gt_t_ns = _to_ns(groundtruth.t_s, "ground-truth")
        zeros = np.zeros((m, 3))
        v = zeros if groundtruth.v_WB is None else groundtruth.v_WB
        bw = zeros if gt_gyro_bias is None else np.asarray(gt_gyro_bias, dtype=float)
        ba = zeros if gt_accel_bias is None else np.asarray(gt_accel_bias, dtype=float)
        table = np.hstack([groundtruth.p_WB, groundtruth.quat_wxyz_WB, v, bw, ba])
        if table.shape != (m, 16):
            raise ValueError(f"write_euroc: ground-truth arrays must all have {m} rows, got {table.shape}")
        with (gt_dir / "data.csv").open("w", newline="") as handle:
            handle.write(GT_HEADER + "\n")
            handle.writelines(f"{t},{_fmt(row)}\n" for t, row in zip(gt_t_ns, table, strict=True))
        (gt_dir / "sensor.yaml").write_text(
            "%YAML:1.0\nsensor_type: visual-inertial\ncomment: vio-testbed simulation ground truth (exact).\n"
        )

    if landmarks_W is not None:
        landmarks_W = np.asarray(landmarks_W, dtype=float)
        if landmarks_W.ndim != 2 or landmarks_W.shape[1] != 3:
            raise ValueError(f"write_euroc: landmarks_W must be (L, 3), got {landmarks_W.shape}")
        lm_dir = mav0 / "sim_landmarks0"
        lm_dir.mkdir(parents=True, exist_ok=True)
        with (lm_dir / "data.csv").open("w", newline="") as handle:
            handle.write(LANDMARK_HEADER + "\n")
            handle.writelines(f"{i},{_fmt(p)}\n" for i, p in enumerate(landmarks_W))
    return mav0
