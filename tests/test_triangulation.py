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
