"""Pinhole camera with radial-tangential (plumb-bob) distortion, OpenCV conventions.

A point ``p_C = (X, Y, Z)`` in the camera frame (x right, y down, z forward) maps to normalized
``(x, y) = (X/Z, Y/Z)``, is distorted with ``k1, k2, p1, p2`` (OpenCV's model) and then mapped by ``K``.
Pixel centres sit at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from viotb.vio.lie import exp_so3


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of a pinhole camera.

    Attributes:
        width: Image width (px).
        height: Image height (px).
        fx: Focal length (px).
        fy: Focal length (px).
        cx: Principal point (px).
        cy: Principal point (px).
        distortion: ``(k1, k2, p1, p2)`` radial-tangential coefficients.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    @classmethod
    def from_fovy(cls, width: int, height: int, fovy_deg: float) -> PinholeCamera:
        """Intrinsics of a MuJoCo camera with vertical field of view ``fovy_deg`` (square pixels).

        ``fx = fy = (height / 2) / tan(fovy / 2)``, ``cx = width / 2 - 0.5``, ``cy = height / 2 - 0.5``.
        """
        f = 0.5 * height / np.tan(np.deg2rad(fovy_deg) * 0.5)
        return cls(width, height, float(f), float(f), width / 2.0 - 0.5, height / 2.0 - 0.5)

    @property
    def K(self) -> np.ndarray:
        """Camera matrix, shape (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return any(c != 0.0 for c in self.distortion)

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply radial-tangential distortion to normalized coordinates, shape (N, 2) -> (N, 2)."""
        k1, k2, p1, p2 = self.distortion
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Distort and apply K: normalized (N, 2) -> pixels (N, 2)."""
        xy_d = self.distort_normalized(xy) if self.has_distortion else xy
        return np.stack([self.fx * xy_d[:, 0] + self.cx, self.fy * xy_d[:, 1] + self.cy], axis=1)

    def project(self, p_C: np.ndarray) -> np.ndarray:
        """Project camera-frame points (m), shape (N, 3), to pixels, shape (N, 2). Z must be > 0."""
        p_C = np.atleast_2d(p_C)
        return self.normalized_to_pixels(p_C[:, :2] / p_C[:, 2:3])

    def undistort_points(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels, shape (N, 2) -> undistorted normalized coordinates, shape (N, 2).

        Inverts the distortion by fixed-point iteration (as OpenCV's ``undistortPoints``).
        """
        uv_px = np.atleast_2d(np.asarray(uv_px, dtype=float))
        xy_d = np.stack([(uv_px[:, 0] - self.cx) / self.fx, (uv_px[:, 1] - self.cy) / self.fy], axis=1)
        if not self.has_distortion:
            return xy_d
        k1, k2, p1, p2 = self.distortion
        xy = xy_d.copy()
        for _ in range(20):
            x, y = xy[:, 0], xy[:, 1]
            r2 = x * x + y * y
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            xy = np.stack([(xy_d[:, 0] - dx) / radial, (xy_d[:, 1] - dy) / radial], axis=1)
        return xy

    def in_image(self, uv_px: np.ndarray, border_px: float = 0.0) -> np.ndarray:
        """Mask of pixels inside the image with a border, shape (N,) bool."""
        return (
            (uv_px[:, 0] >= border_px)
            & (uv_px[:, 0] <= self.width - 1 - border_px)
            & (uv_px[:, 1] >= border_px)
            & (uv_px[:, 1] <= self.height - 1 - border_px)
        )


@dataclass(frozen=True)
class CameraCalibration:
    """Camera intrinsics plus camera-IMU extrinsics and clock offset.

    Attributes:
        camera: Intrinsics.
        R_BC: Rotation camera -> body (IMU), shape (3, 3).
        p_BC: Camera origin in B (m), shape (3,).
        time_offset_s: ``t_imu = t_cam + time_offset_s``.
        rate_hz: Nominal frame rate (Hz).
    """

    camera: PinholeCamera
    R_BC: np.ndarray
    p_BC: np.ndarray
    time_offset_s: float = 0.0
    rate_hz: float = 20.0


def with_extrinsic_rotation_error(calib: CameraCalibration, error_rad: float) -> CameraCalibration:
    """``calib`` with ``R_BC`` rotated by ``error_rad`` about the camera axis ``(1, 0, 1) / sqrt(2)``.

    The miscalibrated extrinsic of the failure scenarios: a rotation about the optical axis and the image x
    axis at once, so that it shifts and rotates the image.
    """
    axis = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    return replace(calib, R_BC=calib.R_BC @ exp_so3(axis * float(error_rad)))
