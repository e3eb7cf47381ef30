"""Ground truth from every source a EuRoC-layout folder ships (envs/data/euroc_truth.py), and its gaps.

TUM-VI's EuRoC export has ``mocap0`` (pose only, partial coverage) instead of EuRoC's
``state_groundtruth_estimate0``; raw EuRoC folders also have ``vicon0`` with a marker ``T_BS``. The expected
body poses here are composed with 4x4 homogeneous matrices, independently of the reader's rotation algebra.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from data_paths import EUROC_MICRO
from scipy.spatial.transform import Rotation
from viotb.envs.data.euroc import read_euroc
from viotb.vio.metrics import evaluate_trajectory, ground_truth_gaps, interpolate_trajectory
from viotb.vio.types import TrajectoryArrays

POSE_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"


@pytest.fixture
def mono_copy(tmp_path):
    """The micro dataset's cam0 and imu0 (a few rows), without any ground truth."""
    if not EUROC_MICRO.exists():
        pytest.skip("EuRoC micro dataset not present")
    src, dst = EUROC_MICRO / "mav0", tmp_path / "ds" / "mav0"
    for sub in ("cam0/data", "imu0"):
        (dst / sub).mkdir(parents=True)
    for name in ("cam0/sensor.yaml", "imu0/sensor.yaml"):
        shutil.copy(src / name, dst / name)
    for name, rows in (("cam0/data.csv", 3), ("imu0/data.csv", 50)):
        lines = (src / name).read_text().splitlines(keepends=True)
        (dst / name).write_text("".join(lines[: rows + 1]))
    for line in (dst / "cam0/data.csv").read_text().splitlines()[1:]:
        png = line.split(",")[1]
        (dst / "cam0/data" / png).symlink_to(src / "cam0/data" / png)
    return dst


def _poses(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t_ns = 1_403_715_273_262_142_976 + np.arange(n, dtype=np.int64) * 8_333_333  # 120 Hz mocap
    p = rng.normal(size=(n, 3))
    quat_xyzw = Rotation.random(n, random_state=rng).as_quat()
    return t_ns, p, np.roll(quat_xyzw, 1, axis=1)


def _write_pose_csv(folder, t_ns, p, q_wxyz, T_BS=None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rows = [POSE_HEADER] + [
        ",".join([str(t)] + [repr(float(v)) for v in (*x, *q)])
        for t, x, q in zip(t_ns, p, q_wxyz, strict=True)
    ]
    (folder / "data.csv").write_text("\n".join(rows) + "\n")
    if T_BS is not None:
        data = ", ".join(repr(float(v)) for v in T_BS.ravel())
        (folder / "sensor.yaml").write_text(
            f"%YAML:1.0\nsensor_type: pose\nT_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"
        )


def test_mocap0_with_marker_extrinsic_gives_the_body_pose(mono_copy):
    rng = np.random.default_rng(1)
    t_ns, p_RS, q_RS = _poses(40, rng)
    T_BS = np.eye(4)
    T_BS[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix()
    T_BS[:3, 3] = [0.05, -0.02, 0.11]
    _write_pose_csv(mono_copy / "mocap0", t_ns, p_RS, q_RS, T_BS)
    ds = read_euroc(mono_copy)
    assert ds.groundtruth_source == "mocap0"
    assert ds.gt_gyro_bias is None and ds.groundtruth.v_WB is None
    np.testing.assert_array_equal(ds.gt_t_ns, t_ns)
    for k in (0, 17, 39):
        T_RS = np.eye(4)
        T_RS[:3, :3] = Rotation.from_quat(np.roll(q_RS[k], -1)).as_matrix()
        T_RS[:3, 3] = p_RS[k]
        T_RB = T_RS @ np.linalg.inv(T_BS)
        np.testing.assert_allclose(ds.groundtruth.p_WB[k], T_RB[:3, 3], atol=1e-12)
        R = Rotation.from_quat(np.roll(ds.groundtruth.quat_wxyz_WB[k], -1)).as_matrix()
        np.testing.assert_allclose(R, T_RB[:3, :3], atol=1e-12)


def test_source_order_identity_pose_and_errors(mono_copy):
    rng = np.random.default_rng(2)
    t_ns, p, q = _poses(10, rng)
    assert read_euroc(mono_copy).groundtruth is None
    _write_pose_csv(mono_copy / "vicon0", t_ns, p, q)
    ds = read_euroc(mono_copy)
    # No sensor.yaml: the pose is the body's, taken as written.
    assert ds.groundtruth_source == "vicon0"
    np.testing.assert_array_equal(ds.groundtruth.p_WB, p)
    np.testing.assert_allclose(ds.groundtruth.quat_wxyz_WB, q, atol=1e-15)
    _write_pose_csv(mono_copy / "mocap0", t_ns, p + 1.0, q)
    assert read_euroc(mono_copy).groundtruth_source == "mocap0"  # mocap0 before vicon0
    # Bad files are named with the line and value.
    path = mono_copy / "mocap0" / "data.csv"
    lines = path.read_text().splitlines()
    lines[3] = lines[2]  # a duplicated row: duplicate stamps
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"mocap0/data\.csv, lines 3-4: duplicate timestamps"):
        read_euroc(mono_copy)
    _write_pose_csv(mono_copy / "mocap0", t_ns, p, 2.0 * q)
    with pytest.raises(ValueError, match=r"mocap0/data\.csv: quaternion of data row 1 has norm 2\.0"):
        read_euroc(mono_copy)
    _write_pose_csv(mono_copy / "mocap0", t_ns, p, q, T_BS=np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match=r"mocap0/sensor\.yaml: T_BS rotation block is not a rotation"):
        read_euroc(mono_copy)


def _line(t_s: np.ndarray) -> TrajectoryArrays:
    n = t_s.size
    return TrajectoryArrays(
        t_s, np.column_stack([t_s, np.sin(t_s), np.zeros(n)]), np.tile([1.0, 0, 0, 0], (n, 1))
    )


def test_interpolation_does_not_bridge_a_ground_truth_gap():
    # 100 Hz truth over [0, 2] s and [7, 9] s (mocap only at the start and the end, as in TUM-VI's corridors).
    t_gt = np.concatenate([np.arange(0.0, 2.0, 0.01), np.arange(7.0, 9.0, 0.01)])
    gt = _line(t_gt)
    np.testing.assert_array_equal(ground_truth_gaps(t_gt), [199])
    assert ground_truth_gaps(t_gt, max_gap_s=6.0).size == 0
    assert ground_truth_gaps(np.arange(0.0, 30.0, 1.0)).size == 0  # a 1 Hz truth still interpolates
    t_est = np.arange(0.0, 9.0, 0.05)
    _, inside = interpolate_trajectory(gt, t_est)
    np.testing.assert_array_equal(inside, (t_est <= t_gt[199]) | (t_est >= 7.0))
    # An estimate exact where the truth exists and 1 m off inside the gap: the gap is not scored.
    est = _line(t_est)
    off = (t_est > t_gt[199]) & (t_est < 7.0)
    est.p_WB[off, 2] += 1.0
    metrics = evaluate_trajectory(est, gt)
    assert metrics["ate_posyaw_m"] < 1e-9
    assert metrics["frames"] == int(np.sum(~off))
