"""Ground truth of a EuRoC-layout folder, from whichever source it ships.

Sources, in the order they are looked for under ``mav0/``:

* ``state_groundtruth_estimate0/data.csv``: EuRoC's (and OpenVINS' vicon2gt) full state of the body/IMU frame:
  ``t, p xyz, q wxyz, v xyz, bw xyz, ba xyz`` (17 columns).
* ``mocap0/data.csv``: a motion-capture pose ``t, p xyz, q wxyz`` (8 columns), as TUM-VI ships it in its EuRoC
  export (already in the IMU frame; its ``sensor.yaml``, when present, says so with an identity ``T_BS``).
* ``vicon0/data.csv``: EuRoC's raw Vicon pose of the marker body ``S`` (8 columns), with ``T_BS`` (the marker
  frame in the IMU frame) in ``vicon0/sensor.yaml``.

The pose files give ``T_RS``, the sensor frame ``S`` in the mocap frame ``R``; the body pose is
``T_RB = T_RS @ inv(T_BS)`` (ASL sensor convention, Burri et al., IJRR 2016). Pose-only sources carry no
velocity or biases (``None``). Motion capture often covers only part of a sequence (TUM-VI's corridors
and outdoor runs: the start and the end); :func:`viotb.vio.metrics.interpolate_trajectory` does not bridge
such gaps.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc_files import ns_to_s, read_numeric_csv, read_T_BS, read_yaml
from viotb.vio.lie import quat_wxyz_to_rotmat, rotmat_to_quat_wxyz
from viotb.vio.types import TrajectoryArrays

GROUNDTRUTH_SOURCES = ("state_groundtruth_estimate0", "mocap0", "vicon0")
"""Folders under ``mav0`` read as ground truth, first found wins."""


@dataclass(frozen=True)
class GroundTruth:
    """Ground truth of the body (IMU) frame B in the world (mocap) frame W.

    Attributes:
        trajectory: Poses of B in W, with velocities where the source has them.
        t_ns: Stamps (ns), shape (M,), int64.
        gyro_bias_rad_s: Gyro bias, shape (M, 3), or None.
        accel_bias_m_s2: Accelerometer bias, shape (M, 3), or None.
        source: The folder it was read from (one of :data:`GROUNDTRUTH_SOURCES`).
    """

    trajectory: TrajectoryArrays
    t_ns: np.ndarray
    gyro_bias_rad_s: np.ndarray | None
    accel_bias_m_s2: np.ndarray | None
    source: str


def _unit_quaternions(path: Path, quat_wxyz: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(quat_wxyz, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        row = int(bad[0])
        raise ValueError(f"{path}: quaternion of data row {row + 1} has norm {norms[row]:.6f}")
    return quat_wxyz / norms[:, None]


def _sensor_T_BS(folder: Path) -> np.ndarray:
    """``T_BS`` (4, 4) of a pose sensor's ``sensor.yaml``; identity when the file or the field is absent."""
    path = folder / "sensor.yaml"
    if not path.is_file():
        return np.eye(4)
    data = read_yaml(path)
    if "T_BS" not in data:
        return np.eye(4)
    return read_T_BS(data, path)


def _read_state(path: Path) -> GroundTruth:
    t_ns, gt = read_numeric_csv(path, 17)
    quat = _unit_quaternions(path, gt[:, 3:7])
    traj = TrajectoryArrays(ns_to_s(t_ns), gt[:, 0:3].copy(), quat, gt[:, 7:10].copy())
    return GroundTruth(traj, t_ns, gt[:, 10:13].copy(), gt[:, 13:16].copy(), path.parent.name)


def _read_pose(path: Path) -> GroundTruth:
    """A pose-only source: ``T_RB = T_RS @ inv(T_BS)`` for every row."""
    t_ns, rows = read_numeric_csv(path, 8)
    quat_RS = _unit_quaternions(path, rows[:, 3:7])
    T_BS = _sensor_T_BS(path.parent)
    if np.array_equal(T_BS, np.eye(4)):
        traj = TrajectoryArrays(ns_to_s(t_ns), rows[:, 0:3].copy(), quat_RS, None)
        return GroundTruth(traj, t_ns, None, None, path.parent.name)
    R_SB = T_BS[:3, :3].T
    p_SB = -R_SB @ T_BS[:3, 3]
    R_RS = np.stack([quat_wxyz_to_rotmat(q) for q in quat_RS])
    R_RB = R_RS @ R_SB
    p_RB = rows[:, 0:3] + R_RS @ p_SB
    quat_RB = np.stack([rotmat_to_quat_wxyz(R) for R in R_RB])
    traj = TrajectoryArrays(ns_to_s(t_ns), p_RB, quat_RB, None)
    return GroundTruth(traj, t_ns, None, None, path.parent.name)


def read_groundtruth(mav0: Path) -> GroundTruth | None:
    """The first ground-truth source found under ``mav0`` (see the module docstring), or None.

    Raises:
        ValueError: A malformed file: wrong column count, non-monotonic or duplicate stamps, non-finite
            values, a non-unit quaternion, a bad ``T_BS`` (the message names the file, line and value).
    """
    for name in GROUNDTRUTH_SOURCES:
        path = mav0 / name / "data.csv"
        if path.exists():
            return _read_state(path) if name == "state_groundtruth_estimate0" else _read_pose(path)
    return None
