"""EuRoC ASL dataset folders: the reader, for real or recorded data (the writer is :mod:`.euroc_writer`).

Layout (Burri et al., "The EuRoC micro aerial vehicle datasets", IJRR 2016)::

    mav0/cam0/data/<t_ns>.png           8-bit (or 16-bit, read as its high byte) grayscale images
    mav0/cam0/data.csv                  #timestamp [ns],filename
    mav0/cam0/sensor.yaml               intrinsics [fu, fv, cu, cv], radtan or equi distortion, T_BS, rate_hz
    mav0/cam1/...                       the right camera of a stereo rig, same layout, its own T_BS (optional)
    mav0/imu0/data.csv                  #timestamp [ns],w_RS_S_x [rad s^-1],...,a_RS_S_z [m s^-2]
    mav0/imu0/sensor.yaml               Kalibr noise densities, rate_hz
    mav0/state_groundtruth_estimate0/data.csv   t, p xyz, q wxyz, v xyz, bw xyz, ba xyz (optional)
    mav0/mocap0/data.csv, mav0/vicon0/data.csv  t, p xyz, q wxyz: pose-only ground truth (TUM-VI, raw EuRoC)
    mav0/sim_landmarks0/data.csv        #id,p_x [m],p_y [m],p_z [m] (our extension, optional)

The camera model is read with :func:`viotb.vio.camera.camera_from_kalibr`, so Kalibr ``pinhole-radtan`` and
``pinhole-equi`` (TUM-VI style fisheye in EuRoC layout) both load. ``sensor.yaml`` files start with
OpenCV's ``%YAML:1.0`` line, which PyYAML rejects; it is stripped before parsing. The camera clock offset,
when non-zero, is stored as Kalibr's ``timeshift_cam_imu`` (``t_imu = t_cam + timeshift_cam_imu``).
Timestamps are integer nanoseconds in files and float64 seconds (``t_ns * 1e-9``) in memory; the integer
stamps are kept as well for exact round trips.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from viotb.envs.data.euroc_files import (
    ns_to_s,
    parse_floats,
    parse_ns,
    read_numeric_csv,
    read_rows,
    read_T_BS,
    read_yaml,
    yaml_number,
)
from viotb.envs.data.euroc_truth import read_groundtruth
from viotb.envs.data.validate import check_camera_ranges, check_imu_ranges
from viotb.vio.camera import CameraCalibration, camera_from_kalibr
from viotb.vio.types import ImuNoise, ImuSeries, TrajectoryArrays

IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
CAM_HEADER = "#timestamp [ns],filename"
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
LANDMARK_HEADER = "#id,p_x [m],p_y [m],p_z [m]"
NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class EurocDataset:
    """A loaded EuRoC folder (images are loaded lazily with :func:`load_image`).

    Attributes:
        root: The ``mav0`` folder.
        imu: IMU readings in B (= imu0 frame), N samples.
        cam_t_s: Camera stamps (s, camera clock), shape (F,).
        image_paths: PNG path of each frame, length F.
        calib: Intrinsics, camera-to-body extrinsics (``T_BS`` of cam0) and clock offset.
        imu_noise: Noise densities from ``imu0/sensor.yaml``.
        imu_rate_hz: Nominal IMU rate (Hz).
        groundtruth: Poses (and velocities) of B in W, or None when the folder has none.
        gt_gyro_bias: Ground-truth gyro bias (rad/s), shape (M, 3), or None.
        gt_accel_bias: Ground-truth accelerometer bias (m/s^2), shape (M, 3), or None.
        landmarks_W: Simulated landmark positions (m), shape (L, 3), or None.
        imu_t_ns: IMU stamps (ns), shape (N,), int64.
        cam_t_ns: Camera stamps (ns), shape (F,), int64.
        gt_t_ns: Ground-truth stamps (ns), shape (M,), int64, or None.
        calib_right: Calibration of ``cam1`` (its own ``T_BS``), or None when the folder has no ``cam1``.
        cam1_t_s: ``cam1`` stamps (s, camera clock), shape (F1,), or None.
        cam1_t_ns: ``cam1`` stamps (ns), int64, or None.
        image_paths_right: PNG path of each ``cam1`` frame (empty without ``cam1``).
        groundtruth_source: The folder the ground truth came from (:mod:`.euroc_truth`), or None.
    """

    root: Path
    imu: ImuSeries
    cam_t_s: np.ndarray
    image_paths: tuple[Path, ...]
    calib: CameraCalibration
    imu_noise: ImuNoise
    imu_rate_hz: float
    groundtruth: TrajectoryArrays | None
    gt_gyro_bias: np.ndarray | None
    gt_accel_bias: np.ndarray | None
    landmarks_W: np.ndarray | None
    imu_t_ns: np.ndarray
    cam_t_ns: np.ndarray
    gt_t_ns: np.ndarray | None
    calib_right: CameraCalibration | None = None
    cam1_t_s: np.ndarray | None = None
    cam1_t_ns: np.ndarray | None = None
    image_paths_right: tuple[Path, ...] = ()
    groundtruth_source: str | None = None

    @property
    def has_stereo(self) -> bool:
        """True when the folder has a ``cam1``."""
        return self.calib_right is not None

    def right_index(self, index: int) -> int | None:
        """Index of the ``cam1`` frame stamped like ``cam0`` frame ``index`` (same ns), or None."""
        if self.cam1_t_ns is None:
            return None
        j = int(np.searchsorted(self.cam1_t_ns, self.cam_t_ns[index]))
        return j if j < len(self.cam1_t_ns) and self.cam1_t_ns[j] == self.cam_t_ns[index] else None

    def __len__(self) -> int:
        """Number of camera frames."""
        return len(self.image_paths)


# ----------------------------------------------------------------------------------------------------------
# Reading.


def _resolve_mav0(path: Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"EuRoC folder not found: {path}")
    if not path.is_dir():
        raise ValueError(f"EuRoC path is not a folder: {path}")
    if (path / "mav0").is_dir():
        return path / "mav0"
    if (path / "imu0").is_dir() or (path / "cam0").is_dir():
        return path
    raise FileNotFoundError(f"no mav0 folder (with cam0/ and imu0/) in {path}")


def _read_camera_yaml(path: Path) -> tuple[CameraCalibration, int, int]:
    data = read_yaml(path)
    # OpenCV-written files hold lists as ``!!opencv-matrix`` mappings: give the camera model their ``data``.
    lists = {k: v["data"] for k, v in data.items() if isinstance(v, dict) and "data" in v and k != "T_BS"}
    camera = camera_from_kalibr({**data, **lists}, str(path))
    T = read_T_BS(data, path)
    R_BC = T[:3, :3]
    rate_hz = yaml_number(data, path, "rate_hz")
    offset_s = yaml_number(data, path, "timeshift_cam_imu") if "timeshift_cam_imu" in data else 0.0
    intrinsics = (camera.fx, camera.fy, camera.cx, camera.cy)
    check_camera_ranges(path, intrinsics, (camera.width, camera.height), rate_hz, offset_s)
    calib = CameraCalibration(camera, R_BC.copy(), T[:3, 3].copy(), offset_s, rate_hz)
    return calib, camera.width, camera.height


def _read_imu_yaml(path: Path) -> tuple[ImuNoise, float]:
    data = read_yaml(path)
    keys = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density")
    densities = {key: yaml_number(data, path, key) for key in (*keys, "accelerometer_random_walk")}
    rate_hz = yaml_number(data, path, "rate_hz")
    check_imu_ranges(path, densities, rate_hz)
    return ImuNoise(*densities.values()), rate_hz


def _read_camera_csv(root: Path, cam: str) -> tuple[np.ndarray, tuple[Path, ...]]:
    """Stamps (ns) and image paths of ``root/cam/data.csv`` (every image must exist)."""
    cam_csv = root / cam / "data.csv"
    cam_lines, cam_rows = read_rows(cam_csv, 2)
    cam_t_ns = parse_ns(cam_csv, cam_lines, [r[0] for r in cam_rows])
    image_paths = []
    for line_no, (_, name) in zip(cam_lines, cam_rows, strict=True):
        image = root / cam / "data" / name
        if not image.is_file():
            raise FileNotFoundError(f"{cam_csv}, line {line_no}: image file not found: {image}")
        image_paths.append(image)
    return cam_t_ns, tuple(image_paths)


def read_euroc(path: Path | str) -> EurocDataset:
    """Load a EuRoC ASL folder (the folder holding ``mav0``, or ``mav0`` itself).

    Raises:
        FileNotFoundError: Missing folder, file or image (the message names it).
        ValueError: Malformed YAML/CSV content, naming the file, line and value.
    """
    root = _resolve_mav0(Path(path))
    calib, _, _ = _read_camera_yaml(root / "cam0" / "sensor.yaml")
    imu_noise, imu_rate_hz = _read_imu_yaml(root / "imu0" / "sensor.yaml")

    imu_path = root / "imu0" / "data.csv"
    imu_t_ns, imu_values = read_numeric_csv(imu_path, 7)
    imu = ImuSeries(
        ns_to_s(imu_t_ns),
        imu_values[:, :3].copy(),
        imu_values[:, 3:].copy(),
        np.zeros(len(imu_t_ns), dtype=bool),
    )

    cam_t_ns, image_paths = _read_camera_csv(root, "cam0")
    calib_right = cam1_t_ns = None
    image_paths_right: tuple[Path, ...] = ()
    if (root / "cam1" / "sensor.yaml").is_file():
        calib_right, _, _ = _read_camera_yaml(root / "cam1" / "sensor.yaml")
        cam1_t_ns, image_paths_right = _read_camera_csv(root, "cam1")

    truth = read_groundtruth(root)

    landmarks = None
    lm_path = root / "sim_landmarks0" / "data.csv"
    if lm_path.exists():
        lm_lines, lm_rows = read_rows(lm_path, 4)
        landmarks = parse_floats(lm_path, lm_lines, [r[1:] for r in lm_rows])

    return EurocDataset(
        root=root,
        imu=imu,
        cam_t_s=ns_to_s(cam_t_ns),
        image_paths=image_paths,
        calib=calib,
        imu_noise=imu_noise,
        imu_rate_hz=imu_rate_hz,
        groundtruth=None if truth is None else truth.trajectory,
        gt_gyro_bias=None if truth is None else truth.gyro_bias_rad_s,
        gt_accel_bias=None if truth is None else truth.accel_bias_m_s2,
        landmarks_W=landmarks,
        imu_t_ns=imu_t_ns,
        cam_t_ns=cam_t_ns,
        gt_t_ns=None if truth is None else truth.t_ns,
        groundtruth_source=None if truth is None else truth.source,
        calib_right=calib_right,
        cam1_t_s=None if cam1_t_ns is None else ns_to_s(cam1_t_ns),
        cam1_t_ns=cam1_t_ns,
        image_paths_right=image_paths_right,
    )


def load_image(dataset: EurocDataset, index: int, camera: int = 0) -> np.ndarray:
    """Frame ``index`` of ``cam0`` (``camera=0``) or ``cam1`` (``camera=1``) as grayscale uint8, shape (H, W).

    The size is checked against that camera's ``sensor.yaml``.

    Raises:
        IndexError: Index out of range.
        FileNotFoundError: The PNG is missing.
        ValueError: No such camera, the PNG cannot be decoded, is neither 8- nor 16-bit, or its size differs
            from the YAML resolution.
    """
    if camera not in (0, 1):
        raise ValueError(f"camera must be 0 or 1, got {camera!r}")
    if camera == 1 and dataset.calib_right is None:
        raise ValueError(f"{dataset.root}: no cam1 in this dataset (mono)")
    paths = dataset.image_paths if camera == 0 else dataset.image_paths_right
    calib = dataset.calib if camera == 0 else dataset.calib_right
    if not -len(paths) <= index < len(paths):
        raise IndexError(
            f"frame index {index} out of range for {len(paths)} cam{camera} frames in {dataset.root}"
        )
    path = paths[index]
    if not path.is_file():
        raise FileNotFoundError(f"image file not found: {path}")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path}: cannot decode image (corrupt or not a PNG)")
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)  # 16-bit PNGs (TUM-VI's EuRoC export): keep the high byte
    elif image.dtype != np.uint8:
        raise ValueError(f"{path}: expected an 8-bit or 16-bit image, got dtype {image.dtype}")
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    cam = calib.camera
    if image.shape != (cam.height, cam.width):
        raise ValueError(
            f"{path}: image size {image.shape[1]}x{image.shape[0]} does not match the resolution "
            f"{cam.width}x{cam.height} in cam{camera}/sensor.yaml"
        )
    return image
