"""Homography alignment of the KLT anchors (vio/klt_anchor.py) on a foreshortened plane.

An affine warp cannot follow the perspective change of a patch on a plane seen at a grazing angle: its
least-squares fit moves the quadratic part of the warp into the translation, one sign for every track on
the plane (README "KLT track bias on foreshortened planes"). The scene here is a textured floor seen by a
camera 1.5 m above it, pitched 25 deg down, flying forward: each image is the floor's texture looked up
through the ray-plane intersection of every pixel, so a track's true position is the exact projection of
the floor point under its first pixel.
"""

from __future__ import annotations

import cv2
import numpy as np
from viotb.vio.klt_anchor import TemplateAnchors

_F, _C = 120.0, np.array([159.5, 119.5])
_TEX_M = 0.005  # floor texture: metres per texel


def _pose(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera k: 1.5 m up, pitched 25 deg down, 7.5 cm further along world x each frame (R_WC, p_WC)."""
    pitch = np.radians(25.0)
    z = np.array([np.cos(pitch), 0.0, -np.sin(pitch)])  # optical axis
    y = np.array([-np.sin(pitch), 0.0, -np.cos(pitch)])  # image down
    return np.column_stack([np.cross(y, z), y, z]), np.array([0.075 * k, 0.0, 1.5])


def _render(tex: np.ndarray, R_WC: np.ndarray, p_WC: np.ndarray) -> np.ndarray:
    u, v = np.meshgrid(np.arange(320.0), np.arange(240.0))
    rays = np.stack([(u - _C[0]) / _F, (v - _C[1]) / _F, np.ones_like(u)], axis=-1) @ R_WC.T
    t = -p_WC[2] / np.minimum(rays[..., 2], -1e-6)
    mx = ((p_WC[0] + t * rays[..., 0]) / _TEX_M).astype(np.float32)
    my = ((p_WC[1] + t * rays[..., 1]) / _TEX_M).astype(np.float32)
    return cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def _floor_point(R_WC: np.ndarray, p_WC: np.ndarray, uv: np.ndarray) -> np.ndarray:
    rays = np.column_stack([(uv - _C) / _F, np.ones(len(uv))]) @ R_WC.T
    return p_WC + (-p_WC[2] / rays[:, 2])[:, None] * rays


def _project(R_WC: np.ndarray, p_WC: np.ndarray, X_W: np.ndarray) -> np.ndarray:
    p_C = (X_W - p_WC) @ R_WC
    return p_C[:, :2] / p_C[:, 2:] * _F + _C


def _floor_errors(projective_after_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Anchored track errors (px) against the exact projection, and the image distance travelled (px).

    Each frame's refinement starts from the truth plus the track's last error (as from frame-to-frame
    KLT); a rejected track ends.
    """
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0.0, 255.0, (512, 512)).astype(np.float32), (0, 0), 2.0)
    tex = np.clip((tex - tex.mean()) * 4.0 + 128.0, 0.0, 255.0)
    R0, p0 = _pose(0)
    img0 = _render(tex, R0, p0)
    uv0 = np.column_stack([rng.uniform(40.0, 280.0, 80), rng.uniform(135.0, 215.0, 80)])
    X_W = _floor_point(R0, p0, uv0)
    anchors = TemplateAnchors(5, projective_after_px=projective_after_px)
    ids = np.arange(len(uv0))
    anchors.take(img0, ids, uv0)
    alive = np.isin(ids, anchors.ids)
    err = np.zeros_like(uv0)
    errors, moved = [], []
    for k in range(1, 14):
        R, p = _pose(k)
        truth = _project(R, p, X_W)
        alive &= np.all((truth > 12.0) & (truth < [308.0, 228.0]), axis=1)
        a = np.flatnonzero(alive)
        refined, ok = anchors.refine(_render(tex, R, p), ids[a], truth[a] + err[a])
        alive[a[~ok]] = False
        err[a] = refined - truth[a]
        errors.append(err[a[ok]])
        moved.append(np.linalg.norm(truth[a[ok]] - uv0[a[ok]], axis=1))
    return np.vstack(errors), np.concatenate(moved)


def test_homography_anchor_removes_the_one_signed_drift_on_a_floor():
    e_aff, d_aff = _floor_errors(float("inf"))
    e_hom, d_hom = _floor_errors(10.0)
    far_aff, far_hom = e_aff[d_aff > 30.0], e_hom[d_hom > 30.0]
    assert len(far_aff) > 100 and len(far_hom) > 100
    # The affine anchor: tracks slide below their point (+v), all of them the same way.
    assert far_aff[:, 1].mean() > 0.05
    assert np.mean(far_aff[:, 1] > 0.0) > 0.8
    # The homography: no shared drift, and a smaller RMS error (what is left is the resampling's).
    assert abs(far_hom[:, 1].mean()) < 0.2 * far_aff[:, 1].mean()
    assert np.sqrt(np.mean(far_hom**2)) < 0.95 * np.sqrt(np.mean(far_aff**2))
    # Near the template (translation and affine fits only) both are the same code: the same errors.
    near = 8
    np.testing.assert_allclose(e_aff[:near], e_hom[:near], atol=1e-9)


def test_projective_update_composes_the_homographies():
    """``T(c') [[A', 0], [g'^T, 1]] = T(c) [[A, 0], [g^T, 1]] H(dp)^-1`` up to scale (a matrix product)."""
    rng = np.random.default_rng(3)
    n = 20
    c = rng.uniform(50.0, 200.0, (n, 2))
    A = np.eye(2) + 0.2 * rng.standard_normal((n, 2, 2))
    g = 0.01 * rng.standard_normal((n, 2))
    dp = np.concatenate(
        [0.05 * rng.standard_normal((n, 4)), rng.standard_normal((n, 2)), 0.01 * rng.standard_normal((n, 2))],
        axis=1,
    )
    delta, A_new, g_new = TemplateAnchors._compose_projective(A, g, dp)

    def full(c, A, g):
        M = np.zeros((len(c), 3, 3))
        M[:, :2, :2], M[:, :2, 2], M[:, 2, :2], M[:, 2, 2] = A, c, g, 1.0
        M[:, :2, :2] += c[:, :, None] * g[:, None, :]  # T(c) [[A, 0], [g^T, 1]]
        return M

    H = np.zeros((n, 3, 3))
    H[:, 0, 0], H[:, 1, 0], H[:, 0, 1], H[:, 1, 1] = 1.0 + dp[:, 0], dp[:, 1], dp[:, 2], 1.0 + dp[:, 3]
    H[:, :2, 2], H[:, 2, :2], H[:, 2, 2] = dp[:, 4:6], dp[:, 6:8], 1.0
    expected = full(c, A, g) @ np.linalg.inv(H)
    expected /= expected[:, 2:, 2:]
    np.testing.assert_allclose(full(c + delta, A_new, g_new), expected, rtol=1e-10, atol=1e-10)
    # Without a projective part it is the affine update: A (I + D)^-1, c - A (I + D)^-1 t.
    dp[:, 6:] = 0.0
    delta, A_aff, g_aff = TemplateAnchors._compose_projective(A, np.zeros((n, 2)), dp)
    inv = np.linalg.inv(np.eye(2) + dp[:, [0, 2, 1, 3]].reshape(-1, 2, 2))
    np.testing.assert_allclose(A_aff, A @ inv, atol=1e-12)
    np.testing.assert_allclose(delta, -np.einsum("nij,nj->ni", A @ inv, dp[:, 4:6]), atol=1e-12)
    np.testing.assert_array_equal(g_aff, 0.0)
