"""Online calibration of the sliding window: extrinsics per camera, one time offset, the IMU intrinsics.

Variables (kept after the keyframes' error states in the window's system, never marginalized): per camera
``c`` the extrinsic rotation and translation, ``R_BC = R_BC,0 Exp(dtheta_c)`` (right perturbation, camera
frame: the MSCKF's and :class:`viotb.vio.types.CalibrationDrift`'s convention) and ``p_BC = p_BC,0 + dp_c``
(m, body frame), the correction ``td`` (s) of the file's camera-IMU time offset (the cameras share
one clock), and the IMU's correction matrices ``w_B = T_g (w_m - b_g)``, ``a_B = T_a (a_m - b_a)`` (the
MSCKF's model, :mod:`viotb.vio.imu_intrinsics`; additive, nine entries each, row-major). The full vector
is ``[dtheta_0, dp_0, dtheta_1, dp_1, ..., td, vec(dT_g), vec(dT_a)]`` (6 per camera + 1 + 18); only the
estimated entries (:class:`CalibLayout`) enter the system. The intrinsics enter the IMU factors only
(:func:`viotb.vio.window_batch.imu_factors`, the preintegration's first-order intrinsics Jacobians), the
extrinsics and time offset the reprojection factors only.

Time offset as in VINS-Mono (Qin and Shen, "Online Temporal Calibration for Monocular Visual-Inertial
Systems", IROS 2018, eq. 5-6): the keyframe's state is at the frame's IMU time by the file's offset; a
feature moving in the image at ``V`` (normalized coordinates per second) is where the keyframe would have
seen it at ``xy - td V``, so the reprojection residual is ``h(x_k, p_l; R_BC, p_BC) - (xy - td V)`` and
``d r / d td = V``. If the image was really taken at IMU time ``t_cam + offset_file + delta``, ``td``
converges to ``delta`` (the estimated minus the given offset). Unlike VINS-Mono, ``V`` is not the measured
feature velocity of consecutive frames: that difference holds the observation's own noise, which then
correlates with the residual and biases ``td`` (by about ``sigma^2 / (dt E|V|^2)``: 1.9 ms on the
simulated 0.5 px figure-8 with the right file). It is the predicted one, from the keyframe's velocity and
angular rate (the gyro reading at the keyframe less its bias; :func:`image_velocity`), i.e. the pose at
``t + td`` to first order. ``V`` is held at each linearization point (as VINS-Mono holds its measured
``V``): the Jacobians leave out ``td dV/dx``, a term of the size ``td`` (ms) times the pose Jacobian.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.lie import exp_so3, log_so3
from viotb.vio.types import CalibrationDrift


@dataclass(frozen=True)
class CalibLayout:
    """Which calibration variables are estimated.

    Attributes:
        n_cams: Cameras (1 mono, 2 stereo).
        extrinsics: Estimate every camera's ``R_BC``, ``p_BC``.
        time_offset: Estimate the time offset correction ``td``.
        gyro_intrinsics: Estimate the gyro's correction matrix ``T_g``.
        accel_intrinsics: Estimate the accelerometer's ``T_a``.
    """

    n_cams: int
    extrinsics: bool
    time_offset: bool
    gyro_intrinsics: bool = False
    accel_intrinsics: bool = False

    @property
    def td_index(self) -> int:
        """Index of ``td`` in the full vector (after the cameras' 6 entries each)."""
        return 6 * self.n_cams

    @property
    def full_dim(self) -> int:
        """Length of the full vector ``[dtheta_c, dp_c]_c, td, vec(dT_g), vec(dT_a)`` (6 per camera + 19)."""
        return 6 * self.n_cams + 19

    @property
    def active(self) -> np.ndarray:
        """Indices of the estimated entries in the full vector, shape (C,)."""
        idx = list(range(6 * self.n_cams)) if self.extrinsics else []
        idx += [self.td_index] if self.time_offset else []
        idx += list(range(self.td_index + 1, self.td_index + 10)) if self.gyro_intrinsics else []
        idx += list(range(self.td_index + 10, self.td_index + 19)) if self.accel_intrinsics else []
        return np.array(idx, dtype=np.int64)

    @property
    def camera_terms(self) -> bool:
        """Whether any estimated entry enters the reprojection factors (extrinsics or time offset)."""
        return self.extrinsics or self.time_offset

    @property
    def imu_terms(self) -> bool:
        """Whether any estimated entry enters the IMU factors (a correction matrix)."""
        return self.gyro_intrinsics or self.accel_intrinsics

    def imu_columns(self, J_full_T: np.ndarray) -> np.ndarray:
        """The estimated columns of Jacobians w.r.t. ``[vec(dT_g), vec(dT_a)]`` (..., 18) -> (..., C)."""
        J = np.zeros((*J_full_T.shape[:-1], self.full_dim))
        J[..., self.td_index + 1 :] = J_full_T
        return J[..., self.active]

    @property
    def dim(self) -> int:
        """C, the estimated entries."""
        return len(self.active)


@dataclass(frozen=True)
class CalibValues:
    """Current camera-IMU calibration.

    Attributes:
        R_BC: Per camera, camera-to-body rotation, shape (3, 3).
        p_BC: Per camera, camera origin in B (m), shape (3,).
        td_s: Time offset correction (s), added to the file's ``time_offset_s``.
        T_g: Gyro correction matrix ``w_B = T_g (w_m - b_g)``, shape (3, 3) (identity: none).
        T_a: Accelerometer correction matrix ``a_B = T_a (a_m - b_a)``, shape (3, 3).
    """

    R_BC: tuple[np.ndarray, ...]
    p_BC: tuple[np.ndarray, ...]
    td_s: float
    T_g: np.ndarray = field(default_factory=lambda: np.eye(3))
    T_a: np.ndarray = field(default_factory=lambda: np.eye(3))

    @classmethod
    def from_files(cls, calib: CameraCalibration, calib_right: CameraCalibration | None) -> CalibValues:
        """The files' calibration (``td = 0``)."""
        cams = [calib] if calib_right is None else [calib, calib_right]
        return cls(
            tuple(np.asarray(c.R_BC, dtype=float) for c in cams),
            tuple(np.asarray(c.p_BC, dtype=float) for c in cams),
            0.0,
        )

    def cameras(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """``(R_BC (3, 3), p_BC (3,) m)`` per camera."""
        return list(zip(self.R_BC, self.p_BC, strict=True))

    def imu_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """``(T_g, T_a)``, each shape (3, 3)."""
        return self.T_g, self.T_a

    def imu_vector(self) -> np.ndarray:
        """``[vec(T_g), vec(T_a)]`` row-major, shape (18,)."""
        return np.concatenate([self.T_g.ravel(), self.T_a.ravel()])

    def retract(self, layout: CalibLayout, dx: np.ndarray) -> CalibValues:
        """``self [+] dx`` for the estimated entries ``dx`` (C,)."""
        d = np.zeros(layout.full_dim)
        d[layout.active] = dx
        R = tuple(R @ exp_so3(d[6 * c : 6 * c + 3]) for c, R in enumerate(self.R_BC))
        p = tuple(p + d[6 * c + 3 : 6 * c + 6] for c, p in enumerate(self.p_BC))
        k = layout.td_index
        T_g, T_a = self.T_g + d[k + 1 : k + 10].reshape(3, 3), self.T_a + d[k + 10 : k + 19].reshape(3, 3)
        return CalibValues(R, p, self.td_s + float(d[k]), T_g, T_a)

    def boxminus(self, layout: CalibLayout, x0: CalibValues) -> np.ndarray:
        """``self [-] x0`` of the estimated entries, shape (C,)."""
        d = np.zeros(layout.full_dim)
        for c in range(layout.n_cams):
            d[6 * c : 6 * c + 3] = log_so3(x0.R_BC[c].T @ self.R_BC[c])
            d[6 * c + 3 : 6 * c + 6] = self.p_BC[c] - x0.p_BC[c]
        k = layout.td_index
        d[k] = self.td_s - x0.td_s
        d[k + 1 :] = self.imu_vector() - x0.imu_vector()
        return d[layout.active]


def calib_jacobian(
    R_WB: np.ndarray,
    p_WB: np.ndarray,
    p_W: np.ndarray,
    R_BC: np.ndarray,
    p_BC: np.ndarray,
    omega_B_rad_s: np.ndarray,
    v_W_m_s: np.ndarray,
    cam: int,
    layout: CalibLayout,
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobian of the normalized reprojection residual w.r.t. the estimated calibration, and ``V``.

    ``p_C = R_BC^T (q - p_BC)``, ``q = R_WB^T (p_W - p_WB)``: ``d p_C / d dtheta_c = [p_C]x``
    (``R_BC Exp(dtheta)``), ``d p_C / d dp_c = -R_BC^T``; ``d r / d td = V`` (module docstring), with
    ``dq/dt = q x omega_B - R_WB^T v_W`` (:func:`image_velocity` in closed form, without ``J_pose``).

    Args:
        R_WB: Keyframe orientations, shape (M, 3, 3).
        p_WB: Keyframe positions (m), shape (M, 3).
        p_W: Landmarks in W (m), shape (M, 3).
        R_BC: This camera's rotation, shape (3, 3).
        p_BC: Its origin in B (m), shape (3,).
        omega_B_rad_s: Angular rate of each observation's keyframe (gyro less bias), shape (M, 3).
        v_W_m_s: Its velocity, shape (M, 3).
        cam: Camera index (its columns in the full vector).
        layout: The estimated entries.

    Returns:
        ``(J (M, 2, C), V (M, 2) normalized coordinates per s)``.
    """
    q = np.einsum("mji,mj->mi", R_WB, p_W - p_WB)
    p_C = (q - p_BC) @ R_BC
    Z = p_C[:, 2]
    Zs = np.where(np.abs(Z) < 1e-9, 1e-9, Z)
    dz = np.zeros((len(q), 2, 3))
    dz[:, 0, 0] = dz[:, 1, 1] = 1.0 / Zs
    dz[:, :, 2] = -p_C[:, :2] / (Zs * Zs)[:, None]
    sk = np.zeros((len(q), 3, 3))
    sk[:, 0, 1], sk[:, 0, 2], sk[:, 1, 2] = -p_C[:, 2], p_C[:, 1], -p_C[:, 0]
    sk[:, 1, 0], sk[:, 2, 0], sk[:, 2, 1] = p_C[:, 2], -p_C[:, 1], p_C[:, 0]
    A = dz @ R_BC.T  # d z / d q
    dq_dt = np.cross(q, omega_B_rad_s) - np.einsum("mji,mj->mi", R_WB, v_W_m_s)
    vel = np.einsum("mij,mj->mi", A, dq_dt)
    J = np.zeros((len(q), 2, layout.full_dim))
    J[:, :, 6 * cam : 6 * cam + 3] = dz @ sk
    J[:, :, 6 * cam + 3 : 6 * cam + 6] = -A
    J[:, :, layout.td_index] = vel
    return J[:, :, layout.active], vel


def image_velocity(J_pose: np.ndarray, omega_B_rad_s: np.ndarray, v_W_m_s: np.ndarray) -> np.ndarray:
    """Image velocity ``V = dz/dt`` of static points from the keyframe's motion, (M, 2) per s.

    With the body turning at ``omega_B`` and moving at ``v_W``, the right-perturbed pose moves by
    ``[dtheta, dp] = [omega_B, v_W] dt``, so ``V = J_pose [omega_B; v_W]`` (the pose's reprojection Jacobian).

    Args:
        J_pose: Reprojection Jacobians w.r.t. ``[dtheta, dp]``, shape (M, 2, 6).
        omega_B_rad_s: Angular rate of each observation's keyframe (gyro less bias), shape (M, 3).
        v_W_m_s: Its velocity, shape (M, 3).
    """
    return np.einsum("mij,mj->mi", J_pose, np.concatenate([omega_B_rad_s, v_W_m_s], axis=1))


def calibration_drift(
    values: CalibValues, layout: CalibLayout, cov: np.ndarray, given: CameraCalibration
) -> CalibrationDrift:
    """Cam0's estimated minus given calibration with sigmas (NaN where not estimated).

    Args:
        values: Current calibration.
        layout: The estimated entries.
        cov: Their covariance, shape (C, C).
        given: Cam0's file calibration.
    """
    sig_full = np.full(layout.full_dim, np.nan)
    sig_full[layout.active] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    out: dict = {}
    if layout.time_offset:
        out["time_offset_s"], out["time_offset_sigma_s"] = values.td_s, float(sig_full[layout.td_index])
    if layout.extrinsics:
        out["rotation_BC_rad"] = log_so3(np.asarray(given.R_BC).T @ values.R_BC[0])
        out["rotation_sigma_rad"] = sig_full[0:3]
        out["translation_BC_m"] = values.p_BC[0] - np.asarray(given.p_BC, dtype=float)
        out["translation_sigma_m"] = sig_full[3:6]
    return CalibrationDrift(**out)
