"""Compiled per-feature stages of the MSCKF update: one kernel call from the residuals to the chi-square.

:func:`feature_gate_kernel` does, for every triangulated feature in one loop, what
:func:`viotb.vio.msckf_update.feature_system`, :func:`viotb.vio.update_helpers.nullspace_project` and the
chi-square gate of :func:`viotb.vio.msckf_update.msckf_update` do batched in numpy (the reference, kept and
selectable with ``MsckfParams.update_kernels``): the residuals and Jacobians of its valid views
(:func:`viotb.vio.update_helpers.feature_jacobian`), the random-walk whitening of its views
(:func:`viotb.vio.update_helpers.random_walk_whitener`, as a triangular solve with the Cholesky factor
instead of its inverse), the left null space of its feature Jacobian by Householder reflections (LAPACK
``dgeqrf``'s convention, applied to ``[H_x | r]`` without forming ``Q``), and its innovation covariance
``S = H_o P H_o^T + sigma^2 I`` and ``chi2 = r_o^T S^-1 r_o``.

Only the feature's valid views enter (the reference carries the masked views as zero rows, which drop
out exactly: their whitening rows are decoupled, and a null-space basis of the padded system spans the
same space plus unit vectors with zero residual and Jacobian), so a feature with ``m`` views gives
``2 m - 3`` rows, the gate's degrees of freedom. The null-space basis is another orthonormal basis of the
same space than the reference's complete QR, so the rows differ by a rotation per feature and ``chi2``,
``H_o^T H_o`` and ``H_o^T r_o`` (all an update depends on) agree to round-off
(``tests/test_msckf_kernels.py``).
"""

from __future__ import annotations

import numpy as np
from viotb.vio.jit import njit


@njit
def _view_rows(
    p_f: np.ndarray,
    R_WB: np.ndarray,
    p_WB: np.ndarray,
    R_BC: np.ndarray,
    p_BC: np.ndarray,
    out_z: np.ndarray,
    out_dz_dpc: np.ndarray,
    out_dz_dpb: np.ndarray,
    out_p_B: np.ndarray,
    out_p_C: np.ndarray,
) -> None:
    """Prediction and the chain factors of one view (``feature_jacobian`` for one clone and camera)."""
    for i in range(3):
        out_p_B[i] = (
            R_WB[0, i] * (p_f[0] - p_WB[0])
            + R_WB[1, i] * (p_f[1] - p_WB[1])
            + R_WB[2, i] * (p_f[2] - p_WB[2])
        )
    for i in range(3):
        out_p_C[i] = (
            R_BC[0, i] * (out_p_B[0] - p_BC[0])
            + R_BC[1, i] * (out_p_B[1] - p_BC[1])
            + R_BC[2, i] * (out_p_B[2] - p_BC[2])
        )
    Z = out_p_C[2] if abs(out_p_C[2]) >= 1e-12 else 1e-12
    out_z[0] = out_p_C[0] / Z
    out_z[1] = out_p_C[1] / Z
    inv_z = 1.0 / Z
    out_dz_dpc[0, 0], out_dz_dpc[0, 1], out_dz_dpc[0, 2] = inv_z, 0.0, -out_z[0] * inv_z
    out_dz_dpc[1, 0], out_dz_dpc[1, 1], out_dz_dpc[1, 2] = 0.0, inv_z, -out_z[1] * inv_z
    for a in range(2):
        for i in range(3):  # dz/dp_B = dz/dp_C R_BC^T
            out_dz_dpb[a, i] = (
                out_dz_dpc[a, 0] * R_BC[i, 0] + out_dz_dpc[a, 1] * R_BC[i, 1] + out_dz_dpc[a, 2] * R_BC[i, 2]
            )


@njit
def _skew_product(A: np.ndarray, v: np.ndarray, out: np.ndarray, col: int, scale: float) -> None:
    """``out[:, col:col + 3] = scale * A [v]x`` for a 2 x 3 ``A``."""
    for a in range(2):
        out[a, col + 0] = scale * (A[a, 1] * v[2] - A[a, 2] * v[1])
        out[a, col + 1] = scale * (A[a, 2] * v[0] - A[a, 0] * v[2])
        out[a, col + 2] = scale * (A[a, 0] * v[1] - A[a, 1] * v[0])


@njit
def _whiten_rows(X: np.ndarray, L: np.ndarray, m: int) -> None:
    """``X <- L^-1 X`` on the views (rows: view, axis), ``L`` (m, m) lower triangular."""
    n_col = X.shape[1]
    for i in range(m):
        for j in range(i):
            lij = L[i, j]
            if lij != 0.0:
                for a in range(2):
                    for c in range(n_col):
                        X[2 * i + a, c] -= lij * X[2 * j + a, c]
        inv = 1.0 / L[i, i]
        for a in range(2):
            for c in range(n_col):
                X[2 * i + a, c] *= inv


@njit
def _reflect_rows(X: np.ndarray, vv: np.ndarray, tau: np.ndarray) -> None:
    """``X <- H_2 H_1 H_0 X`` with the reflectors ``H_c = I - tau_c v_c v_c^T`` (``v_c`` zero above ``c``)."""
    n_rows, n_col = X.shape
    s = np.zeros(n_col)
    for c in range(3):
        if tau[c] == 0.0:
            continue
        s[:] = 0.0
        for i in range(c, n_rows):
            vi = vv[c, i]
            for j in range(n_col):
                s[j] += vi * X[i, j]
        for j in range(n_col):
            s[j] *= tau[c]
        for i in range(c, n_rows):
            vi = vv[c, i]
            for j in range(n_col):
                X[i, j] -= vi * s[j]


@njit
def feature_gate_kernel(
    xy: np.ndarray,
    mask: np.ndarray,
    p_f: np.ndarray,
    R_cur: np.ndarray,
    p_cur: np.ndarray,
    R_jac: np.ndarray,
    p_jac: np.ndarray,
    R_BC: np.ndarray,
    p_BC: np.ndarray,
    has_ext: bool,
    w_right: float,
    rw_to_white_var: float,
    focal_v: np.ndarray,
    P_cc: np.ndarray,
    sigma2: float,
    chi2_max: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Null-space-projected rows and chi-square of every feature (module docstring).

    Args:
        xy: Observed normalized coordinates, shape (F, C K, 2) (cam0's K views, then cam1's).
        mask: Valid views, shape (F, C K), at least 2 per feature.
        p_f: Feature positions (m) in W, shape (F, 3), the linearization point.
        R_cur: Clone orientations at the current estimates (residuals), shape (K, 3, 3).
        p_cur: Clone positions (m) at the current estimates, shape (K, 3).
        R_jac: Clone orientations where the Jacobians are evaluated, shape (K, 3, 3).
        p_jac: Clone positions (m) where the Jacobians are evaluated, shape (K, 3).
        R_BC: Camera-to-body rotations, shape (C, 3, 3).
        p_BC: Camera origins in B (m), shape (C, 3).
        has_ext: The cam0 extrinsic is estimated (its 6 columns follow the clones' 6 K; cam1 has none).
        w_right: Weight of cam1 rows (``f1 / f0``: whitened to cam0's normalized sigma).
        rw_to_white_var: Random-walk to white variance per px of image path (0: white noise, no whitening).
        focal_v: Focal length (px) of each view's camera, shape (C K,).
        P_cc: Covariance of the columns (clones, then extrinsic), shape (n_c, n_c), n_c = 6 K (+ 6).
        sigma2: White measurement variance (normalized coordinates squared).
        chi2_max: Gate of each degree of freedom, shape (at least 2 C K - 2,): a feature passes when
            ``chi2 < chi2_max[dof]``.

    Returns:
        ``(chi2 (F,), dof (F,), passed (F,), gram (n_c, n_c), h_r (n_c,))``: ``dof = 2 m - 3``, and the
        normal equations ``H^T H``, ``H^T r`` of the passed features' stacked rows ``(H_o, r_o)``.
    """
    F, V = mask.shape
    K = R_cur.shape[0]
    n_c = P_cc.shape[0]
    ext_col = 6 * K
    dof = np.zeros(F, np.int64)
    chi2 = np.zeros(F)
    passed = np.zeros(F, np.bool_)
    gram = np.zeros((n_c, n_c))
    h_r = np.zeros(n_c)
    z = np.zeros(2)
    dz_dpc = np.zeros((2, 3))
    dz_dpb = np.zeros((2, 3))
    p_B = np.zeros(3)
    p_C = np.zeros(3)
    rows = np.zeros((2, 2 * n_c + 4))
    for f in range(F):
        views = np.zeros(V, np.int64)
        m = 0
        for v in range(V):
            if mask[f, v]:
                views[m] = v
                m += 1
        n_rows = 2 * m
        dof[f] = n_rows - 3
        # [H_x | H_f | r] of the valid views, rows (view, axis).
        A = np.zeros((n_rows, 2 * n_c + 4))  # [H_x | H_f | r | H_x P]
        blk = np.zeros((m, 12), np.int64)  # the columns each view's rows touch
        n_blk = np.zeros(m, np.int64)
        for j in range(m):
            v = views[j]
            k = v % K
            c = v // K
            w = w_right if c == 1 else 1.0
            _view_rows(p_f[f], R_cur[k], p_cur[k], R_BC[c], p_BC[c], z, dz_dpc, dz_dpb, p_B, p_C)
            r0 = (xy[f, v, 0] - z[0]) * w
            r1 = (xy[f, v, 1] - z[1]) * w
            _view_rows(p_f[f], R_jac[k], p_jac[k], R_BC[c], p_BC[c], z, dz_dpc, dz_dpb, p_B, p_C)
            rows[:] = 0.0
            _skew_product(dz_dpb, p_B, rows, 6 * k, w)
            for a in range(2):
                for i in range(3):  # H_f = dz/dp_B R_WB^T
                    hf = w * (
                        dz_dpb[a, 0] * R_jac[k, i, 0]
                        + dz_dpb[a, 1] * R_jac[k, i, 1]
                        + dz_dpb[a, 2] * R_jac[k, i, 2]
                    )
                    rows[a, n_c + i] = hf
                    rows[a, 6 * k + 3 + i] = -hf
            if has_ext and c == 0:
                _skew_product(dz_dpc, p_C, rows, ext_col, w)
                for a in range(2):
                    for i in range(3):
                        rows[a, ext_col + 3 + i] = -w * dz_dpb[a, i]
            for i in range(6):
                blk[j, i] = 6 * k + i
            n_blk[j] = 6
            if has_ext and c == 0:
                for i in range(6):
                    blk[j, 6 + i] = ext_col + i
                n_blk[j] = 12
            rows[0, n_c + 3] = r0
            rows[1, n_c + 3] = r1
            A[2 * j] = rows[0]
            A[2 * j + 1] = rows[1]
        # G = H_x P of the unwhitened rows from the per-view blocks (2 x 6 on its clone, plus the
        # extrinsic's 6 on a cam0 view), carried through the same row operations: H_o P.
        for i in range(n_rows):
            for ci in range(n_blk[i // 2]):
                col = blk[i // 2, ci]
                h = A[i, col]
                for c in range(n_c):
                    A[i, n_c + 4 + c] += h * P_cc[col, c]
        L = np.zeros((m, m))
        if rw_to_white_var > 0.0:
            # Clock: image path (px) since the feature's first view in each camera; R = I + q min(n_k, n_l).
            path = np.zeros(m)
            for j in range(1, m):
                v, u = views[j], views[j - 1]
                if v // K == u // K:
                    dx0 = xy[f, v, 0] - xy[f, u, 0]
                    dx1 = xy[f, v, 1] - xy[f, u, 1]
                    step = np.sqrt(dx0 * dx0 + dx1 * dx1) * focal_v[v]
                    path[j] = path[j - 1] + (step if np.isfinite(step) else 0.0)
            for i in range(m):
                for j in range(i + 1):
                    same = views[i] // K == views[j] // K
                    L[i, j] = rw_to_white_var * min(path[i], path[j]) if same else 0.0
                L[i, i] += 1.0
            L = np.linalg.cholesky(L)
            _whiten_rows(A, L, m)  # A <- L^-1 A on the views, for each image axis
        # Householder QR of the H_f columns (LAPACK dgeqrf's reflectors) applied to every column.
        vv = np.zeros((3, n_rows))
        tau = np.zeros(3)
        for col in range(3):
            cc = n_c + col
            alpha = A[col, cc]
            xnorm = 0.0
            for i in range(col + 1, n_rows):
                xnorm += A[i, cc] * A[i, cc]
            xnorm = np.sqrt(xnorm)
            if xnorm == 0.0:
                continue
            beta = -np.copysign(np.hypot(alpha, xnorm), alpha)
            tau[col] = (beta - alpha) / beta
            scale = 1.0 / (alpha - beta)
            vv[col, col] = 1.0
            for i in range(col + 1, n_rows):
                vv[col, i] = A[i, cc] * scale
            single = np.zeros(3)
            single[col] = tau[col]
            _reflect_rows(A, vv, single)
        n_o = n_rows - 3
        Ho = np.ascontiguousarray(A[3:, :n_c])
        ro = np.ascontiguousarray(A[3:, n_c + 3])
        S = np.dot(np.ascontiguousarray(A[3:, n_c + 4 :]), Ho.T)
        for i in range(n_o):
            for j in range(i):
                S[i, j] = S[j, i] = 0.5 * (S[i, j] + S[j, i])
            S[i, i] += sigma2
        chi2[f] = np.dot(ro, np.linalg.solve(S, ro))
        passed[f] = chi2[f] < chi2_max[dof[f]]
        if passed[f]:
            gram += np.dot(Ho.T, Ho)
            h_r += np.dot(Ho.T, ro)
    return chi2, dof, passed, gram, h_r
