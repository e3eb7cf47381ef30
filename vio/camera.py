"""Pinhole cameras with radial-tangential or equidistant distortion, OpenCV conventions.

A point ``p_C = (X, Y, Z)`` in the camera frame (x right, y down, z forward) maps to normalized
``(x, y) = (X/Z, Y/Z)``, is distorted and then mapped by ``K``. Pixel centres sit at integer coordinates.

* :class:`PinholeCamera`: radial-tangential ``k1, k2, p1, p2`` (Kalibr ``pinhole-radtan``, OpenCV's
  plumb-bob model without ``k3``).
* :class:`EquidistantCamera`: Kannala-Brandt ``k1..k4`` (Kalibr ``pinhole-equi``, OpenCV ``cv2.fisheye``)::

      r = |(x, y)|,  theta = atan2(r_C, Z) (= atan(r) for Z > 0),
      theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
      (x_d, y_d) = (theta_d / r) (x, y),   (u, v) = (fx x_d + cx, fy y_d + cy).

Both offer the same interface (``K``, ``has_distortion``, ``distort_normalized``, ``normalized_to_pixels``,
``project``, ``project_jacobian``, ``undistort_points``, ``unproject``, ``in_image``), so estimators and
front ends take either. :func:`camera_from_kalibr` builds the right one from Kalibr / EuRoC yaml fields.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import ClassVar

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

    distortion_model: ClassVar[str] = "radial-tangential"
    """Kalibr name of the distortion model."""

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

    def distortion_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """Jacobian of :meth:`distort_normalized`, shape (N, 2) -> (N, 2, 2): ``d(x_d, y_d) / d(x, y)``."""
        k1, k2, p1, p2 = self.distortion
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        d_radial = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d x = x * d_radial (and y for y)
        jac = np.empty((len(xy), 2, 2))
        jac[:, 0, 0] = radial + x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        jac[:, 0, 1] = x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        jac[:, 1, 0] = x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        jac[:, 1, 1] = radial + y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        return jac

    def project_jacobian(self, p_C: np.ndarray) -> np.ndarray:
        """Jacobian of :meth:`project` with respect to ``p_C``: (N, 3) m -> (N, 2, 3) px/m. Z must be > 0."""
        p_C = np.atleast_2d(np.asarray(p_C, dtype=float))
        inv_z = 1.0 / p_C[:, 2]
        xy = p_C[:, :2] * inv_z[:, None]
        d_xy = np.zeros((len(p_C), 2, 3))
        d_xy[:, 0, 0] = inv_z
        d_xy[:, 1, 1] = inv_z
        d_xy[:, :, 2] = -xy * inv_z[:, None]
        if self.has_distortion:
            d_xy = self.distortion_jacobian(xy) @ d_xy
        return np.array([self.fx, self.fy])[None, :, None] * d_xy

    def unproject(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels, shape (N, 2) -> unit bearing vectors in C, shape (N, 3)."""
        xy = self.undistort_points(uv_px)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def in_image(self, uv_px: np.ndarray, border_px: float = 0.0) -> np.ndarray:
        """Mask of pixels inside the image with a border, shape (N,) bool."""
        return (
            (uv_px[:, 0] >= border_px)
            & (uv_px[:, 0] <= self.width - 1 - border_px)
            & (uv_px[:, 1] >= border_px)
            & (uv_px[:, 1] <= self.height - 1 - border_px)
        )


@dataclass(frozen=True)
class EquidistantCamera:
    """Intrinsics of a pinhole camera with equidistant (Kannala-Brandt) distortion.

    Kalibr ``pinhole-equi`` and OpenCV's ``cv2.fisheye`` model: the image radius grows with the angle
    ``theta`` off the optical axis,
    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` (normalized units), not
    with ``tan(theta)``; so it covers wide lenses, beyond 180 deg with :meth:`unproject` and
    :meth:`project` (normalized ``(x, y)`` only exist for ``theta < 90 deg``).

    Attributes:
        width: Image width (px).
        height: Image height (px).
        fx: Focal length (px).
        fy: Focal length (px).
        cx: Principal point (px).
        cy: Principal point (px).
        distortion: ``(k1, k2, k3, k4)`` equidistant coefficients.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    distortion_model: ClassVar[str] = "equidistant"
    """Kalibr name of the distortion model."""

    @classmethod
    def from_fovy(cls, width: int, height: int, fovy_deg: float) -> EquidistantCamera:
        """Ideal equidistant lens (``k = 0``) whose image height spans ``fovy_deg``.

        ``f = (height / 2) / (fovy / 2)`` (fovy in rad), ``cx = width / 2 - 0.5``, ``cy = height / 2 - 0.5``.
        """
        f = 0.5 * height / (np.deg2rad(fovy_deg) * 0.5)
        return cls(width, height, float(f), float(f), width / 2.0 - 0.5, height / 2.0 - 0.5)

    @property
    def K(self) -> np.ndarray:
        """Camera matrix, shape (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        """Always True: even with ``k = 0`` the equidistant mapping differs from a pinhole's ``tan``."""
        return True

    def _theta_d(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted angle ``theta_d(theta)`` and its derivative, both shaped like ``theta``."""
        k1, k2, k3, k4 = self.distortion
        t2 = theta * theta
        poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
        d_poly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        return theta * poly, d_poly

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Map normalized ``(X/Z, Y/Z)`` to distorted normalized coordinates, shape (N, 2) -> (N, 2)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        r = np.linalg.norm(xy, axis=1)
        theta_d, _ = self._theta_d(np.arctan(r))
        scale = np.where(r > 1e-12, theta_d / np.where(r > 1e-12, r, 1.0), 1.0)
        return xy * scale[:, None]

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Distort and apply K: normalized (N, 2) -> pixels (N, 2)."""
        xy_d = self.distort_normalized(xy)
        return np.stack([self.fx * xy_d[:, 0] + self.cx, self.fy * xy_d[:, 1] + self.cy], axis=1)

    def project(self, p_C: np.ndarray) -> np.ndarray:
        """Project camera-frame points (m), shape (N, 3), to pixels, shape (N, 2).

        Uses ``theta = atan2(|(X, Y)|, Z)``, so points behind the image plane (``Z <= 0``) project too, as a
        lens wider than 180 deg would see them; points on the optical axis need ``Z > 0``.
        """
        p_C = np.atleast_2d(np.asarray(p_C, dtype=float))
        rho = np.linalg.norm(p_C[:, :2], axis=1)
        theta_d, _ = self._theta_d(np.arctan2(rho, p_C[:, 2]))
        off_axis = rho > 1e-12 * np.abs(p_C[:, 2])
        scale = np.where(off_axis, theta_d / np.where(off_axis, rho, 1.0), 1.0 / p_C[:, 2])
        return np.stack(
            [self.fx * scale * p_C[:, 0] + self.cx, self.fy * scale * p_C[:, 1] + self.cy], axis=1
        )

    def project_jacobian(self, p_C: np.ndarray) -> np.ndarray:
        """Jacobian of :meth:`project` with respect to ``p_C``: (N, 3) m -> (N, 2, 3) px/m.

        With ``s = theta_d / rho`` (``rho = |(X, Y)|``, ``n^2 = rho^2 + Z^2``), ``u = fx s X + cx``::

            ds/dX = (X / rho) (theta_d' Z / (n^2 rho) - theta_d / rho^2),   ds/dZ = -theta_d' / n^2

        (the bracket is O(rho), so the product stays accurate near the axis; on it ``s = 1/Z``).
        """
        p_C = np.atleast_2d(np.asarray(p_C, dtype=float))
        X, Y, Z = p_C[:, 0], p_C[:, 1], p_C[:, 2]
        rho = np.linalg.norm(p_C[:, :2], axis=1)
        n2 = rho * rho + Z * Z
        theta_d, d_theta_d = self._theta_d(np.arctan2(rho, Z))
        off_axis = rho > 1e-12 * np.abs(Z)
        rho_safe = np.where(off_axis, rho, 1.0)
        s = np.where(off_axis, theta_d / rho_safe, 1.0 / Z)
        bracket = np.where(off_axis, d_theta_d * Z / (n2 * rho_safe) - theta_d / rho_safe**2, 0.0)
        ds = np.stack([X / rho_safe * bracket, Y / rho_safe * bracket, -d_theta_d / n2], axis=1)
        jac = np.empty((len(p_C), 2, 3))
        for row, (f, c) in enumerate(((self.fx, X), (self.fy, Y))):
            jac[:, row, :] = f * (c[:, None] * ds)
            jac[:, row, row] += f * s
        return jac

    def _undistorted_angles(self, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels (N, 2) -> (theta (N,), unit direction of (x_d, y_d) (N, 2), valid mask (N,)).

        Inverts ``theta_d(theta)`` by Newton's method from ``theta = theta_d`` (as OpenCV's fisheye
        ``undistortPoints``); invalid where it does not converge or the polynomial is not increasing.
        """
        uv_px = np.atleast_2d(np.asarray(uv_px, dtype=float))
        xy_d = np.stack([(uv_px[:, 0] - self.cx) / self.fx, (uv_px[:, 1] - self.cy) / self.fy], axis=1)
        theta_d = np.linalg.norm(xy_d, axis=1)
        theta = theta_d.copy()
        for _ in range(30):
            value, slope = self._theta_d(theta)
            theta = theta - (value - theta_d) / np.where(slope > 1e-12, slope, 1e-12)
        value, slope = self._theta_d(theta)
        valid = (np.abs(value - theta_d) <= 1e-10 * np.maximum(1.0, theta_d)) & (slope > 0.0) & (theta >= 0.0)
        direction = np.where(
            theta_d[:, None] > 0.0, xy_d / np.where(theta_d > 0.0, theta_d, 1.0)[:, None], 0.0
        )
        return theta, direction, valid

    def undistort_points(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels, shape (N, 2) -> undistorted normalized coordinates ``tan(theta) * direction``, (N, 2).

        Rows are NaN where the inversion fails or ``theta >= 90 deg`` (no normalized coordinates there; use
        :meth:`unproject`).
        """
        theta, direction, valid = self._undistorted_angles(uv_px)
        valid &= theta < 0.5 * np.pi
        xy = direction * np.tan(np.where(valid, theta, 0.0))[:, None]
        xy[~valid] = np.nan
        return xy

    def unproject(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels, shape (N, 2) -> unit bearing vectors in C, shape (N, 3) (NaN rows where not invertible)."""
        theta, direction, valid = self._undistorted_angles(uv_px)
        rays = np.concatenate([direction * np.sin(theta)[:, None], np.cos(theta)[:, None]], axis=1)
        rays[~valid] = np.nan
        return rays

    def in_image(self, uv_px: np.ndarray, border_px: float = 0.0) -> np.ndarray:
        """Mask of pixels inside the image with a border, shape (N,) bool."""
        return (
            (uv_px[:, 0] >= border_px)
            & (uv_px[:, 0] <= self.width - 1 - border_px)
            & (uv_px[:, 1] >= border_px)
            & (uv_px[:, 1] <= self.height - 1 - border_px)
        )


CameraModel = PinholeCamera | EquidistantCamera
"""Any camera model of this module (they share one interface)."""


@dataclass(frozen=True)
class CameraCalibration:
    """Camera intrinsics plus camera-IMU extrinsics and clock offset.

    Attributes:
        camera: Intrinsics and distortion (any :data:`CameraModel`).
        R_BC: Rotation camera -> body (IMU), shape (3, 3).
        p_BC: Camera origin in B (m), shape (3,).
        time_offset_s: ``t_imu = t_cam + time_offset_s``.
        rate_hz: Nominal frame rate (Hz).
    """

    camera: CameraModel
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


_DISTORTION_MODELS: dict[str, type[PinholeCamera] | type[EquidistantCamera]] = {
    "radial-tangential": PinholeCamera,
    "radtan": PinholeCamera,
    "plumb_bob": PinholeCamera,
    "equidistant": EquidistantCamera,
    "equi": EquidistantCamera,
    "fisheye": EquidistantCamera,
}
"""Kalibr / ROS / OpenCV names of a distortion model -> camera class."""


def _kalibr_numbers(fields: Mapping, source: str, key: str, count: int) -> list[float]:
    """``fields[key]`` as ``count`` finite floats; errors name the field, its value and ``source``."""
    if key not in fields:
        raise ValueError(f"{source}: missing field {key!r}")
    value = fields[key]
    if isinstance(value, str | bytes):
        raise ValueError(f"{source}: field {key!r} must be a list of {count} numbers, got {value!r}")
    try:
        numbers = [float(v) for v in value]
    except (TypeError, ValueError):
        raise ValueError(
            f"{source}: field {key!r} must be a list of {count} numbers, got {value!r}"
        ) from None
    if len(numbers) != count or not all(np.isfinite(numbers)):
        raise ValueError(f"{source}: field {key!r} must hold {count} finite numbers, got {value!r}")
    return numbers


def camera_from_kalibr(fields: Mapping, source: str = "camera") -> CameraModel:
    """Camera model from Kalibr / EuRoC ``sensor.yaml`` fields.

    Args:
        fields: Mapping with ``camera_model`` (``pinhole``; default ``pinhole``), ``distortion_model``
            (``radial-tangential`` / ``radtan`` / ``plumb_bob`` or ``equidistant`` / ``equi`` / ``fisheye``;
            default ``radial-tangential``), ``intrinsics`` ``[fu, fv, cu, cv]`` (px),
            ``distortion_coefficients`` (4 numbers: ``k1 k2 p1 p2`` or ``k1 k2 k3 k4``) and ``resolution``
            ``[width, height]`` (px).
        source: Where the fields came from (a file path), for error messages.

    Returns:
        A :class:`PinholeCamera` (radial-tangential) or an :class:`EquidistantCamera`.

    Raises:
        ValueError: Unknown ``camera_model`` or ``distortion_model``, a missing field, or a field with the
            wrong count or type; the message names the field and its value.
    """
    camera_model = fields.get("camera_model", "pinhole")
    if camera_model != "pinhole":
        raise ValueError(
            f"{source}: field 'camera_model' must be 'pinhole', got {camera_model!r} "
            "(omni, double-sphere and other projection models are not supported)"
        )
    distortion_model = fields.get("distortion_model", "radial-tangential")
    cls = _DISTORTION_MODELS.get(distortion_model) if isinstance(distortion_model, str) else None
    if cls is None:
        raise ValueError(
            f"{source}: field 'distortion_model' must be one of {sorted(_DISTORTION_MODELS)}, "
            f"got {distortion_model!r}"
        )
    fu, fv, cu, cv = _kalibr_numbers(fields, source, "intrinsics", 4)
    distortion = tuple(_kalibr_numbers(fields, source, "distortion_coefficients", 4))
    width, height = _kalibr_numbers(fields, source, "resolution", 2)
    if width != int(width) or height != int(height) or width <= 0 or height <= 0:
        raise ValueError(
            f"{source}: field 'resolution' must be 2 positive integers, got {fields['resolution']!r}"
        )
    if fu <= 0 or fv <= 0:
        raise ValueError(
            f"{source}: field 'intrinsics' needs positive focal lengths, got {fields['intrinsics']!r}"
        )
    return cls(int(width), int(height), fu, fv, cu, cv, distortion)  # type: ignore[arg-type]


def camera_to_kalibr(camera: CameraModel) -> dict:
    """Kalibr / EuRoC ``sensor.yaml`` fields of a camera model (inverse of :func:`camera_from_kalibr`)."""
    return {
        "camera_model": "pinhole",
        "distortion_model": camera.distortion_model,
        "intrinsics": [camera.fx, camera.fy, camera.cx, camera.cy],
        "distortion_coefficients": [float(c) for c in camera.distortion],
        "resolution": [camera.width, camera.height],
    }
