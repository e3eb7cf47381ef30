"""A EuRoC ASL writer fed piece by piece, for recordings too long to hold in memory (``viotb record``).

:func:`viotb.envs.data.euroc_writer.write_euroc` takes whole arrays; :class:`EurocStreamWriter` takes the
IMU and ground truth in chunks and the frames one at a time, and writes each row as it comes, in the same
layout and number format, so that a long recording starts writing at once and its memory stays flat.
"""

from __future__ import annotations

from pathlib import Path
from types import TracebackType

import cv2
import numpy as np
from viotb.envs.data.euroc import CAM_HEADER, GT_HEADER, IMU_HEADER, LANDMARK_HEADER
from viotb.envs.data.euroc_writer import _fmt, _to_ns, _write_camera_yaml, _write_imu_yaml
from viotb.vio.camera import CameraCalibration
from viotb.vio.types import ImuNoise, ImuSeries, TrajectoryArrays


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
        for sub in (
            "imu0",
            "state_groundtruth_estimate0",
            *(f"cam{k}/data" for k in range(len(self._calibs))),
        ):
            (self.mav0 / sub).mkdir(parents=True, exist_ok=True)
        self._imu = (self.mav0 / "imu0" / "data.csv").open("w", newline="")
        self._cams = [
            (self.mav0 / f"cam{k}" / "data.csv").open("w", newline="") for k in range(len(self._calibs))
        ]
        self._gt = (self.mav0 / "state_groundtruth_estimate0" / "data.csv").open("w", newline="")
        self._imu.write(IMU_HEADER + "\n")
        for cam in self._cams:
            cam.write(CAM_HEADER + "\n")
        self._gt.write(GT_HEADER + "\n")
        self._last_ns = {"imu": -1, "cam": -1, "gt": -1}
        self.frames = 0
        self.imu_samples = 0

    def _stamps(self, t_s: np.ndarray, what: str) -> np.ndarray:
        t_ns = _to_ns(t_s, what)
        if t_ns.size and t_ns[0] <= self._last_ns[what]:
            raise ValueError(f"EurocStreamWriter: {what} times must strictly increase across chunks")
        if t_ns.size:
            self._last_ns[what] = int(t_ns[-1])
        return t_ns

    def imu(self, chunk: ImuSeries) -> None:
        """Append IMU readings (times after those already written)."""
        values = np.hstack([chunk.gyro_B_rad_s, chunk.accel_B_m_s2])
        if not np.all(np.isfinite(values)):
            row = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
            raise ValueError(f"EurocStreamWriter: IMU row {row} is not finite: {values[row].tolist()}")
        t_ns = self._stamps(chunk.t_s, "imu")
        self._imu.writelines(f"{t},{_fmt(row)}\n" for t, row in zip(t_ns, values, strict=True))
        self.imu_samples += len(t_ns)

    def groundtruth(self, chunk: TrajectoryArrays, gyro_bias: np.ndarray, accel_bias: np.ndarray) -> None:
        """Append ground-truth rows: pose, velocity and the true biases (rad/s, m/s^2) at each time."""
        m = len(chunk)
        v = np.zeros((m, 3)) if chunk.v_WB is None else chunk.v_WB
        table = np.hstack([chunk.p_WB, chunk.quat_wxyz_WB, v, gyro_bias, accel_bias])
        if table.shape != (m, 16):
            raise ValueError(f"EurocStreamWriter: ground-truth arrays need {m} rows, got {table.shape}")
        t_ns = self._stamps(chunk.t_s, "gt")
        self._gt.writelines(f"{t},{_fmt(row)}\n" for t, row in zip(t_ns, table, strict=True))

    def frame(self, t_cam_s: float, *images: np.ndarray) -> None:
        """One image per camera (uint8, of the calibration size), all stamped ``t_cam_s`` (camera clock)."""
        if len(images) != len(self._calibs):
            raise ValueError(f"EurocStreamWriter: {len(self._calibs)} image(s) per frame, got {len(images)}")
        t_ns = int(self._stamps(np.array([t_cam_s]), "cam")[0])
        for k, (image, calib, csv) in enumerate(zip(images, self._calibs, self._cams, strict=True)):
            cam = calib.camera
            image = np.asarray(image)
            if image.dtype != np.uint8 or image.shape != (cam.height, cam.width):
                raise ValueError(
                    f"EurocStreamWriter: frame {self.frames} of cam{k} must be uint8 of shape "
                    f"({cam.height}, {cam.width}), got {image.dtype} {image.shape}"
                )
            path = self.mav0 / f"cam{k}" / "data" / f"{t_ns}.png"
            if not cv2.imwrite(str(path), image):
                raise ValueError(f"EurocStreamWriter: could not write {path}")
            csv.write(f"{t_ns},{path.name}\n")
        self.frames += 1

    def finish(self, imu_noise: ImuNoise, imu_rate_hz: float, landmarks_W: np.ndarray | None = None) -> Path:
        """Write the ``sensor.yaml`` files and the landmarks, close the files; returns ``mav0``."""
        self.close()
        _write_imu_yaml(self.mav0 / "imu0" / "sensor.yaml", imu_noise, imu_rate_hz)
        for k, calib in enumerate(self._calibs):
            _write_camera_yaml(self.mav0 / f"cam{k}" / "sensor.yaml", calib, self._exposure_s)
        (self.mav0 / "state_groundtruth_estimate0" / "sensor.yaml").write_text(
            "%YAML:1.0\nsensor_type: visual-inertial\ncomment: vio-testbed simulation ground truth (exact).\n"
        )
        if landmarks_W is not None:
            lm_dir = self.mav0 / "sim_landmarks0"
            lm_dir.mkdir(parents=True, exist_ok=True)
            with (lm_dir / "data.csv").open("w", newline="") as handle:
                handle.write(LANDMARK_HEADER + "\n")
                handle.writelines(f"{i},{_fmt(p)}\n" for i, p in enumerate(np.asarray(landmarks_W, float)))
        return self.mav0

    def close(self) -> None:
        """Close the CSV files (idempotent)."""
        for handle in (self._imu, *self._cams, self._gt):
            handle.close()

    def __enter__(self) -> EurocStreamWriter:
        """The writer."""
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Close the files."""
        self.close()
