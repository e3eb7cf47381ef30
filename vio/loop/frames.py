"""Rigid transforms and the 4-DOF (x, y, z, yaw) quantities of the pose graph.

A ``RigidTransform`` ``T_AB`` maps B coordinates to A: ``x_A = R_AB @ x_B + p_AB``. Roll and pitch are
observable
from gravity in VIO, so drift lives in yaw and translation only (VINS-Mono, Qin et al. 2018, Sec. VIII); the
4-DOF relative measurement between keyframes i and j, both gravity-aligned, is

    dyaw_ij = yaw_j - yaw_i,        dp_ij = Rz(yaw_i)^T (p_WBj - p_WBi),

i.e. the pose of j in the *yaw frame* of i (i's heading, world z up), which is unchanged by a 4-DOF drift
``(Rz(psi), t)`` applied to both poses. The heading is that of a body-fixed axis ``axis_B`` that stays
roughly horizontal: ``yaw = atan2((R a)_y, (R a)_x)``; any such axis shifts by exactly ``psi`` under a drift
``Rz(psi)``. Body x is not always it: the EuRoC IMU's x axis points up, where its heading is undefined.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp
from viotb.vio.lie import rotz, yaw_from_rotmat

X_AXIS = np.array([1.0, 0.0, 0.0])


def heading_rad(R_WB: np.ndarray, axis_B: np.ndarray = X_AXIS) -> float:
    """Heading (rad) of the body axis ``axis_B`` (shape (3,)) in the world xy plane."""
    a_W = R_WB @ axis_B
    return float(np.arctan2(a_W[1], a_W[0]))


def horizontal_axis_B(R_WB: np.ndarray) -> np.ndarray:
    """The body-frame direction that points along world x at attitude ``R_WB``, shape (3,)."""
    return R_WB.T @ X_AXIS


def wrap_angle(angle_rad: float) -> float:
    """Angle wrapped to ``[-pi, pi)`` (rad)."""
    return float((angle_rad + np.pi) % (2.0 * np.pi) - np.pi)


@dataclass(frozen=True)
class RigidTransform:
    """A rigid transform ``T_AB``: ``x_A = R @ x_B + p``.

    Attributes:
        R: Rotation B -> A, shape (3, 3).
        p: Origin of B in A (m), shape (3,).
    """

    R: np.ndarray
    p: np.ndarray

    @classmethod
    def identity(cls) -> RigidTransform:
        """The identity transform."""
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_yaw(cls, yaw_rad: float, p: np.ndarray) -> RigidTransform:
        """A 4-DOF transform: rotation about world z by ``yaw_rad``, then translation ``p`` (m)."""
        return cls(rotz(yaw_rad), np.asarray(p, dtype=float).copy())

    def inverse(self) -> RigidTransform:
        """``T_BA``."""
        return RigidTransform(self.R.T, -self.R.T @ self.p)

    def __matmul__(self, other: RigidTransform) -> RigidTransform:
        """Composition ``T_AB @ T_BC = T_AC``."""
        return RigidTransform(self.R @ other.R, self.R @ other.p + self.p)

    def apply_pose(self, R_XB: np.ndarray, p_XB: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pose of B expressed in A given its pose in X = this transform's source frame: ``(R @ R_XB,.

        R @ p + p)``.
        """
        return self.R @ R_XB, self.R @ p_XB + self.p

    def quat_xyzw(self) -> np.ndarray:
        """Rotation as a Hamilton quaternion, ``(x, y, z, w)`` order, shape (4,)."""
        return Rotation.from_matrix(self.R).as_quat()

    def yaw_rad(self) -> float:
        """Heading of ``R`` (rad)."""
        return yaw_from_rotmat(self.R)


def interpolate(T0: RigidTransform, T1: RigidTransform, alpha: float) -> RigidTransform:
    """SLERP of the rotation and linear interpolation of the translation, ``alpha`` in [0, 1]."""
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0.R, T1.R])))
    R = slerp([float(alpha)]).as_matrix()[0]
    return RigidTransform(R, (1.0 - alpha) * T0.p + alpha * T1.p)


def relative_4dof(
    R_WBi: np.ndarray, p_WBi: np.ndarray, R_WBj: np.ndarray, p_WBj: np.ndarray, axis_B: np.ndarray = X_AXIS
) -> tuple[float, np.ndarray]:
    """4-DOF pose of j in the yaw frame of i from two poses in one world frame.

    Returns:
        ``(dyaw_rad, dp_m)``: ``yaw_j - yaw_i`` wrapped, and ``Rz(yaw_i)^T (p_j - p_i)``, shape (3,).
    """
    yaw_i = heading_rad(R_WBi, axis_B)
    dyaw = wrap_angle(heading_rad(R_WBj, axis_B) - yaw_i)
    return dyaw, rotz(yaw_i).T @ (np.asarray(p_WBj) - np.asarray(p_WBi))


def loop_4dof(
    R_WBi: np.ndarray, T_ij: RigidTransform, axis_B: np.ndarray = X_AXIS
) -> tuple[float, np.ndarray]:
    """4-DOF measurement from a 6-DOF relative pose ``T_ij`` (j's body in i's body) and i's attitude.

    Only i's roll and pitch matter (its yaw cancels), so ``R_WBi`` may be in any yaw-drifted frame.

    Returns:
        ``(dyaw_rad, dp_m)`` as :func:`relative_4dof`.
    """
    R_WBj = R_WBi @ T_ij.R
    return relative_4dof(R_WBi, np.zeros(3), R_WBj, R_WBi @ T_ij.p, axis_B)


def projection_jacobian(p_C: np.ndarray) -> np.ndarray:
    """Jacobian of the normalized projection ``(x / z, y / z)`` with respect to the point, shape (N, 2, 3).

    Args:
        p_C: Points in the camera frame (m), shape (N, 3), positive depth.
    """
    x, y, z = p_C[:, 0], p_C[:, 1], p_C[:, 2]
    d_proj = np.zeros((len(p_C), 2, 3))
    d_proj[:, 0, 0] = d_proj[:, 1, 1] = 1.0 / z
    d_proj[:, 0, 2], d_proj[:, 1, 2] = -x / z**2, -y / z**2
    return d_proj


def tilt_error_rad(R_WB_a: np.ndarray, R_WB_b: np.ndarray) -> float:
    """Angle between the gravity directions that two attitudes imply in the body frame (rad).

    Zero when ``R_WB_a`` and ``R_WB_b`` differ only by a rotation about world z.
    """
    z_a = R_WB_a.T[:, 2]
    z_b = R_WB_b.T[:, 2]
    return float(np.arccos(np.clip(z_a @ z_b, -1.0, 1.0)))


def drift_4dof(
    R_WB_map: np.ndarray,
    p_WB_map: np.ndarray,
    R_WB_odom: np.ndarray,
    p_WB_odom: np.ndarray,
    axis_B: np.ndarray = X_AXIS,
) -> RigidTransform:
    """The 4-DOF transform ``T_map_odom`` that carries an odometry pose onto its map pose.

    ``yaw = yaw(R_map) - yaw(R_odom)``, ``p = p_map - Rz(yaw) p_odom`` (VINS-Mono's ``r_drift``, ``t_drift``).

    Returns:
        RigidTransform: ``T_W_corrected_from_W_odom``.
    """
    yaw = wrap_angle(heading_rad(R_WB_map, axis_B) - heading_rad(R_WB_odom, axis_B))
    return RigidTransform.from_yaw(yaw, np.asarray(p_WB_map) - rotz(yaw) @ np.asarray(p_WB_odom))
