"""Tests of vio/lie.py against scipy Rotation, finite differences and closed forms."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.vio.lie import (
    cross,
    exp_se3,
    exp_so3,
    left_jacobian_so3,
    log_se3,
    log_so3,
    normalize_rotmat,
    quat_wxyz_multiply,
    quat_wxyz_to_rotmat,
    right_jacobian_inv_so3,
    right_jacobian_so3,
    rotmat_to_quat_wxyz,
    rotz,
    se3_inverse,
    se3_matrix,
    skew,
    vee,
    yaw_from_rotmat,
)


def _random_rotvecs(rng: np.random.Generator, n: int, max_angle_rad: float = np.pi - 1e-3) -> np.ndarray:
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(0.0, max_angle_rad, size=(n, 1))


def test_skew_vee_cross_product():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 3))
    np.testing.assert_allclose(skew(a) @ b, np.cross(a, b), atol=1e-15)
    np.testing.assert_allclose(vee(skew(a)), a, atol=1e-15)
    # The lean row-wise cross agrees with numpy, also broadcast over leading axes.
    np.testing.assert_allclose(cross(a, b), np.cross(a, b), atol=1e-15)
    A, B = rng.normal(size=(2, 4, 5, 3))
    np.testing.assert_allclose(cross(A, B), np.cross(A, B), atol=1e-14)
    np.testing.assert_allclose(cross(A, b), np.cross(A, b), atol=1e-14)


def test_exp_so3_matches_scipy():
    rng = np.random.default_rng(0)
    for phi in _random_rotvecs(rng, 50):
        np.testing.assert_allclose(exp_so3(phi), Rotation.from_rotvec(phi).as_matrix(), atol=1e-14)
    tiny = np.array([1e-9, -2e-9, 3e-10])
    np.testing.assert_allclose(exp_so3(tiny), Rotation.from_rotvec(tiny).as_matrix(), atol=1e-16)


def test_log_so3_matches_scipy_and_round_trips():
    rng = np.random.default_rng(0)
    for phi in _random_rotvecs(rng, 50):
        R = Rotation.from_rotvec(phi).as_matrix()
        np.testing.assert_allclose(log_so3(R), Rotation.from_matrix(R).as_rotvec(), atol=1e-12)
        np.testing.assert_allclose(log_so3(exp_so3(phi)), phi, atol=1e-12)
    for phi in (np.zeros(3), np.array([1e-9, 0.0, -1e-9]), np.array([1e-5, 2e-5, -3e-5])):
        np.testing.assert_allclose(log_so3(exp_so3(phi)), phi, atol=1e-15)


@pytest.mark.parametrize("gap_rad", [0.0, 1e-9, 1e-6, 5e-5, 2e-4, 1e-2])
def test_log_so3_near_pi(gap_rad):
    rng = np.random.default_rng(0)
    for _ in range(10):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        phi = axis * (np.pi - gap_rad)
        R = Rotation.from_rotvec(phi).as_matrix()
        out = log_so3(R)
        assert abs(np.linalg.norm(out) - (np.pi - gap_rad)) < 1e-9
        # At exactly pi the sign of the axis is ambiguous: compare the rotations instead.
        np.testing.assert_allclose(exp_so3(out), R, atol=1e-9)
        if gap_rad > 0.0:
            np.testing.assert_allclose(out, phi, atol=1e-8)


def test_quaternion_conversions_match_scipy():
    rng = np.random.default_rng(0)
    for quat_xyzw in Rotation.random(50, random_state=0).as_quat():
        quat_wxyz = np.roll(quat_xyzw, 1)
        R_ref = Rotation.from_quat(quat_xyzw).as_matrix()
        np.testing.assert_allclose(quat_wxyz_to_rotmat(quat_wxyz), R_ref, atol=1e-14)
        np.testing.assert_allclose(quat_wxyz_to_rotmat(-quat_wxyz), R_ref, atol=1e-14)  # q ~ -q
        q_back = rotmat_to_quat_wxyz(R_ref)
        assert q_back[0] >= 0.0
        # Same rotation up to sign.
        assert min(np.abs(q_back - quat_wxyz).max(), np.abs(q_back + quat_wxyz).max()) < 1e-12
    # Branches of Shepperd's method: 180 deg about each axis and a near-zero trace.
    half_turns = [np.array([np.pi, 0, 0]), np.array([0, np.pi, 0]), np.array([0, 0, np.pi])]
    for phi in [*half_turns, rng.normal(size=3)]:
        R = Rotation.from_rotvec(phi).as_matrix()
        np.testing.assert_allclose(quat_wxyz_to_rotmat(rotmat_to_quat_wxyz(R)), R, atol=1e-14)


def test_quaternion_product_matches_rotation_product():
    r1, r2 = Rotation.random(2, random_state=1)
    q1 = np.roll(r1.as_quat(), 1)
    q2 = np.roll(r2.as_quat(), 1)
    np.testing.assert_allclose(
        quat_wxyz_to_rotmat(quat_wxyz_multiply(q1, q2)), (r1 * r2).as_matrix(), atol=1e-14
    )


def test_right_jacobian_by_finite_differences():
    """Exp(phi + d) ~= Exp(phi) Exp(Jr(phi) d) to second order (Forster 2017, eq. 7)."""
    rng = np.random.default_rng(0)
    eps = 1e-6
    for phi in np.vstack([_random_rotvecs(rng, 20, 3.0), [[1e-8, 0.0, 0.0]]]):
        jr_fd = np.zeros((3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            jr_fd[:, k] = (
                log_so3(exp_so3(phi).T @ exp_so3(phi + d)) - log_so3(exp_so3(phi).T @ exp_so3(phi - d))
            ) / (2 * eps)
        np.testing.assert_allclose(right_jacobian_so3(phi), jr_fd, atol=1e-8)
        jr_inv_jr = right_jacobian_inv_so3(phi) @ right_jacobian_so3(phi)
        np.testing.assert_allclose(jr_inv_jr, np.eye(3), atol=1e-12)


def test_left_jacobian_by_finite_differences():
    rng = np.random.default_rng(0)
    eps = 1e-6
    for phi in _random_rotvecs(rng, 20, 3.0):
        jl_fd = np.zeros((3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            jl_fd[:, k] = (
                log_so3(exp_so3(phi + d) @ exp_so3(phi).T) - log_so3(exp_so3(phi - d) @ exp_so3(phi).T)
            ) / (2 * eps)
        np.testing.assert_allclose(left_jacobian_so3(phi), jl_fd, atol=1e-8)


def test_jacobian_small_angle_branch_continuous():
    phi = np.array([3e-7, -2e-7, 4e-7])
    k = skew(phi)
    np.testing.assert_allclose(right_jacobian_so3(phi), np.eye(3) - 0.5 * k, atol=1e-13)
    np.testing.assert_allclose(right_jacobian_inv_so3(phi), np.eye(3) + 0.5 * k, atol=1e-13)


def test_se3_exp_log_round_trip_and_inverse():
    rng = np.random.default_rng(0)
    for phi in _random_rotvecs(rng, 20, 3.0):
        xi = np.concatenate([rng.normal(size=3), phi])
        T = exp_se3(xi)
        np.testing.assert_allclose(T[:3, :3], Rotation.from_rotvec(phi).as_matrix(), atol=1e-13)
        np.testing.assert_allclose(log_se3(T), xi, atol=1e-10)
        np.testing.assert_allclose(se3_inverse(T) @ T, np.eye(4), atol=1e-13)
    # Pure translation twist.
    T_trans = exp_se3(np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(T_trans, se3_matrix(np.eye(3), [1, 2, 3]), atol=1e-15)


def test_exp_se3_closed_form_screw():
    """A screw about z: rotation theta with axial translation h and zero offset is (Rz(theta), (0, 0, h))."""
    theta, h = 1.2, 0.7
    T = exp_se3(np.array([0.0, 0.0, h, 0.0, 0.0, theta]))
    np.testing.assert_allclose(T[:3, :3], rotz(theta), atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, h], atol=1e-15)


def test_yaw_normalize_helpers():
    R = Rotation.from_euler("ZYX", [0.8, 0.2, -0.1]).as_matrix()
    assert abs(yaw_from_rotmat(R) - 0.8) < 1e-12
    rng = np.random.default_rng(0)
    noisy = R + 1e-4 * rng.normal(size=(3, 3))
    Rn = normalize_rotmat(noisy)
    np.testing.assert_allclose(Rn.T @ Rn, np.eye(3), atol=1e-14)
    assert abs(np.linalg.det(Rn) - 1.0) < 1e-14
    assert np.abs(Rn - R).max() < 1e-3
