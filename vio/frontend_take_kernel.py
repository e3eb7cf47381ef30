"""Compiled template taking of the KLT anchoring: :meth:`viotb.vio.klt_anchor.TemplateAnchors.take` per track.

When a track starts (or its anchoring failed), :class:`~viotb.vio.klt_anchor.TemplateAnchors` takes its
template and precomputes the inverse-compositional solve matrices (Baker and Matthews, "Lucas-Kanade 20
years on", IJCV 56(3), 2004, sec. 3.2): the steepest-descent images ``SD`` of the translation, affine and
homography fits, their damped Gauss-Newton matrices ``H``, and ``J = H^-1 SD^T`` with ``J T``. The numpy
version does this for a batch in ~40 array calls of small stacks (``(N, 6, 6)`` inverses, ``(N, 6, P)``
products), whose fixed cost dominates at the 10-60 new tracks of a frame. :func:`take_templates` does it
track by track in one loop, in the same order of operations and precisions (the patch sampled as
``cv2.remap`` samples it, float32 template and gradients, float64 solve matrices), so the numpy code stays
the reference the tests compare against (``tests/test_frontend_kernels.py``): the sums here are
sequential float64 where numpy's are pairwise (float32 for the patch mean and RMS) and the inverses come
from a Gauss-Jordan elimination instead of LAPACK's, so the stored matrices agree to round-off.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from viotb.vio.frontend_kernels import _bilinear
from viotb.vio.jit import njit


@njit
def _inverse_into(M: np.ndarray, n: int, out: np.ndarray) -> bool:
    """``out[:n, :n] = M[:n, :n]^-1`` by Gauss-Jordan elimination with partial pivoting; False if singular."""
    a = np.empty((n, 2 * n))
    for i in range(n):
        for j in range(n):
            a[i, j] = M[i, j]
            a[i, n + j] = 1.0 if i == j else 0.0
    for col in range(n):
        piv = col
        for i in range(col + 1, n):
            if abs(a[i, col]) > abs(a[piv, col]):
                piv = i
        if a[piv, col] == 0.0:
            return False
        if piv != col:
            for j in range(2 * n):
                a[col, j], a[piv, j] = a[piv, j], a[col, j]
        inv_p = 1.0 / a[col, col]
        for j in range(2 * n):
            a[col, j] *= inv_p
        for i in range(n):
            if i != col and a[i, col] != 0.0:
                f = a[i, col]
                for j in range(2 * n):
                    a[i, j] -= f * a[col, j]
    for i in range(n):
        for j in range(n):
            out[i, j] = a[i, n + j]
    return True


@njit
def _damped_gauss_newton(sd: np.ndarray, n_sd: int, damp: np.ndarray) -> np.ndarray:
    """``H = SD SD^T`` of the first ``n_sd`` steepest-descent images, its diagonal times ``1 + damp``."""
    S = np.ascontiguousarray(sd[:n_sd])
    H = np.dot(S, S.T)
    for i in range(n_sd):
        H[i, i] += damp[i] * H[i, i]
    return H


@njit
def _solve_matrices(
    H: np.ndarray, sd: np.ndarray, tmpl: np.ndarray, J_out: np.ndarray, Jt_out: np.ndarray
) -> bool:
    """``J = H^-1 SD`` (rounded to float32 into ``J_out``) and ``J T`` (float64, from the unrounded ``J``).

    Returns False where ``H`` is singular.
    """
    n_sd = H.shape[0]
    n_px = sd.shape[1]
    H_inv = np.empty((n_sd, n_sd))
    if not _inverse_into(H, n_sd, H_inv):
        return False
    row = np.empty(n_px)
    for i in range(n_sd):
        row[:] = 0.0
        for k in range(n_sd):  # row i of H^-1 SD as a sum of scaled rows (no reduction in the inner loop)
            h = H_inv[i, k]
            for p in range(n_px):
                row[p] += h * sd[k, p]
        jt = 0.0
        for p in range(n_px):
            J_out[i, p] = np.float32(row[p])
            jt += row[p] * np.float64(tmpl[p])
        Jt_out[i] = jt
    return True


@njit
def take_templates(
    image: np.ndarray,
    uv: np.ndarray,
    r: np.ndarray,
    damping: float,
    projective_damping: float,
    projective: bool,
    min_texture: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Templates and solve matrices of tracks at pixels ``uv`` (``TemplateAnchors.take`` after its checks).

    Args:
        image: float32 image (H, W).
        uv: Pixels (px) of the new templates' centres, shape (N, 2), inside the image by the patch.
        r: Template offsets (px), shape (side,), ``side^2 = P`` (the template grid's rows and columns).
        damping: Levenberg damping of the 6 affine parameters (relative to their diagonal).
        projective_damping: The same for the two projective parameters.
        projective: Also the homography's matrices (``J`` has 8 rows, else 6).
        min_texture: Smallest template RMS (gray levels) for a kept template.

    Returns:
        ``(keep (N,) bool, tmpl (N, P) float32, J (N, 3, W, P) float32, J_tmpl (N, 3, W))``: whether a
        template was kept (textured, invertible), the normalized template, and per fit (translation in
        rows 4-5 of slot 0, affine rows 0-5 of slot 1, homography rows 0-7 of slot 2) ``H^-1 SD^T`` and
        its product with the template; rows a fit does not have are zero.
    """
    n = uv.shape[0]
    side = r.shape[0]
    n_px = side * side
    width = 8 if projective else 6
    keep = np.zeros(n, dtype=np.bool_)
    tmpl = np.zeros((n, n_px), dtype=np.float32)
    J = np.zeros((n, 3, width, n_px), dtype=np.float32)
    J_tmpl = np.zeros((n, 3, width))
    big = np.empty((side + 2, side + 2), dtype=np.float32)
    sd = np.empty((8, n_px))
    damp6 = np.full(6, damping)
    damp8 = np.full(8, damping)
    damp8[6:] = projective_damping
    J2 = np.empty((2, n_px), dtype=np.float32)
    Jt2 = np.empty(2)
    for k in range(n):
        # 1. The patch with one more ring (for central differences), sampled as cv2.remap samples it.
        for i in range(side + 2):
            y = np.float32(uv[k, 1] + (i - 1 + r[0]))
            for j in range(side + 2):
                x = np.float32(uv[k, 0] + (j - 1 + r[0]))
                big[i, j] = _bilinear(image, x, y)
        # 2. Zero-mean, unit-RMS template (float32, as the numpy version).
        total = 0.0
        for i in range(side):
            for j in range(side):
                total += big[i + 1, j + 1]
        mean = np.float32(total / n_px)
        ss = 0.0
        for i in range(side):
            for j in range(side):
                d = np.float32(big[i + 1, j + 1] - mean)
                ss += np.float64(d) * d
        rms = np.float32(math.sqrt(np.float32(ss / n_px)))
        if not rms >= min_texture:
            continue
        inv_rms = np.float32(1.0 / max(rms, np.float32(1e-9)))
        # 3. Steepest-descent images of the affine warp at p = 0 (gradient times dW/dp), then the two
        #    homography rows -(x, y) (gx x + gy y).
        for i in range(side):
            for j in range(side):
                p = i * side + j
                d = np.float32(big[i + 1, j + 1] - mean)
                tmpl[k, p] = np.float32(d / max(rms, np.float32(1e-9)))
                gx = np.float64(np.float32(np.float32(0.5) * (big[i + 1, j + 2] - big[i + 1, j])) * inv_rms)
                gy = np.float64(np.float32(np.float32(0.5) * (big[i + 2, j + 1] - big[i, j + 1])) * inv_rms)
                dx, dy = r[j], r[i]
                sd[0, p], sd[1, p], sd[2, p], sd[3, p] = gx * dx, gy * dx, gx * dy, gy * dy
                sd[4, p], sd[5, p] = gx, gy
                radial = gx * dx + gy * dy
                sd[6, p], sd[7, p] = -dx * radial, -dy * radial
        # 4. The damped affine Gauss-Newton matrix must be invertible (the numpy version's determinant test).
        H6 = _damped_gauss_newton(sd, 6, damp6)
        if not np.linalg.det(H6) > 0.0:
            continue
        # 5. J = H^-1 SD^T and J T of the affine fit (slot 1), of the translation (slot 0, rows 4-5: the
        #    damped matrix's translation block) and of the homography (slot 2).
        if not _solve_matrices(H6, sd, tmpl[k], J[k, 1], J_tmpl[k, 1]):
            continue
        if not _solve_matrices(np.ascontiguousarray(H6[4:, 4:]), sd[4:6], tmpl[k], J2, Jt2):
            continue
        for q in range(2):
            J[k, 0, 4 + q] = J2[q]
            J_tmpl[k, 0, 4 + q] = Jt2[q]
        if projective:
            if not _solve_matrices(_damped_gauss_newton(sd, 8, damp8), sd, tmpl[k], J[k, 2], J_tmpl[k, 2]):
                continue
        keep[k] = True
    return keep, tmpl, J, J_tmpl


@functools.cache
def warm_up(half_size_px: int, projective: bool) -> None:
    """Load (or, on a machine's first run, compile) the anchoring's kernels with their call types, once.

    Numba loads a cached kernel on its first call in a process (measured 0.3 s for :func:`take_templates`
    in a fresh process), which would otherwise land in a timed frame: in a 201-frame replay, the p99 frame
    time. :class:`viotb.vio.klt_anchor.TemplateAnchors` calls this when it is built with ``compiled``, as
    :mod:`viotb.vio.imu_kernels_calls` does for the propagation; it runs once per process and template
    size. The image is a fixed synthetic texture, so no random state is touched.
    """
    from viotb.vio.frontend_kernels import align_templates

    n = 4 * half_size_px + 8
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    image = np.ascontiguousarray(128.0 + 60.0 * np.sin(0.7 * xx) * np.cos(0.5 * yy), dtype=np.float32)
    r = np.arange(-half_size_px, half_size_px + 1, dtype=float)
    uv = np.array([[0.5 * n, 0.5 * n]])
    keep, tmpl, J, J_tmpl = take_templates(image, uv, r, 1e-3, 1.0, projective, 4.0)
    rows, mode = np.zeros(1, dtype=np.int64), np.ones(1, dtype=np.int64)
    A, g = np.eye(2)[None].copy(), np.zeros((1, 2))
    align_templates(image, uv, A, g, rows, mode, J, J_tmpl, tmpl, r, 1, 0.0, True)
