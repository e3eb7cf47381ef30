"""Closed-form helpers of the template anchoring (:mod:`viotb.vio.klt_anchor`) on stacks of 2x2 matrices."""

from __future__ import annotations

import cv2
import numpy as np


def _normalize(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean, unit-RMS patches (N, P) and their RMS (N,) (a flat patch gets RMS 0)."""
    centred = patches - patches.mean(axis=1, keepdims=True)
    rms = np.sqrt(np.mean(centred * centred, axis=1))
    return centred / np.maximum(rms, 1e-9)[:, None], rms


def _inv_2x2(M: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 2x2 matrices (N, 2, 2), closed form (the caller keeps them invertible)."""
    a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
    out = np.empty_like(M)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = d, -b, -c, a
    return out / (a * d - b * c)[:, None, None]


def singular_values_2x2(M: np.ndarray) -> np.ndarray:
    """Singular values of a stack of 2x2 matrices (N, 2, 2), largest first, shape (N, 2), closed form.

    ``s1^2, s2^2`` are the eigenvalues of ``M^T M``: ``(f +- sqrt(f^2 - 4 det^2)) / 2`` with ``f`` the squared
    Frobenius norm.
    """
    f = np.sum(M * M, axis=(1, 2))
    det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] * M[:, 1, 0]
    root = np.sqrt(np.maximum(f * f - 4.0 * det * det, 0.0))
    s1 = np.sqrt(0.5 * (f + root))
    return np.stack([s1, np.abs(det) / np.maximum(s1, 1e-300)], axis=1)


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at pixel coordinates (pixel centres at integers), ``cv2.remap``.

    OpenCV 5 interpolates in float32 at the coordinate itself (OpenCV 4 rounded it to 1/32 px); borders
    are replicated (:mod:`viotb.vio.frontend_kernels` gives the formula).

    Args:
        image: Grayscale float32 image, shape (H, W).
        x: Column coordinates (px), shape (N, P).
        y: Row coordinates (px), shape (N, P).

    Returns:
        float32 samples, shape (N, P).
    """
    mx = np.ascontiguousarray(x, dtype=np.float32)
    my = np.ascontiguousarray(y, dtype=np.float32)
    out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(x.shape)


def take_templates_numpy(
    image: np.ndarray,
    uv: np.ndarray,
    r: np.ndarray,
    damping: float,
    projective_damping: float,
    projective: bool,
    min_texture: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Templates and inverse-compositional solve matrices of new tracks, batched in numpy (the reference).

    The template anchoring's (:meth:`viotb.vio.klt_anchor.TemplateAnchors.take`) steepest-descent images,
    damped Gauss-Newton matrices and ``J = H^-1 SD^T`` of the translation, affine and homography fits
    (Baker and Matthews, IJCV 56(3), 2004, sec. 2 and 3.2); arguments and returns as the compiled
    :func:`viotb.vio.frontend_take_kernel.take_templates`.
    """
    n = len(uv)
    r1 = np.arange(r[0] - 1.0, r[-1] + 2.0)  # one extra ring, for the central-difference gradients
    gy1, gx1 = np.meshgrid(r1, r1, indexing="ij")
    side1, side = r1.size, r.size
    gy0, gx0 = np.meshgrid(r, r, indexing="ij")
    dx, dy = gx0.ravel(), gy0.ravel()
    width = 8 if projective else 6
    J_all = np.zeros((n, 3, width, side * side), dtype=np.float32)
    J_tmpl = np.zeros((n, 3, width))
    big = sample_bilinear(image, uv[:, :1] + gx1.ravel(), uv[:, 1:] + gy1.ravel()).reshape(-1, side1, side1)
    inner = big[:, 1:-1, 1:-1].reshape(n, -1)
    tmpl, rms = _normalize(inner)
    scale = 1.0 / np.maximum(rms, 1e-9)[:, None]
    gx = 0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2]).reshape(n, -1) * scale
    gy = 0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1]).reshape(n, -1) * scale
    # Steepest-descent images, transposed (N, 6, P): the template gradient times dW/dp at p = 0 of
    # W(x; p) = (I + [[p1, p3], [p2, p4]]) x + (p5, p6) (Baker & Matthews 2004, sec. 2).
    sd_t = np.stack([gx * dx, gy * dx, gx * dy, gy * dy, gx, gy], axis=1)
    hess = np.matmul(sd_t, sd_t.transpose(0, 2, 1))
    hess += damping * hess[:, np.arange(6), np.arange(6)][:, :, None] * np.eye(6)
    keep = (rms >= min_texture) & (np.linalg.det(hess) > 0.0)
    if not np.any(keep):
        return keep, tmpl, J_all, J_tmpl
    rows = np.flatnonzero(keep)
    sd_t, hess, t64 = sd_t[rows], hess[rows], tmpl[rows][:, :, None].astype(float)
    J = np.matmul(np.linalg.inv(hess), sd_t)
    J_t = np.matmul(np.linalg.inv(hess[:, 4:, 4:]), sd_t[:, 4:])
    if projective:
        # The homography's two more steepest-descent images: dW/dp7 = -(x^2, x y), dW/dp8 = -(x y, y^2)
        # (W = H(p) x with H's last row (p7, p8, 1); Baker & Matthews 2004, sec. 2 and 3.2).
        radial = gx[rows] * dx + gy[rows] * dy
        sd_h = np.concatenate([sd_t, np.stack([-dx * radial, -dy * radial], axis=1)], axis=1)
        hess_h = np.matmul(sd_h, sd_h.transpose(0, 2, 1))
        damp = np.full(8, damping)
        damp[6:] = projective_damping
        hess_h += hess_h[:, np.arange(8), np.arange(8)][:, :, None] * np.diag(damp)
        J_h = np.matmul(np.linalg.inv(hess_h), sd_h)
        J_all[rows, 2] = J_h
        J_tmpl[rows, 2] = np.matmul(J_h, t64)[:, :, 0]
    J_all[rows, 0, 4:6] = J_t
    J_all[rows, 1, :6] = J
    J_tmpl[rows, 0, 4:6] = np.matmul(J_t, t64)[:, :, 0]
    J_tmpl[rows, 1, :6] = np.matmul(J, t64)[:, :, 0]
    return keep, tmpl, J_all, J_tmpl
