"""EuRoC ASL dataset folders: the writer (``viotb record``), in the layout that :mod:`.euroc` reads.

:class:`EurocStreamWriter` takes the IMU and ground truth in chunks and the frames one at a time and writes
each row as it comes, so a long recording starts writing at once and its memory stays flat;
:func:`write_euroc` feeds it whole arrays.

A stereo rig writes ``cam1`` beside ``cam0`` exactly as the stereo EuRoC folders do: the same stamps, its own
``sensor.yaml`` with its own ``T_BS``.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from types import TracebackType

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
    """Write a EuRoC ASL tree under ``out_dir/mav0`` from whole arrays; returns the ``mav0`` path.

    The rows are written by :class:`EurocStreamWriter` (the writer of ``viotb record``), fed all at once.

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
    if imu_rate_hz is None:
        imu_rate_hz = float(1.0 / np.median(np.diff(imu.t_s))) if len(imu.t_s) > 1 else 200.0
    with EurocStreamWriter(out_dir, calib, calib_right, exposure_s) as writer:
        writer.imu(imu)
        for t_s, *images in frames:
            writer.frame(t_s, *images)
        if groundtruth is not None:
            zeros = np.zeros((len(groundtruth), 3))
            bw = zeros if gt_gyro_bias is None else np.asarray(gt_gyro_bias, dtype=float)
            ba = zeros if gt_accel_bias is None else np.asarray(gt_accel_bias, dtype=float)
            writer.groundtruth(groundtruth, bw, ba)
        return writer.finish(imu_noise, imu_rate_hz, landmarks_W)


class EurocStreamWriter:
    """Writes ``out_dir/mav0`` row by row; use as a context manager, then :meth:`finish`.

    Args:
        out_dir: Output folder (``mav0`` is created inside).
        calib: Camera calibration (for the frame size check and ``cam0/sensor.yaml``).
        calib_right: Calibration of a stereo rig's right camera (``cam1``, same stamps); None = mono.
        exposure_s: Shutter time (s) written to the cameras' ``sensor.yaml`` (``exposure_time_s``); None = not
            written.
    """

    def __init__(
        self,
        out_dir: Path | str,
        calib: CameraCalibration,
        calib_right: CameraCalibration | None = None,
        exposure_s: float | None = None,
    ) -> None:
        """Create the folders and open the CSV files with their headers."""
        self.mav0 = Path(out_dir) / "mav0"
        self._calibs = [calib] if calib_right is None else [calib, calib_right]
        self._exposure_s = exposure_s
        for sub in ("imu0", *(f"cam{k}/data" for k in range(len(self._calibs)))):
            (self.mav0 / sub).mkdir(parents=True, exist_ok=True)
        self._imu = (self.mav0 / "imu0" / "data.csv").open("w", newline="")
        self._cams = [
            (self.mav0 / f"cam{k}" / "data.csv").open("w", newline="") for k in range(len(self._calibs))
        ]
        self._gt = None  # opened by the first ground-truth chunk: a dataset may have none
        self._imu.write(IMU_HEADER + "\n")
        for cam in self._cams:
            cam.write(CAM_HEADER + "\n")
        self._last_ns = {"IMU": -1, "camera": -1, "ground-truth": -1}
        self.frames = 0
        self.imu_samples = 0

    def _stamps(self, t_s: np.ndarray, what: str) -> np.ndarray:
        t_ns = _to_ns(t_s, what)
        if t_ns.size and t_ns[0] <= self._last_ns[what]:
            raise ValueError(f"write_euroc: {what} times must strictly increase (across chunks)")
        if t_ns.size:
            self._last_ns[what] = int(t_ns[-1])
        return t_ns

    def imu(self, chunk: ImuSeries) -> None:
        """Append IMU readings (times after those already written)."""
        if chunk.gyro_B_rad_s.shape != (len(chunk), 3) or chunk.accel_B_m_s2.shape != (len(chunk), 3):
            raise ValueError(f"write_euroc: IMU arrays must be ({len(chunk)}, 3)")
        values = np.hstack([chunk.gyro_B_rad_s, chunk.accel_B_m_s2])
        if not np.all(np.isfinite(values)):
            row = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
            raise ValueError(f"write_euroc: IMU row {row} is not finite: {values[row].tolist()}")
        t_ns = self._stamps(chunk.t_s, "IMU")
        self._imu.writelines(f"{t},{_fmt(row)}\n" for t, row in zip(t_ns, values, strict=True))
        self.imu_samples += len(t_ns)

    def groundtruth(self, chunk: TrajectoryArrays, gyro_bias: np.ndarray, accel_bias: np.ndarray) -> None:
        """Append ground-truth rows: pose, velocity and the true biases (rad/s, m/s^2) at each time."""
        m = len(chunk)
        v = np.zeros((m, 3)) if chunk.v_WB is None else chunk.v_WB
        table = np.hstack([chunk.p_WB, chunk.quat_wxyz_WB, v, gyro_bias, accel_bias])
        if table.shape != (m, 16):
            raise ValueError(f"write_euroc: ground-truth arrays must all have {m} rows, got {table.shape}")
        t_ns = self._stamps(chunk.t_s, "ground-truth")
        if self._gt is None:
            (self.mav0 / "state_groundtruth_estimate0").mkdir(parents=True, exist_ok=True)
            self._gt = (self.mav0 / "state_groundtruth_estimate0" / "data.csv").open("w", newline="")
            self._gt.write(GT_HEADER + "\n")
        self._gt.writelines(f"{t},{_fmt(row)}\n" for t, row in zip(t_ns, table, strict=True))

    def frame(self, t_cam_s: float, *images: np.ndarray) -> None:
        """One image per camera (uint8, of the calibration size), all stamped ``t_cam_s`` (camera clock)."""
        if len(images) != len(self._calibs):
            raise ValueError(
                f"write_euroc: frame {self.frames} carries {len(images)} image(s) "
                f"for {len(self._calibs)} camera(s)"
            )
        t_ns = int(self._stamps(np.array([t_cam_s]), "camera")[0])
        for k, (image, calib, csv) in enumerate(zip(images, self._calibs, self._cams, strict=True)):
            cam = calib.camera
            image = np.asarray(image)
            if image.dtype != np.uint8 or image.shape != (cam.height, cam.width):
                raise ValueError(
                    f"write_euroc: frame {self.frames}{' of cam1' if k else ''} must be uint8 of shape "
                    f"({cam.height}, {cam.width}), got {image.dtype} {image.shape}"
                )
            path = self.mav0 / f"cam{k}" / "data" / f"{t_ns}.png"
            if not cv2.imwrite(str(path), image):
                raise ValueError(f"write_euroc: could not write {path}")
            csv.write(f"{t_ns},{path.name}\n")
        self.frames += 1

    def finish(self, imu_noise: ImuNoise, imu_rate_hz: float, landmarks_W: np.ndarray | None = None) -> Path:
        """Write the ``sensor.yaml`` files and the landmarks, close the files; returns ``mav0``."""
        self.close()
        _write_imu_yaml(self.mav0 / "imu0" / "sensor.yaml", imu_noise, imu_rate_hz)
        for k, calib in enumerate(self._calibs):
            _write_camera_yaml(self.mav0 / f"cam{k}" / "sensor.yaml", calib, self._exposure_s)
        if self._gt is not None:
            (self.mav0 / "state_groundtruth_estimate0" / "sensor.yaml").write_text(
                "%YAML:1.0\nsensor_type: visual-inertial\n"
                "comment: vio-testbed simulation ground truth (exact).\n"
            )
        if landmarks_W is not None:
            landmarks_W = np.asarray(landmarks_W, dtype=float)
            if landmarks_W.ndim != 2 or landmarks_W.shape[1] != 3:
                raise ValueError(f"write_euroc: landmarks_W must be (L, 3), got {landmarks_W.shape}")
            lm_dir = self.mav0 / "sim_landmarks0"
            lm_dir.mkdir(parents=True, exist_ok=True)
            with (lm_dir / "data.csv").open("w", newline="") as handle:
                handle.write(LANDMARK_HEADER + "\n")
                handle.writelines(f"{i},{_fmt(p)}\n" for i, p in enumerate(np.asarray(landmarks_W, float)))
        return self.mav0

    def close(self) -> None:
        """Close the CSV files (idempotent)."""
        for handle in (self._imu, *self._cams, self._gt):
            if handle is not None:
                handle.close()

    def __enter__(self) -> EurocStreamWriter:
        """The writer."""
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Close the files."""
        self.close()
