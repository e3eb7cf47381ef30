"""Compiled kernels of the KLT front end (numba, :func:`viotb.vio.jit.njit`).

:func:`align_templates` runs the whole inverse-compositional alignment of :class:`viotb.vio.klt_anchor.
TemplateAnchors` (``_align`` and the final ZNCC of ``refine``) as one loop over the tracks: the patch
sampling, the normalization, ``dp = J (w / rms) - J T``, the affine and homography compositions and the
image-bounds test, without the ~25 numpy calls per iteration on ``(N, P)`` arrays that the numpy version
makes. The numpy code stays as the reference its tests compare against.

The bilinear sample is OpenCV 5's ``cv2.remap`` (``INTER_LINEAR``, ``BORDER_REPLICATE``, float32 maps) as
measured on this build: ``v0 = fma(fx, p01 - p00, p00)``, ``v1 = fma(fx, p11 - p10, p10)``, ``v = fma(fy,
v1 - v0, v0)`` in float32 with ``fx = x - floor(x)`` (no 1/32 px quantization); the fused multiply-adds are
taken in float64 and rounded once to float32. The patch coordinates are built in float32 as the numpy
version builds them (each track by its own fit's formula; numpy builds a whole batch by the homography's
once one track in it is a homography), so the samples agree bit for bit where OpenCV uses that formula.
The sums (patch mean, dot products) are taken in float64 here and in float32 pairwise by numpy, so the
aligned positions agree to round-off (``tests/test_frontend_kernels.py``).
"""

from __future__ import annotations

import math

import numpy as np
from viotb.vio.jit import njit


@njit
def _bilinear(image: np.ndarray, x: np.float32, y: np.float32) -> np.float32:
    """``cv2.remap`` of a float32 image at one float32 point (bilinear, replicated border)."""
    h, w = image.shape
    xf = np.floor(x)  # float32 (math.floor, an int, is 10x slower here)
    yf = np.floor(y)
    fx = np.float32(x - xf)
    fy = np.float32(y - yf)
    xi, yi = int(xf), int(yf)
    x0 = min(max(xi, 0), w - 1)
    x1 = min(max(xi + 1, 0), w - 1)
    y0 = min(max(yi, 0), h - 1)
    y1 = min(max(yi + 1, 0), h - 1)
    p00, p01 = image[y0, x0], image[y0, x1]
    p10, p11 = image[y1, x0], image[y1, x1]
    v0 = np.float32(np.float64(fx) * np.float64(np.float32(p01 - p00)) + np.float64(p00))
    v1 = np.float32(np.float64(fx) * np.float64(np.float32(p11 - p10)) + np.float64(p10))
    return np.float32(np.float64(fy) * np.float64(np.float32(v1 - v0)) + np.float64(v0))


@njit
def sample_patch(
    image: np.ndarray,
    c: np.ndarray,
    A: np.ndarray,
    g: np.ndarray,
    use_g: bool,
    r: np.ndarray,
    out: np.ndarray,
) -> None:
    """One patch of ``TemplateAnchors._sample`` into ``out`` (P,) float32.

    Args:
        image: float32 image (H, W).
        c: Centre (px), shape (2,).
        A: Linear warp, shape (2, 2).
        g: Projective row (1/px), shape (2,) (read only with ``use_g``).
        use_g: Build the coordinates as the homography path does (``_sample`` with ``g``).
        r: Template offsets (px), shape (side,).
        out: Samples, shape (side * side,), float32 (written).
    """
    side = r.shape[0]
    f32 = np.float32
    for i in range(side):
        for j in range(side):
            if use_g:
                den = f32(f32(1.0 + g[0] * r[j]) + f32(g[1] * r[i]))
                x = f32(f32(A[0, 0] * r[j]) + f32(A[0, 1] * r[i]))
                y = f32(f32(A[1, 0] * r[j]) + f32(A[1, 1] * r[i]))
                x = f32(f32(x / den) + f32(c[0]))
                y = f32(f32(y / den) + f32(c[1]))
            else:
                x = f32(f32(c[0] + A[0, 0] * r[j]) + f32(A[0, 1] * r[i]))
                y = f32(f32(c[1] + A[1, 0] * r[j]) + f32(A[1, 1] * r[i]))
            out[i * side + j] = _bilinear(image, x, y)


@njit
def _inside_warped(
    c0: float, c1: float, A: np.ndarray, g0: float, g1: float, half: int, h: int, w: int
) -> bool:
    """``TemplateAnchors._inside_warped`` of one warp (``g0 = g1 = 0`` for an affine one)."""
    den = 1.0 - half * (abs(g0) + abs(g1))
    d = max(den, 0.5)
    ex = half * (abs(A[0, 0]) + abs(A[0, 1])) / d + 1.0
    ey = half * (abs(A[1, 0]) + abs(A[1, 1])) / d + 1.0
    return (c0 >= ex) and (c0 <= w - 1 - ex) and (c1 >= ey) and (c1 <= h - 1 - ey) and (den >= 0.5)


@njit
def _compose(A: np.ndarray, g: np.ndarray, dp: np.ndarray, proj: bool, c: np.ndarray) -> None:
    """The inverse compositional update of one warp, in place (``TemplateAnchors._align`` step 3).

    Affine: ``A <- A (I + D)^-1``, ``c <- c - A_new t``. Homography: ``_compose_projective`` (its
    docstring gives the closed form); ``g`` is updated only there.
    """
    # (I + D)^-1 with D = [[dp0, dp2], [dp1, dp3]], closed form as _inv_2x2.
    a, b, cc, d = 1.0 + dp[0], dp[2], dp[1], 1.0 + dp[3]
    det = a * d - b * cc
    m00, m01, m10, m11 = d / det, -b / det, -cc / det, a / det
    if not proj:
        n00 = A[0, 0] * m00 + A[0, 1] * m10
        n01 = A[0, 0] * m01 + A[0, 1] * m11
        n10 = A[1, 0] * m00 + A[1, 1] * m10
        n11 = A[1, 0] * m01 + A[1, 1] * m11
        A[0, 0], A[0, 1], A[1, 0], A[1, 1] = n00, n01, n10, n11
        c[0] = c[0] - (n00 * dp[4] + n01 * dp[5])
        c[1] = c[1] - (n10 * dp[4] + n11 * dp[5])
        return
    u0 = m00 * dp[4] + m01 * dp[5]
    u1 = m10 * dp[4] + m11 * dp[5]
    w0 = m00 * dp[6] + m10 * dp[7]  # M^-T p
    w1 = m01 * dp[6] + m11 * dp[7]
    s = 1.0 - (dp[6] * u0 + dp[7] * u1)
    k = 1.0 - (g[0] * u0 + g[1] * u1)
    delta0 = -(A[0, 0] * u0 + A[0, 1] * u1) / k
    delta1 = -(A[1, 0] * u0 + A[1, 1] * u1) / k
    gn0 = (s / k) * (m00 * g[0] + m10 * g[1]) - w0
    gn1 = (s / k) * (m01 * g[0] + m11 * g[1]) - w1
    t00 = m00 * s + u0 * w0
    t01 = m01 * s + u0 * w1
    t10 = m10 * s + u1 * w0
    t11 = m11 * s + u1 * w1
    n00 = (A[0, 0] * t00 + A[0, 1] * t10) / k - delta0 * gn0
    n01 = (A[0, 0] * t01 + A[0, 1] * t11) / k - delta0 * gn1
    n10 = (A[1, 0] * t00 + A[1, 1] * t10) / k - delta1 * gn0
    n11 = (A[1, 0] * t01 + A[1, 1] * t11) / k - delta1 * gn1
    A[0, 0], A[0, 1], A[1, 0], A[1, 1] = n00, n01, n10, n11
    g[0], g[1] = gn0, gn1
    c[0] += delta0
    c[1] += delta1


@njit
def align_templates(
    image: np.ndarray,
    c_start: np.ndarray,
    A_start: np.ndarray,
    g_start: np.ndarray,
    rows: np.ndarray,
    mode: np.ndarray,
    J_store: np.ndarray,
    J_tmpl_store: np.ndarray,
    tmpl_store: np.ndarray,
    r: np.ndarray,
    iterations: int,
    converged_px: float,
    zncc_at_final_warp: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``TemplateAnchors._align`` and ``refine``'s ZNCC, one track at a time.

    Args:
        image: float32 image (H, W).
        c_start: Start centres (px), shape (N, 2).
        A_start: Start linear warps, shape (N, 2, 2).
        g_start: Start projective rows (1/px), shape (N, 2) (read for the homography tracks only).
        rows: Storage rows of the templates, shape (N,).
        mode: Fit of each track (N,): 0 translation, 1 affine, 2 homography.
        J_store: ``H^-1 SD^T`` of every slot, shape (S, 3, W, P) float32 (W = 6 or 8).
        J_tmpl_store: ``J T`` of every slot, shape (S, 3, W).
        tmpl_store: Normalized templates, shape (S, P) float32.
        r: Template offsets (px), shape (side,), ``side^2 = P``.
        iterations: Largest number of Gauss-Newton iterations.
        converged_px: A track stops after a step of its centre no larger than this (px).
        zncc_at_final_warp: ZNCC of the patch at the final warp (else of the last iteration's samples).

    Returns:
        ``(c (N, 2), A (N, 2, 2), g (N, 2), ok (N,) bool, zncc (N,))``: the final warps, whether they
        stayed inside the image, and the ZNCC against the template (NaN where not computed).
    """
    n = c_start.shape[0]
    h, w = image.shape
    half = (r.shape[0] - 1) // 2
    n_px = r.shape[0] * r.shape[0]
    c = c_start.copy()
    A = A_start.copy()
    g = g_start.copy()
    ok = np.zeros(n, dtype=np.bool_)
    zncc = np.full(n, np.nan)
    patch = np.empty(n_px, dtype=np.float32)
    dp = np.zeros(8)
    acc = np.zeros(8)
    c_i = np.empty(2)
    A_i = np.empty((2, 2))
    g_i = np.zeros(2)
    for k in range(n):
        if not _inside_warped(c[k, 0], c[k, 1], A[k], g[k, 0], g[k, 1], half, h, w):
            continue
        ok[k] = True
        row, m = rows[k], mode[k]
        # Each track on its own fit's path: the numpy version builds every patch of a batch that holds
        # a homography with the homography's formula (the same coordinates up to float32 rounding), so
        # here a track's result does not depend on the other tracks of its batch.
        proj = m == 2
        width = 8 if proj else 6
        c_i[:] = c[k]
        A_i[:, :] = A[k]
        g_i[:] = g[k]
        for _ in range(iterations):
            sample_patch(image, c_i, A_i, g_i, proj, r, patch)
            total = 0.0
            for p in range(n_px):
                total += patch[p]
            mean = np.float32(total / n_px)
            ss = 0.0
            dot_t = 0.0
            for p in range(n_px):
                patch[p] = np.float32(patch[p] - mean)
                ss += np.float64(patch[p]) * patch[p]
                dot_t += np.float64(patch[p]) * tmpl_store[row, p]
            rms = max(np.float32(math.sqrt(np.float32(ss / n_px))), np.float32(1e-9))
            if not zncc_at_final_warp:
                zncc[k] = np.float32(dot_t / (n_px * rms))
            acc[:] = 0.0
            J_k = J_store[row, m]
            for p in range(n_px):  # all rows of J at once: independent sums
                wp = np.float64(patch[p])
                for q in range(width):
                    acc[q] += np.float64(J_k[q, p]) * wp
            for q in range(width):
                dp[q] = np.float64(np.float32(np.float32(acc[q]) / rms)) - J_tmpl_store[row, m, q]
            _compose(A_i, g_i, dp, proj, c_i)
            if not _inside_warped(c_i[0], c_i[1], A_i, g_i[0], g_i[1], half, h, w):
                ok[k] = False
                break
            c[k] = c_i
            A[k] = A_i
            g[k] = g_i
            if not math.hypot(dp[4], dp[5]) > converged_px:
                break
        if ok[k] and zncc_at_final_warp:
            sample_patch(image, c[k], A[k], g[k], proj, r, patch)
            total_f = 0.0
            for p in range(n_px):
                total_f += patch[p]
            mean_f = total_f / n_px
            ss_f = 0.0
            dot_f = 0.0
            for p in range(n_px):
                centred = patch[p] - mean_f
                ss_f += centred * centred
                dot_f += centred * tmpl_store[row, p]
            zncc[k] = dot_f / (max(math.sqrt(ss_f / n_px), 1e-9) * n_px)
    return c, A, g, ok, zncc
