"""Compiled kernels of the window optimizer's linearization (numba, :func:`viotb.vio.jit.njit`).

:func:`white_reprojection` is one loop over a camera's observations that does what the white-noise branch of
:func:`viotb.vio.window_reprojection.add_reprojection` does with numpy (which stays the reference its tests
compare against, ``tests/test_window_reprojection.py``): the projection and its Jacobians
(:func:`viotb.vio.window_factors.reprojection`), the whitened residual, its Huber weight and cost, each
observation's block ``A = w J^T J`` (``J = [J_pose (6), J_point (3), r] / sigma``, shape (2, 10)) and their
sums per keyframe and per landmark. The numpy path made about 40 array operations of M rows each and two
sparse products; at the window's sizes (M ~ 700-1000) their call overhead and temporaries were most of a
linearization. The formulas are the reference's; only the order of a few sums differs (BLAS may group a 3-term
product otherwise, ``np.sum`` sums pairwise): a last-bit difference.
"""

from __future__ import annotations

import math

import numpy as np
from viotb.vio.jit import njit


@njit
def white_reprojection(
    R_WB: np.ndarray,
    p_WB: np.ndarray,
    pts: np.ndarray,
    kf_i: np.ndarray,
    lm_i: np.ndarray,
    xy: np.ndarray,
    R_BC: np.ndarray,
    p_BC: np.ndarray,
    s: float,
    k_h: float,
    per_kf: np.ndarray,
    per_lm: np.ndarray,
    A: np.ndarray,
    E: np.ndarray,
    max_err: np.ndarray,
) -> float:
    """One camera's Huber-weighted reprojection blocks, white noise (module doc); returns the sum of ``rho``.

    Args:
        R_WB: Keyframe orientations, shape (N, 3, 3).
        p_WB: Keyframe positions in W (m), shape (N, 3).
        pts: Landmarks in W (m), shape (L, 3).
        kf_i: Keyframe of each observation, shape (M,) int64.
        lm_i: Landmark of each observation, shape (M,) int64 (one observation per keyframe and landmark).
        xy: Measured normalized coordinates, shape (M, 2).
        R_BC: Camera-to-body rotation, shape (3, 3).
        p_BC: Camera origin in B (m), shape (3,).
        s: ``1 / sigma`` in normalized coordinates.
        k_h: Huber threshold (sigmas).
        per_kf: Out, zeros on entry: ``sum_m A_m`` per keyframe, shape (N, 10, 10).
        per_lm: Out, zeros on entry: the same per landmark, shape (L, 10, 10).
        A: Out: each observation's ``w J^T J``, shape (M, 10, 10).
        E: In/out: ``A_m[:6, 6:9]`` added at ``[l, k]``, shape (L, N, 6, 3).
        max_err: In/out: raised to each landmark's largest whitened error norm (NaN propagates), (L,).

    Returns:
        ``sum_m rho(e_m)`` with ``rho(e) = e^2`` (``e <= k_h``) or ``2 k_h e - k_h^2`` (the cost is half).
    """
    huber_sum = 0.0
    J = np.empty((2, 10))
    Aq = np.empty((2, 3))
    for m in range(kf_i.shape[0]):
        k = kf_i[m]
        lm = lm_i[m]
        d0 = pts[lm, 0] - p_WB[k, 0]
        d1 = pts[lm, 1] - p_WB[k, 1]
        d2 = pts[lm, 2] - p_WB[k, 2]
        q0 = R_WB[k, 0, 0] * d0 + R_WB[k, 1, 0] * d1 + R_WB[k, 2, 0] * d2
        q1 = R_WB[k, 0, 1] * d0 + R_WB[k, 1, 1] * d1 + R_WB[k, 2, 1] * d2
        q2 = R_WB[k, 0, 2] * d0 + R_WB[k, 1, 2] * d1 + R_WB[k, 2, 2] * d2
        c0, c1, c2 = q0 - p_BC[0], q1 - p_BC[1], q2 - p_BC[2]
        x_c = c0 * R_BC[0, 0] + c1 * R_BC[1, 0] + c2 * R_BC[2, 0]
        y_c = c0 * R_BC[0, 1] + c1 * R_BC[1, 1] + c2 * R_BC[2, 1]
        z_c = c0 * R_BC[0, 2] + c1 * R_BC[1, 2] + c2 * R_BC[2, 2]
        Zs = 1e-9 if abs(z_c) < 1e-9 else z_c
        u = x_c / Zs
        v = y_c / Zs
        iz = 1.0 / Zs
        du = -u / Zs
        dv = -v / Zs
        for i in range(3):  # d z / d q = dz R_BC^T
            Aq[0, i] = iz * R_BC[i, 0] + du * R_BC[i, 2]
            Aq[1, i] = iz * R_BC[i, 1] + dv * R_BC[i, 2]
        r0 = (u - xy[m, 0]) * s
        r1 = (v - xy[m, 1]) * s
        for a in range(2):
            # d z / d theta = Aq [q]x; d z / d p_W = Aq R_WB^T = -d z / d p_WB
            J[a, 0] = (Aq[a, 1] * q2 - Aq[a, 2] * q1) * s
            J[a, 1] = (Aq[a, 2] * q0 - Aq[a, 0] * q2) * s
            J[a, 2] = (Aq[a, 0] * q1 - Aq[a, 1] * q0) * s
            for i in range(3):
                jp = Aq[a, 0] * R_WB[k, i, 0] + Aq[a, 1] * R_WB[k, i, 1] + Aq[a, 2] * R_WB[k, i, 2]
                J[a, 3 + i] = -jp * s
                J[a, 6 + i] = jp * s
        J[0, 9] = r0
        J[1, 9] = r1
        e = math.sqrt(r0 * r0 + r1 * r1)
        if e <= k_h:
            w = 1.0
            huber_sum += e * e
        else:
            w = k_h / (1e-12 if e < 1e-12 else e)  # NaN stays NaN, as np.maximum
            huber_sum += 2.0 * k_h * e - k_h * k_h
        if not e <= max_err[lm]:
            max_err[lm] = e
        for i in range(10):
            w0 = J[0, i] * w
            w1 = J[1, i] * w
            for j in range(10):
                aij = w0 * J[0, j] + w1 * J[1, j]
                A[m, i, j] = aij
                per_kf[k, i, j] += aij
                per_lm[lm, i, j] += aij
        for i in range(6):
            for j in range(3):
                E[lm, k, i, j] += A[m, i, 6 + j]
    return huber_sum


@njit
def _inv3(M: np.ndarray, out: np.ndarray) -> None:
    """``out = M^-1`` of a 3 x 3 matrix by its adjugate (M is a damped landmark information block)."""
    a, b, c = M[0, 0], M[0, 1], M[0, 2]
    d, e, f = M[1, 0], M[1, 1], M[1, 2]
    g, h, k = M[2, 0], M[2, 1], M[2, 2]
    A0, A1, A2 = e * k - f * h, f * g - d * k, d * h - e * g
    inv_det = 1.0 / (a * A0 + b * A1 + c * A2)
    out[0, 0], out[0, 1], out[0, 2] = A0 * inv_det, (c * h - b * k) * inv_det, (b * f - c * e) * inv_det
    out[1, 0], out[1, 1], out[1, 2] = A1 * inv_det, (a * k - c * g) * inv_det, (c * d - a * f) * inv_det
    out[2, 0], out[2, 1], out[2, 2] = A2 * inv_det, (b * g - a * h) * inv_det, (a * e - b * d) * inv_det


@njit
def landmark_products(
    E: np.ndarray, H_ll: np.ndarray, g_l: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The factors of the Schur complement over the landmarks, laid out for one matrix product.

    With ``B_l = E_l H_ll,l^-1`` (R, 3) the complement is ``S -= sum_l B_l E_l^T`` and ``g -= sum_l B_l g_l``
    (:func:`viotb.vio.window_solver.schur_reduce`). Here each ``H_ll,l^-1`` is the adjugate inverse of the
    3 x 3 block, ``B`` and ``E`` are written side by side as (R, 3 L) matrices (column ``3 l + i``), so the
    caller's one BLAS product ``B_flat E_flat^T`` sums every landmark, and ``B g_l`` is summed here, the zero
    rows of each ``E_l`` skipped.

    Args:
        E: Pose-landmark blocks, shape (L, R, 3).
        H_ll: Damped landmark information blocks, shape (L, 3, 3).
        g_l: Landmark gradients, shape (L, 3).

    Returns:
        ``(B_flat (R, 3 L), E_flat (R, 3 L), H_ll^-1 (L, 3, 3), sum_l B_l g_l (R,))``.
    """
    L, R = E.shape[0], E.shape[1]
    B_flat = np.zeros((R, 3 * L))
    E_flat = np.zeros((R, 3 * L))
    H_ll_inv = np.empty((L, 3, 3))
    Bg = np.zeros(R)
    for lm in range(L):
        Hi = H_ll_inv[lm]
        _inv3(H_ll[lm], Hi)
        for r in range(R):
            e0, e1, e2 = E[lm, r, 0], E[lm, r, 1], E[lm, r, 2]
            if e0 == 0.0 and e1 == 0.0 and e2 == 0.0:
                continue
            E_flat[r, 3 * lm], E_flat[r, 3 * lm + 1], E_flat[r, 3 * lm + 2] = e0, e1, e2
            acc = 0.0
            for j in range(3):
                b = e0 * Hi[0, j] + e1 * Hi[1, j] + e2 * Hi[2, j]
                B_flat[r, 3 * lm + j] = b
                acc += b * g_l[lm, j]
            Bg[r] += acc
    return B_flat, E_flat, H_ll_inv, Bg
