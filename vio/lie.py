"""SO(3) and SE(3) utilities with Hamilton quaternions.

Conventions (see DESIGN.md): ``R_WB`` maps B-coordinates to W; quaternions are Hamilton and stored
``quat_wxyz``. The right Jacobian satisfies ``Exp(phi + dphi) ~= Exp(phi) Exp(Jr(phi) dphi)`` and the left
Jacobian ``Exp(phi + dphi) ~= Exp(Jl(phi) dphi) Exp(phi)`` (Forster et al., "On-Manifold Preintegration",
TRO 2017, eqs. 7-9; Barfoot, "State Estimation for Robotics", sec. 7.1).
"""

from __future__ import annotations

import math

import numpy as np

_SMALL_ANGLE_RAD = 1e-8


def skew(v: np.ndarray) -> np.ndarray:
    """Return the 3x3 cross-product matrix ``[v]x`` with ``skew(a) @ b == cross(a, b)``.

    Args:
        v: Vector, shape (3,).
    """
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (..., 3) arrays; a lean ``np.cross`` for the tiny inputs of control loops.

    ``np.cross`` spends ~10 us per call on axis bookkeeping, which dominated the 250 Hz controller.
    """
    if np.ndim(a) == 1 and np.ndim(b) == 1:
        # Two 3-vectors (the control loops): the same products and differences, without the shape work.
        a0, a1, a2 = a
        b0, b1, b2 = b
        return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dtype=float)
    out = np.empty(np.broadcast_shapes(np.shape(a), np.shape(b)))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def vee(m: np.ndarray) -> np.ndarray:
    """Inverse of :func:`skew` for a 3x3 (approximately) skew-symmetric matrix, shape (3,)."""
    return np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) * 0.5


def exp_so3(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: rotation vector (rad), shape (3,) -> rotation matrix, shape (3, 3)."""
    angle = float(np.linalg.norm(phi))
    k = skew(phi)
    if angle < _SMALL_ANGLE_RAD:
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + (np.sin(angle) / angle) * k + ((1.0 - np.cos(angle)) / angle**2) * k @ k


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation matrix, shape (3, 3) -> rotation vector (rad), shape (3,), angle in [0, pi]."""
    sin_axis = vee(0.5 * (R - R.T))  # sin(angle) * axis
    cos_angle = float(np.clip((np.trace(R) - 1.0) * 0.5, -1.0, 1.0))
    angle = float(np.arctan2(np.linalg.norm(sin_axis), cos_angle))
    if angle < 1e-6:
        return sin_axis * (1.0 + angle**2 / 6.0)
    if np.pi - angle < 1e-4:
        # Near pi: read the axis from the symmetric part, (R + R^T)/2 = cos I + (1 - cos) a a^T.
        sym = (0.5 * (R + R.T) - cos_angle * np.eye(3)) / (1.0 - cos_angle)
        col = int(np.argmax(np.diag(sym)))
        axis = sym[:, col] / np.sqrt(max(sym[col, col], 1e-300))
        axis /= np.linalg.norm(axis)
        if np.dot(sin_axis, axis) < 0.0:
            axis = -axis
        return axis * angle
    return sin_axis * (angle / np.sin(angle))


def right_jacobian_so3(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3), ``Jr(phi)``, shape (3, 3) (Forster 2017, eq. 8)."""
    angle = float(np.linalg.norm(phi))
    k = skew(phi)
    if angle < 1e-6:
        return np.eye(3) - 0.5 * k + k @ k / 6.0
    return np.eye(3) - ((1.0 - np.cos(angle)) / angle**2) * k + ((angle - np.sin(angle)) / angle**3) * k @ k


def left_jacobian_so3(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3), ``Jl(phi) = Jr(-phi)``, shape (3, 3)."""
    return right_jacobian_so3(-phi)


def right_jacobian_inv_so3(phi: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian of SO(3), shape (3, 3) (Forster 2017, eq. 9)."""
    angle = float(np.linalg.norm(phi))
    k = skew(phi)
    if angle < 1e-6:
        return np.eye(3) + 0.5 * k + k @ k / 12.0
    return (
        np.eye(3) + 0.5 * k + (1.0 / angle**2 - (1.0 + np.cos(angle)) / (2.0 * angle * np.sin(angle))) * k @ k
    )


def quat_wxyz_to_rotmat(quat_wxyz: np.ndarray) -> np.ndarray:
    """Hamilton unit quaternion (w, x, y, z), shape (4,) -> rotation matrix, shape (3, 3)."""
    return np.array(quat_wxyz_to_rotmat_rows(quat_wxyz)).reshape(3, 3)


def quat_wxyz_to_rotmat_rows(quat_wxyz: np.ndarray) -> list[float]:
    """:func:`quat_wxyz_to_rotmat` as 9 plain floats, row by row (for callers that pack their own arrays).

    The quaternion is normalised by ``np.linalg.norm``'s own formula for a real vector (``sqrt(q . q)``, the
    dot product in numpy, so summed as ``norm`` sums it); the division and the products are the same IEEE
    operations in plain floats as on numpy scalars, several times cheaper.
    """
    q = np.asarray(quat_wxyz, dtype=float).ravel()
    n = math.sqrt(q.dot(q))
    # A zero (or NaN) norm takes numpy's division, which gives NaN or inf where plain floats would raise.
    if n > 0.0:
        w, x, y, z = q.tolist()
        w, x, y, z = w / n, x / n, y / n, z / n
    else:
        w, x, y, z = (q / np.sqrt(q.dot(q))).tolist()
    return [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip


def rotmat_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix, shape (3, 3) -> Hamilton unit quaternion (w, x, y, z) with w >= 0, shape (4,).

    Uses Shepperd's method (branch on the largest diagonal term) for numerical stability.
    """
    trace = np.trace(R)
    if trace > 0.0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0.0 else q


def quat_wxyz_multiply(q1_wxyz: np.ndarray, q2_wxyz: np.ndarray) -> np.ndarray:
    """Hamilton product ``q1 * q2`` of (w, x, y, z) quaternions, shape (4,)."""
    w1, x1, y1, z1 = q1_wxyz
    w2, x2, y2, z2 = q2_wxyz
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def normalize_rotmat(R: np.ndarray) -> np.ndarray:
    """Project a near-rotation matrix back onto SO(3) by SVD, shape (3, 3)."""
    u, _, vt = np.linalg.svd(R)
    out = u @ vt
    if np.linalg.det(out) < 0.0:
        out = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return out


def yaw_from_rotmat(R_WB: np.ndarray) -> float:
    """Heading (rad) of ``R_WB``: the angle of the body x axis projected on the world xy plane."""
    return float(np.arctan2(R_WB[1, 0], R_WB[0, 0]))


def rotz(yaw_rad: float) -> np.ndarray:
    """Rotation about world z by ``yaw_rad``, shape (3, 3)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def se3_matrix(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Homogeneous 4x4 transform from rotation (3, 3) and translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform, shape (4, 4)."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential of twist ``xi = (rho, phi)`` (translation first), shape (6,) -> (4, 4)."""
    rho, phi = xi[:3], xi[3:]
    return se3_matrix(exp_so3(phi), left_jacobian_so3(phi) @ rho)


def log_se3(T: np.ndarray) -> np.ndarray:
    """SE(3) logarithm, (4, 4) -> twist ``(rho, phi)``, shape (6,)."""
    phi = log_so3(T[:3, :3])
    rho = np.linalg.solve(left_jacobian_so3(phi), T[:3, 3])
    return np.concatenate([rho, phi])


def skew_batch(v: np.ndarray) -> np.ndarray:
    """Stacked :func:`skew`: vectors, shape (..., 3) -> cross-product matrices, shape (..., 3, 3)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _rodrigues_batch(phi: np.ndarray, small: float, first, second) -> np.ndarray:
    """``I + c1(angle) [phi]x + c2(angle) [phi]x^2`` for stacked ``phi`` (N, 3); series below ``small``."""
    # Stacked 1x3 @ 3x1 products: the dot kernel of np.linalg.norm, so angles equal the scalar functions'.
    angle = np.sqrt((phi[:, None, :] @ phi[:, :, None])[:, 0, 0])
    k = skew_batch(phi)
    big = angle >= small
    safe = np.where(big, angle, 1.0)
    c1, c2 = first(safe), second(safe)
    c1 = np.where(big, c1, first(None))
    c2 = np.where(big, c2, second(None))
    out = c1[:, None, None] * k + (c2[:, None, None] * k) @ k
    out[:, 0, 0] += 1.0
    out[:, 1, 1] += 1.0
    out[:, 2, 2] += 1.0
    return out


def exp_so3_batch(phi: np.ndarray) -> np.ndarray:
    """Stacked :func:`exp_so3`: rotation vectors (rad), shape (N, 3) -> rotations, shape (N, 3, 3)."""
    return _rodrigues_batch(
        phi,
        _SMALL_ANGLE_RAD,
        lambda a: 1.0 if a is None else np.sin(a) / a,
        lambda a: 0.5 if a is None else (1.0 - np.cos(a)) / a**2,
    )


def right_jacobian_so3_batch(phi: np.ndarray) -> np.ndarray:
    """Stacked :func:`right_jacobian_so3`: shape (N, 3) -> (N, 3, 3) (Forster 2017, eq. 8)."""
    return _rodrigues_batch(
        phi,
        1e-6,
        lambda a: -0.5 if a is None else -(1.0 - np.cos(a)) / a**2,
        lambda a: 1.0 / 6.0 if a is None else (a - np.sin(a)) / a**3,
    )
