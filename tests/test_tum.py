"""Tests of the TUM trajectory format (envs/tum.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.envs.data.tum import read_tum, write_tum
from viotb.vio.types import TrajectoryArrays


def _trajectory(n: int = 50) -> TrajectoryArrays:
    rng = np.random.default_rng(0)
    quat_xyzw = Rotation.random(n, random_state=1).as_quat()
    return TrajectoryArrays(
        1403715273.262143 + np.arange(n) * 0.05, rng.normal(size=(n, 3)), quat_xyzw[:, [3, 0, 1, 2]]
    )


def test_round_trip_exact(tmp_path):
    traj = _trajectory()
    path = write_tum(tmp_path / "sub" / "est.txt", traj)
    back = read_tum(path)
    np.testing.assert_array_equal(back.t_s, traj.t_s)
    np.testing.assert_array_equal(back.p_WB, traj.p_WB)
    np.testing.assert_allclose(back.quat_wxyz_WB, traj.quat_wxyz_WB, rtol=0, atol=1e-15)
    assert back.v_WB is None


def test_column_order_is_xyzw(tmp_path):
    """A 90 deg yaw: TUM stores qx qy qz qw = 0 0 sin45 cos45 (checked against scipy)."""
    quat_xyzw = Rotation.from_euler("z", 90, degrees=True).as_quat()
    traj = TrajectoryArrays(np.array([1.5]), np.array([[1.0, 2.0, 3.0]]), quat_xyzw[None, [3, 0, 1, 2]])
    path = write_tum(tmp_path / "one.txt", traj)
    values = [float(v) for v in path.read_text().splitlines()[1].split()]
    np.testing.assert_allclose(values, [1.5, 1.0, 2.0, 3.0, *quat_xyzw], atol=1e-15)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("1 2 3 4 0 0 0\n", r"line 1: expected 8 values"),
        ("# c\n1 2 3 x 0 0 0 1\n", r"line 2: not a number"),
        ("1 2 3 nan 0 0 0 1\n", r"line 1: non-finite"),
        ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", r"lines 1-2: times must strictly increase"),
        ("1 0 0 0 0 0 0 0\n", r"line 1: zero quaternion"),
        ("# only a comment\n", r"no poses"),
    ],
)
def test_bad_files_name_line_and_value(tmp_path, content, message):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(ValueError, match=message):
        read_tum(path)


def test_missing_file_and_bad_arrays(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        read_tum(tmp_path / "nope.txt")
    traj = _trajectory(3)
    bad = TrajectoryArrays(traj.t_s, traj.p_WB[:2], traj.quat_wxyz_WB)
    with pytest.raises(ValueError, match="expected p_WB"):
        write_tum(tmp_path / "x.txt", bad)
    p = traj.p_WB.copy()
    p[1, 0] = np.inf
    with pytest.raises(ValueError, match="pose 1 is not finite"):
        write_tum(tmp_path / "y.txt", TrajectoryArrays(traj.t_s, p, traj.quat_wxyz_WB))
