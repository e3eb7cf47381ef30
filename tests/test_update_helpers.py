"""Tests of vio/update_helpers.py: feature Jacobians vs finite differences, null space, compression, chi2."""

import numpy as np
import pytest
import scipy.stats
from viotb.vio.lie import exp_so3, log_so3
from viotb.vio.update_helpers import (
    Chi2Table,
    clone_unobservable_basis,
    feature_jacobian,
    measurement_compress,
    nullspace_project,
    observability_constrain,
    observability_projector,
)


def _setup(rng):
    R_WB = exp_so3(rng.normal(size=3))
    p_WB = rng.normal(size=3)
    R_BC = exp_so3(rng.normal(0, 0.3, 3))
    p_BC = rng.normal(0, 0.1, 3)
    # A feature 4 m in front of the camera.
    p_WC = p_WB + R_WB @ p_BC
    p_f = p_WC + R_WB @ R_BC @ np.array([0.3, -0.2, 4.0])
    return R_WB, p_WB, R_BC, p_BC, p_f


def test_feature_jacobian_matches_central_differences():
    rng = np.random.default_rng(0)
    R_WB, p_WB, R_BC, p_BC, p_f = _setup(rng)
    jac = feature_jacobian(R_WB, p_WB, R_BC, p_BC, p_f)
    eps = 1e-6

    def z(dpose=None, dext=None, df=None):
        dpose = np.zeros(6) if dpose is None else dpose
        dext = np.zeros(6) if dext is None else dext
        df = np.zeros(3) if df is None else df
        return feature_jacobian(
            R_WB @ exp_so3(dpose[:3]), p_WB + dpose[3:], R_BC @ exp_so3(dext[:3]), p_BC + dext[3:], p_f + df
        ).z_norm

    for name, H, size, key in (
        ("pose", jac.H_pose, 6, "dpose"),
        ("ext", jac.H_extrinsic, 6, "dext"),
        ("feature", jac.H_feature, 3, "df"),
    ):
        num = np.zeros((2, size))
        for i in range(size):
            d = np.zeros(size)
            d[i] = eps
            num[:, i] = (z(**{key: d}) - z(**{key: -d})) / (2 * eps)
        np.testing.assert_allclose(H, num, atol=1e-8, err_msg=name)


def test_feature_jacobian_broadcasts_over_features_and_clones():
    rng = np.random.default_rng(1)
    R_WB = np.stack([exp_so3(rng.normal(0, 0.1, 3)) for _ in range(4)])
    p_WB = rng.normal(0, 0.2, (4, 3))
    p_f = rng.normal(0, 1, (5, 3)) + np.array([0, 0, 6.0])
    batch = feature_jacobian(R_WB[None], p_WB[None], np.eye(3), np.zeros(3), p_f[:, None])
    assert batch.H_pose.shape == (5, 4, 2, 6)
    one = feature_jacobian(R_WB[2], p_WB[2], np.eye(3), np.zeros(3), p_f[3])
    np.testing.assert_allclose(batch.H_pose[3, 2], one.H_pose, atol=1e-15)
    np.testing.assert_allclose(batch.z_norm[3, 2], one.z_norm, atol=1e-15)


def test_nullspace_projection_annihilates_the_feature_jacobian():
    rng = np.random.default_rng(0)
    m, n = 14, 30
    H_f = rng.normal(size=(m, 3))
    H_x = rng.normal(size=(m, n))
    r = rng.normal(size=m)
    H_o, r_o = nullspace_project(H_x, H_f, r)
    assert H_o.shape == (m - 3, n) and r_o.shape == (m - 3,)
    H_ff, _ = nullspace_project(H_f, H_f, r)
    assert np.linalg.norm(H_ff) < 1e-10
    # Independent check: the projected system carries the same information as the orthogonal projector.
    Pn = np.eye(m) - H_f @ np.linalg.solve(H_f.T @ H_f, H_f.T)
    np.testing.assert_allclose(H_o.T @ H_o, H_x.T @ Pn @ H_x, atol=1e-10)
    np.testing.assert_allclose(H_o.T @ r_o, H_x.T @ Pn @ r, atol=1e-10)
    # The lesson's 1-D example: the projected residual does not depend on the landmark guess.
    with pytest.raises(ValueError, match="needs more than"):
        nullspace_project(H_x[:3], H_f[:3], r[:3])


def test_measurement_compress_preserves_information():
    rng = np.random.default_rng(0)
    H = rng.normal(size=(200, 40))
    r = rng.normal(size=200)
    Hc, rc = measurement_compress(H, r)
    assert Hc.shape == (40, 40) and rc.shape == (40,)
    np.testing.assert_allclose(Hc.T @ Hc, H.T @ H, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(Hc.T @ rc, H.T @ r, rtol=1e-10, atol=1e-9)
    small_H, small_r = measurement_compress(H[:10], r[:10])
    assert small_H.shape == (10, 40)


def test_measurement_compress_of_constrained_rows_matches_qr_of_the_formed_product():
    """``right=Pi`` compresses ``H Pi`` without forming it; the QR of the formed ``[H Pi | r]`` agrees."""
    rng = np.random.default_rng(1)
    U = rng.normal(size=(30, 4))
    Pi = observability_projector(U)
    H = rng.normal(size=(300, 30)) * rng.uniform(0.01, 100.0, size=30)  # badly scaled columns
    r = rng.normal(size=300)
    Hc, rc = measurement_compress(H, r, Pi)
    assert Hc.shape == (26, 30)  # the four directions of U carry no information and are dropped
    np.testing.assert_allclose(Hc @ U, 0.0, atol=1e-9 * np.abs(Hc).max())
    T = np.linalg.qr(np.column_stack([H @ Pi, r]), mode="r")  # independent: Householder on the product
    scale = np.abs(T).max() ** 2
    np.testing.assert_allclose(Hc.T @ Hc, T[:30, :30].T @ T[:30, :30], atol=1e-10 * scale)
    np.testing.assert_allclose(Hc.T @ rc, T[:30, :30].T @ T[:30, 30], atol=1e-10 * np.abs(T).max())
    # Rows without information compress to an empty system (the update then skips).
    H0c, r0c = measurement_compress(np.zeros((50, 30)), np.zeros(50))
    assert H0c.shape == (0, 30) and r0c.shape == (0,)
    # Pi is the symmetric, idempotent projector of observability_constrain.
    np.testing.assert_allclose(Pi, Pi.T, atol=0.0)
    np.testing.assert_allclose(Pi @ Pi, Pi, atol=1e-12)
    np.testing.assert_allclose(H @ Pi, observability_constrain(H, U), atol=1e-9)


def test_chi2_table_matches_scipy():
    table = Chi2Table(50)
    dof = np.array([1, 3, 17, 50])
    np.testing.assert_allclose(table(dof), scipy.stats.chi2.ppf(0.95, dof), rtol=1e-12)
    assert table(1) == pytest.approx(3.841458820694124, rel=1e-12)
    with pytest.raises(ValueError, match="outside"):
        table(51)


def test_measurement_jacobian_annihilates_the_unobservable_directions():
    """Global translation and yaw move clone and feature together: H_pose N_clone + H_f N_f = 0."""
    rng = np.random.default_rng(2)
    R_WB, p_WB, R_BC, p_BC, p_f = _setup(rng)
    jac = feature_jacobian(R_WB, p_WB, R_BC, p_BC, p_f)
    ez = np.array([0.0, 0.0, 1.0])
    skew_ez = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    N_clone = np.zeros((6, 4))
    N_clone[3:6, 0:3] = np.eye(3)
    N_clone[0:3, 3] = R_WB.T @ ez
    N_clone[3:6, 3] = skew_ez @ p_WB
    N_f = np.hstack([np.eye(3), (skew_ez @ p_f)[:, None]])
    np.testing.assert_allclose(jac.H_pose @ N_clone + jac.H_feature @ N_f, 0.0, atol=1e-12)


def test_clone_unobservable_basis_matches_a_global_yaw_and_shift_of_the_clones():
    """Finite difference: rotate every clone about world z by alpha and shift it; read the error state."""
    rng = np.random.default_rng(3)
    K, dim, offsets = 4, 15 + 6 * 4, 15 + 6 * np.arange(4)
    R = np.stack([exp_so3(rng.normal(size=3)) for _ in range(K)])
    p = rng.normal(0.0, 3.0, (K, 3))
    U = clone_unobservable_basis(R, p, offsets, dim)
    alpha, shift = 1e-6, np.array([1e-6, -2e-6, 3e-6])
    Rz = exp_so3(np.array([0.0, 0.0, alpha]))
    dx = np.zeros(dim)
    for k, o in enumerate(offsets):
        dx[o : o + 3] = log_so3(R[k].T @ Rz @ R[k])  # R' = R Exp(dtheta)
        dx[o + 3 : o + 6] = Rz @ p[k] + shift - p[k]
    # Values are ~1e-6; the neglected second-order term is alpha^2 |p| ~ 1e-11.
    np.testing.assert_allclose(U @ np.r_[shift, alpha], dx, rtol=0.0, atol=1e-10)
    assert np.all(U[:15] == 0.0)


def test_observability_constrain_is_the_smallest_change_that_annihilates_the_directions():
    rng = np.random.default_rng(4)
    U = rng.normal(size=(20, 4))
    H = rng.normal(size=(3, 7, 20))
    H_star = observability_constrain(H, U)
    np.testing.assert_allclose(H_star @ U, 0.0, atol=1e-12)
    # Independent closed form: remove each row's component in span(U) through an orthonormal basis (SVD).
    Q = np.linalg.svd(U, full_matrices=False)[0]
    np.testing.assert_allclose(H_star, H - H @ Q @ Q.T, atol=1e-12)
    # Rows that already ignore the directions are unchanged.
    H0 = H_star[0]
    np.testing.assert_allclose(observability_constrain(H0, U), H0, atol=1e-12)


def test_clone_unobservable_basis_equals_the_per_clone_blocks():
    """Each clone block holds ``[R_k^T e_z; e_z x p_k]`` and the identity translation block; the rest is 0."""
    rng = np.random.default_rng(5)
    K, dim = 7, 21 + 6 * 7
    R_WB = np.stack([exp_so3(rng.normal(size=3)) for _ in range(K)])
    p_WB = rng.normal(size=(K, 3))
    offsets = 21 + 6 * rng.permutation(K)
    ref = np.zeros((dim, 4))
    for k, o in enumerate(offsets):
        ref[o + 3 : o + 6, 0:3] = np.eye(3)
        ref[o : o + 3, 3] = R_WB[k].T @ np.array([0.0, 0.0, 1.0])
        ref[o + 3 : o + 6, 3] = np.cross([0.0, 0.0, 1.0], p_WB[k])
    np.testing.assert_allclose(clone_unobservable_basis(R_WB, p_WB, offsets, dim), ref, rtol=0, atol=1e-15)
