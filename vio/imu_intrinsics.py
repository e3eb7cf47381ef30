"""Online IMU intrinsics: a 3x3 correction matrix per sensor, estimated as optional state blocks.

Model (Yang, Geneva, Huang et al., "Online IMU intrinsic calibration: is it necessary?", RSS 2020; open_vins
``calib_imu_intrinsics``). The readings are corrected as::

    w_B = T_g (w_m - b_g),        a_B = T_a (a_m - b_a)

``T_g`` and ``T_a`` (3, 3) undo the sensors' scale factors and axis misalignments (a sensor that reads
``w_m = M w_B + b`` has ``T_g = M^-1``). The error state of each is the additive ``dT`` of all nine entries,
row-major (``T = T_hat + dT``): blocks ``imu_intr_gyro`` (9) and ``imu_intr_accel`` (9), right after the IMU
block. open_vins parametrizes each matrix as a triangular 6 plus one sensor-to-IMU rotation, because its IMU
frame is defined by one of the two sensors while the camera extrinsic is estimated too; here the body frame
is tied to the camera through a given extrinsic, so the full matrix of either sensor is observable from the
camera's rotation and the gravity direction when the head turns about more than one axis (the priors keep it
bounded when it does not).

The readings enter the propagation only through ``w_B`` and ``a_B``, so the transition columns of ``dT`` are
the existing ones with respect to the corrected readings times ``dw/d dT = kron(I_3, (w_m - b_g)^T)``
(:func:`viotb.vio.imu_integration.intrinsic_columns`), and the bias columns become the old ones times ``T``
(``dw = -T_g db_g``), which also carries the white noise (``T_g n_g``) into the process noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GYRO_INTRINSICS_BLOCK = "imu_intr_gyro"
ACCEL_INTRINSICS_BLOCK = "imu_intr_accel"
INTRINSICS_SENSOR_DIM = 9
INTRINSICS_CHOICES = ("none", "gyro", "gyro+accel")


@dataclass
class ImuIntrinsics:
    """Current correction matrices and which of them are estimated (mutable; written by the filter).

    Attributes:
        T_g: Gyro correction ``w_B = T_g (w_m - b_g)``, shape (3, 3).
        T_a: Accelerometer correction ``a_B = T_a (a_m - b_a)``, shape (3, 3).
        gyro: Whether ``T_g`` has a state block (else it is held).
        accel: Whether ``T_a`` has a state block (else it is held).
    """

    T_g: np.ndarray
    T_a: np.ndarray
    gyro: bool = True
    accel: bool = False

    @classmethod
    def identity(cls, gyro: bool, accel: bool) -> ImuIntrinsics:
        """Identity matrices (the uncalibrated prior mean) with the given blocks."""
        return cls(np.eye(3), np.eye(3), bool(gyro), bool(accel))

    @classmethod
    def from_choice(cls, choice: str) -> ImuIntrinsics | None:
        """``"none"`` -> None, ``"gyro"``, ``"gyro+accel"`` (ValueError naming the value otherwise)."""
        if choice not in INTRINSICS_CHOICES:
            raise ValueError(
                f"MsckfParams.imu_intrinsics must be one of {INTRINSICS_CHOICES}, got {choice!r}"
            )
        if choice == "none":
            return None
        return cls.identity(True, choice == "gyro+accel")

    @property
    def dim(self) -> int:
        """Error-state dimension of the estimated blocks (9 per sensor)."""
        return INTRINSICS_SENSOR_DIM * (int(self.gyro) + int(self.accel))

    def block_names(self) -> list[str]:
        """Names of the estimated blocks, in state order (gyro first)."""
        names = ((GYRO_INTRINSICS_BLOCK, self.gyro), (ACCEL_INTRINSICS_BLOCK, self.accel))
        return [name for name, on in names if on]

    def copy(self) -> ImuIntrinsics:
        """Deep copy."""
        return ImuIntrinsics(self.T_g.copy(), self.T_a.copy(), self.gyro, self.accel)

    def boxplus(self, dx: np.ndarray) -> None:
        """Add the correction ``dx`` (``dim``,): gyro entries first, each row-major."""
        k = 0
        if self.gyro:
            self.T_g = self.T_g + dx[k : k + 9].reshape(3, 3)
            k += 9
        if self.accel:
            self.T_a = self.T_a + dx[k : k + 9].reshape(3, 3)

    def is_finite(self) -> bool:
        """Whether both matrices are finite."""
        return bool(np.all(np.isfinite(self.T_g)) and np.all(np.isfinite(self.T_a)))


def correct_readings(
    intr: ImuIntrinsics | None, gyro: np.ndarray, accel: np.ndarray, b_g: np.ndarray, b_a: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bias-corrected, and with ``intr`` intrinsic-corrected, readings ``(w (n, 3), a (n, 3))``.

    Args:
        intr: The intrinsics, or None (plain ``w_m - b_g``, ``a_m - b_a``).
        gyro: Raw gyro readings (rad/s), shape (n, 3) or (3,).
        accel: Raw accelerometer readings (m/s^2), same shape.
        b_g: Gyro bias (rad/s), shape (3,).
        b_a: Accelerometer bias (m/s^2), shape (3,).
    """
    w, a = gyro - b_g, accel - b_a
    if intr is None:
        return w, a
    return w @ intr.T_g.T, a @ intr.T_a.T


def input_jacobian(unbiased: np.ndarray) -> np.ndarray:
    """``d (T x) / d vec(T)`` (row-major) at readings ``x`` (m, 3): ``kron(I_3, x^T)``, shape (m, 3, 9)."""
    m = unbiased.shape[0]
    H = np.zeros((m, 3, 9))
    for i in range(3):
        H[:, i, 3 * i : 3 * i + 3] = unbiased
    return H
