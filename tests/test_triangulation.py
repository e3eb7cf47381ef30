"""Tests of vio/triangulation.py: recovery of known points from noisy views and the rejection checks."""

import numpy as np
import scipy.stats
from viotb.vio.lie import exp_so3
from viotb.vio.triangulation import TriangulationParams, triangulate
from viotb.vio.update_helpers import feature_jacobian


def _views(rng, K=6):
    """Cameras on a 1 m arc looking along +z towards points ~5 m away."""
    R_WC = np.stack([exp_so3(rng.normal(0, 0.05, 3)) for _ in range(K)])
    p_WC = np.stack([np.array([x, 0.1 * np.sin(3 * x), 0.0]) for x in np.linspace(-0.5, 0.5, K)])
    return R_WC, p_WC


def _observe(R_WC, p_WC, pts, rng, sigma):
    p_C = np.einsum("kji,fkj->fki", R_WC, pts[:, None, :] - p_WC[None])
    return p_C[..., :2] / p_C[..., 2:3] + rng.normal(0, sigma, p_C[..., :2].shape)


def test_recovers_known_points_from_noisy_views():
    rng = np.random.default_rng(0)
    R_WC, p_WC = _views(rng)
    pts = rng.uniform([-2, -2, 4], [2, 2, 6], (50, 3))
    f = 400.0
    xy = _observe(R_WC, p_WC, pts, rng, 0.5 / f)
    mask = np.ones((50, 6), dtype=bool)
    mask[::3, :2] = False  # some features seen in only part of the window
    res = triangulate(R_WC, p_WC, xy, mask, focal_px=f)
    assert res.valid.all()
    # Consistency with the Cramer-Rao bound: the sum of e^T (sum_k H_k^T H_k / sigma^2) e over 50 points is
    # chi-square with 150 dof (H_k from the finite-difference-tested feature Jacobian).
    H = feature_jacobian(R_WC[None], p_WC[None], np.eye(3), np.zeros(3), pts[:, None]).H_feature
    info = np.einsum("fk,fkia,fkib->fab", mask.astype(float), H, H) / (0.5 / f) ** 2
    e = res.p_W - pts
    nees = float(np.einsum("fa,fab,fb->", e, info, e))
    lo, hi = scipy.stats.chi2.ppf([0.005, 0.995], 150)
    assert lo < nees < hi
    assert np.linalg.norm(e, axis=1).max() < 0.3
    assert np.all(res.rms_error_px < 1.5)
    # Noise-free views give the exact point (Gauss-Newton converges).
    exact = triangulate(R_WC, p_WC, _observe(R_WC, p_WC, pts, rng, 0.0), mask, focal_px=f)
    np.testing.assert_allclose(exact.p_W, pts, atol=1e-7)


def test_rejects_degenerate_geometry_and_outliers():
    rng = np.random.default_rng(1)
    R_WC, p_WC = _views(rng)
    pts = np.array([[0.5, 0.2, 5.0], [0.0, 0.0, -5.0], [0.3, 0.1, 5.0], [0.1, 0.1, 400.0]])
    xy = _observe(R_WC, p_WC, pts, rng, 0.0)
    xy[2, 3] += 0.05  # a 20 px outlier
    mask = np.ones((4, 6), dtype=bool)
    res = triangulate(R_WC, p_WC, xy, mask, TriangulationParams(), focal_px=400.0)
    assert res.valid.tolist() == [True, False, False, False]
    # Zero baseline: every view at the same place.
    same = triangulate(np.repeat(R_WC[:1], 6, 0), np.zeros((6, 3)), np.repeat(xy[:1, :1], 6, 1), mask[:1])
    assert not same.valid[0]
    single = triangulate(R_WC, p_WC, xy[:1], np.eye(6, dtype=bool)[:1])
    assert not single.valid[0]


def _triangulate_one(R_WC, p_WC, xy, m, p, focal_px):
    """Per-feature reference: midpoint start, LM on ``h = R_CA ([a, b, 1] - rho p)`` (J = dz/dh dh/dx)."""
    idx = np.flatnonzero(m)
    R_WA, p_WA = R_WC[idx[0]], p_WC[idx[0]]
    R_AC = [R_WA.T @ R_WC[k] for k in idx]
    p_AC = [R_WA.T @ (p_WC[k] - p_WA) for k in idx]
    A, rhs = np.zeros((3, 3)), np.zeros(3)
    for R, t, z in zip(R_AC, p_AC, xy[idx], strict=True):
        b = R @ np.append(z, 1.0)
        b /= np.linalg.norm(b)
        A += np.eye(3) - np.outer(b, b)
        rhs += (np.eye(3) - np.outer(b, b)) @ t
    p_A = np.linalg.solve(A, rhs)
    x = np.array([p_A[0] / p_A[2], p_A[1] / p_A[2], 1.0 / p_A[2]])

    def residual_and_jacobian(x_):
        e, J = [], []
        for R, t, z in zip(R_AC, p_AC, xy[idx], strict=True):
            h = R.T @ (np.array([x_[0], x_[1], 1.0]) - x_[2] * t)
            e.append(h[:2] / h[2] - z)
            dz_dh = np.array([[1.0, 0.0, -h[0] / h[2]], [0.0, 1.0, -h[1] / h[2]]]) / h[2]
            J.append(dz_dh @ np.column_stack([R.T[:, 0], R.T[:, 1], -R.T @ t]))
        return np.concatenate(e), np.vstack(J)

    e, _ = residual_and_jacobian(x)
    cost, lam = e @ e, p.initial_damping
    for _ in range(p.max_iterations):
        e, J = residual_and_jacobian(x)
        JtJ = J.T @ J
        x_new = x - np.linalg.solve(JtJ + lam * (np.diag(np.diag(JtJ)) + 1e-12 * np.eye(3)), J.T @ e)
        e_new, _ = residual_and_jacobian(x_new)
        if e_new @ e_new < cost:
            x, cost, lam = x_new, e_new @ e_new, lam * 0.1
        else:
            lam *= 10.0
    p_W = R_WA @ (np.array([x[0], x[1], 1.0]) / x[2]) + p_WA
    return p_W, np.sqrt(cost / len(idx)) * focal_px


def test_batched_triangulation_equals_the_per_feature_reference():
    """The batched LM (``h`` affine in the inverse-depth parameters) is the per-feature one to round-off."""
    rng = np.random.default_rng(7)
    R_WC, p_WC = _views(rng, K=9)
    pts = rng.uniform([-2, -1.5, 3.0], [2, 1.5, 8.0], size=(40, 3))
    xy = _observe(R_WC, p_WC, pts, rng, sigma=3.0 / 120.0)
    mask = rng.random((40, 9)) < 0.7
    mask[:, :2] = True  # at least two views each
    p = TriangulationParams(step_tolerance=0.0)  # every iteration, as the reference
    res = triangulate(R_WC, p_WC, np.where(mask[..., None], xy, np.nan), mask, p, 120.0)
    for f in range(40):
        p_ref, rms_ref = _triangulate_one(R_WC, p_WC, xy[f], mask[f], p, 120.0)
        np.testing.assert_allclose(res.p_W[f], p_ref, rtol=1e-9, atol=1e-9 * np.linalg.norm(p_ref))
        np.testing.assert_allclose(res.rms_error_px[f], rms_ref, rtol=1e-9, atol=1e-12)
    # The default stops once every step is below 1e-6 of the parameters: the points move by far less.
    early = triangulate(R_WC, p_WC, np.where(mask[..., None], xy, np.nan), mask, TriangulationParams(), 120.0)
    np.testing.assert_array_equal(early.valid, res.valid)
    np.testing.assert_allclose(early.p_W, res.p_W, rtol=1e-6)
    np.testing.assert_allclose(early.rms_error_px, res.rms_error_px, rtol=1e-6)
