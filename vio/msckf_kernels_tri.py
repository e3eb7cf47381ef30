"""Compiled triangulation of the MSCKF update: :func:`viotb.vio.triangulation.triangulate` in loops.

The same computation as the batched numpy reference (anchor at the first view, linear midpoint start by
the 3 x 3 SVD of a symmetric matrix, here its Jacobi eigendecomposition, Levenberg-Marquardt on the
inverse depth ``(alpha, beta, rho)`` with one damping per feature, the same checks), written as loops over
features and views so that one call does the whole batch: the numpy version spends its time in ~300
small-array calls per update (README "MSCKF per frame"). The iterations stop for all features together,
as in the reference (once every feature's last step is below ``step_tolerance`` of its parameters), so
both take the same steps; the sums run in another order, so the points agree to round-off, up to a last
step accepted by one and not the other when the costs tie to round-off (``tests/test_msckf_kernels.py``).
"""

from __future__ import annotations

import numpy as np
from viotb.vio.jit import njit


@njit
def _solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A^-1 b`` for a 3 x 3 ``A`` by Gaussian elimination with partial pivoting (LAPACK ``dgesv``'s LU)."""
    M = A.copy()
    y = b.copy()
    for j in range(3):
        piv = j
        for i in range(j + 1, 3):
            if abs(M[i, j]) > abs(M[piv, j]):
                piv = i
        if piv != j:
            for c in range(3):
                M[j, c], M[piv, c] = M[piv, c], M[j, c]
            y[j], y[piv] = y[piv], y[j]
        for i in range(j + 1, 3):
            f = M[i, j] / M[j, j]
            for c in range(j + 1, 3):
                M[i, c] -= f * M[j, c]
            y[i] -= f * y[j]
    x = np.zeros(3)
    for i in range(2, -1, -1):
        s = y[i]
        for c in range(i + 1, 3):
            s -= M[i, c] * x[c]
        x[i] = s / M[i, i]
    return x


@njit
def _eig_sym3(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (by decreasing magnitude) and eigenvectors (columns) of a symmetric 3 x 3 ``A``.

    Cyclic Jacobi rotations (Golub and Van Loan, "Matrix Computations", Alg. 8.5.3) to round-off: for the
    symmetric midpoint matrix this is its SVD (singular values ``|w|``) without a LAPACK call per feature.
    """
    a = A.copy()
    V = np.eye(3)
    for _ in range(30):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-36 * diag or off == 0.0:
            break
        for p_, q in ((0, 1), (0, 2), (1, 2)):
            if a[p_, q] == 0.0:
                continue
            theta = (a[q, q] - a[p_, p_]) / (2.0 * a[p_, q])
            t = np.copysign(1.0, theta) / (abs(theta) + np.sqrt(theta * theta + 1.0))
            c = 1.0 / np.sqrt(t * t + 1.0)
            s_ = t * c
            for k in range(3):  # a <- a J (columns p, q)
                akp, akq = a[k, p_], a[k, q]
                a[k, p_], a[k, q] = c * akp - s_ * akq, s_ * akp + c * akq
            for k in range(3):  # a <- J^T a (rows p, q)
                apk, aqk = a[p_, k], a[q, k]
                a[p_, k], a[q, k] = c * apk - s_ * aqk, s_ * apk + c * aqk
            for k in range(3):
                vkp, vkq = V[k, p_], V[k, q]
                V[k, p_], V[k, q] = c * vkp - s_ * vkq, s_ * vkp + c * vkq
    w = np.array([a[0, 0], a[1, 1], a[2, 2]])
    order = np.argsort(-np.abs(w))
    return w[order], V[:, order]


@njit
def _cost(
    h1: np.ndarray, dh: np.ndarray, xy: np.ndarray, mask: np.ndarray, x: np.ndarray, h: np.ndarray
) -> float:
    """Fill ``h`` (K, 3) at the parameters ``x``; return the squared reprojection error (masked views 0)."""
    cost = 0.0
    for k in range(h.shape[0]):
        for i in range(3):
            h[k, i] = h1[k, i] + dh[k, i, 0] * x[0] + dh[k, i, 1] * x[1] + dh[k, i, 2] * x[2]
        if mask[k]:
            hz = h[k, 2] if abs(h[k, 2]) >= 1e-12 else 1e-12
            for a in range(2):
                e = h[k, a] / hz - xy[k, a]
                cost += e * e
    return cost


@njit
def triangulate_kernel(
    R_WC: np.ndarray,
    p_WC: np.ndarray,
    xy_norm: np.ndarray,
    mask: np.ndarray,
    max_iterations: int,
    step_tolerance: float,
    initial_damping: float,
    focal_px: float,
    limits: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate F features seen in (subsets of) K views (the loops of ``triangulate``).

    Args:
        R_WC: Camera orientations, shape (K, 3, 3).
        p_WC: Camera positions (m) in W, shape (K, 3).
        xy_norm: Undistorted normalized observations, shape (F, K, 2).
        mask: Which view saw which feature, shape (F, K) bool.
        max_iterations: Most Levenberg-Marquardt iterations.
        step_tolerance: Relative step below which (for every feature) the iterations stop.
        initial_damping: Initial LM damping (relative to the diagonal).
        focal_px: Focal length (px) of the reprojection error in pixels.
        limits: ``[min_depth_m, max_depth_m, max_depth_baseline_ratio, max_condition_number,
            max_reprojection_error_px]``, shape (5,).

    Returns:
        ``(p_W (F, 3), valid (F,), rms_error_px (F,), condition_number (F,))`` as ``TriangulationResult``.
    """
    F, K = mask.shape
    x = np.zeros((F, 3))
    cond = np.zeros(F)
    cost = np.zeros(F)
    lam = np.full(F, initial_damping)
    anchor = np.zeros(F, np.int64)
    h1 = np.zeros((F, K, 3))
    dh = np.zeros((F, K, 3, 3))  # dh[f, k, i, j] = d h_i / d x_j
    h = np.zeros((F, K, 3))
    p_AC = np.zeros((F, K, 3))
    R_AC = np.zeros((3, 3))
    for f in range(F):
        a = 0
        while a < K - 1 and not mask[f, a]:
            a += 1
        if not mask[f, a]:
            a = 0  # no view: argmax of an all-False row
        anchor[f] = a
        A = np.zeros((3, 3))
        rhs = np.zeros(3)
        for k in range(K):
            for i in range(3):
                for c in range(3):
                    R_AC[i, c] = (
                        R_WC[a, 0, i] * R_WC[k, 0, c]
                        + R_WC[a, 1, i] * R_WC[k, 1, c]
                        + R_WC[a, 2, i] * R_WC[k, 2, c]
                    )
                p_AC[f, k, i] = (
                    R_WC[a, 0, i] * (p_WC[k, 0] - p_WC[a, 0])
                    + R_WC[a, 1, i] * (p_WC[k, 1] - p_WC[a, 1])
                    + R_WC[a, 2, i] * (p_WC[k, 2] - p_WC[a, 2])
                )
            # h = R_CA ([alpha, beta, 1] - rho p_AC): h_1 = R_CA e_z, dh/dx = [R_CA e_x, R_CA e_y, -R_CA p_AC]
            for i in range(3):
                h1[f, k, i] = R_AC[2, i]
                dh[f, k, i, 0] = R_AC[0, i]
                dh[f, k, i, 1] = R_AC[1, i]
                dh[f, k, i, 2] = -(
                    R_AC[0, i] * p_AC[f, k, 0] + R_AC[1, i] * p_AC[f, k, 1] + R_AC[2, i] * p_AC[f, k, 2]
                )
            if not mask[f, k]:
                continue
            b = np.zeros(3)
            for i in range(3):
                b[i] = R_AC[i, 0] * xy_norm[f, k, 0] + R_AC[i, 1] * xy_norm[f, k, 1] + R_AC[i, 2]
            nb = np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
            for i in range(3):
                b[i] /= nb
            for i in range(3):
                s = 0.0
                for c in range(3):
                    proj = (1.0 if i == c else 0.0) - b[i] * b[c]
                    A[i, c] += proj
                    s += proj * p_AC[f, k, c]
                rhs[i] += s
        # Pseudo-inverse solve V S^+ U^T rhs with the SVD of the symmetric A = its eigendecomposition.
        w_eig, V_eig = _eig_sym3(A)
        S0, S2 = abs(w_eig[0]), abs(w_eig[2])
        cond[f] = S0 / max(S2, 1e-300)
        uty = np.zeros(3)
        for j in range(3):
            if abs(w_eig[j]) > S0 * 1e-12:
                proj_j = V_eig[0, j] * rhs[0] + V_eig[1, j] * rhs[1] + V_eig[2, j] * rhs[2]
                uty[j] = proj_j / np.copysign(max(abs(w_eig[j]), 1e-300), w_eig[j])
        p_A = np.zeros(3)
        for i in range(3):
            p_A[i] = V_eig[i, 0] * uty[0] + V_eig[i, 1] * uty[1] + V_eig[i, 2] * uty[2]
        z0 = p_A[2] if p_A[2] > 1e-6 else 1.0
        x[f, 0], x[f, 1], x[f, 2] = p_A[0] / z0, p_A[1] / z0, 1.0 / z0
        cost[f] = _cost(h1[f], dh[f], xy_norm[f], mask[f], x[f], h[f])
    # Levenberg-Marquardt, all features in step (the reference's batched iterations).
    h_new = np.zeros((K, 3))
    x_new = np.zeros(3)
    for _ in range(max_iterations):
        converged = True
        for f in range(F):
            JtJ = np.zeros((3, 3))
            Jte = np.zeros(3)
            for k in range(K):
                if not mask[f, k]:
                    continue
                hz = h[f, k, 2] if abs(h[f, k, 2]) >= 1e-12 else 1e-12
                inv_z = 1.0 / hz
                for a_ in range(2):
                    za = h[f, k, a_] * inv_z * inv_z
                    e = h[f, k, a_] / hz - xy_norm[f, k, a_]
                    J0 = dh[f, k, a_, 0] * inv_z - dh[f, k, 2, 0] * za
                    J1 = dh[f, k, a_, 1] * inv_z - dh[f, k, 2, 1] * za
                    J2 = dh[f, k, a_, 2] * inv_z - dh[f, k, 2, 2] * za
                    JtJ[0, 0] += J0 * J0
                    JtJ[0, 1] += J0 * J1
                    JtJ[0, 2] += J0 * J2
                    JtJ[1, 1] += J1 * J1
                    JtJ[1, 2] += J1 * J2
                    JtJ[2, 2] += J2 * J2
                    Jte[0] += J0 * e
                    Jte[1] += J1 * e
                    Jte[2] += J2 * e
            JtJ[1, 0], JtJ[2, 0], JtJ[2, 1] = JtJ[0, 1], JtJ[0, 2], JtJ[1, 2]
            damp = JtJ.copy()
            for i in range(3):
                damp[i, i] += lam[f] * (JtJ[i, i] + 1e-12)
            dx = _solve3(damp, Jte)
            for i in range(3):
                x_new[i] = x[f, i] - dx[i]
            c_new = _cost(h1[f], dh[f], xy_norm[f], mask[f], x_new, h_new)
            finite = np.isfinite(x_new[0]) and np.isfinite(x_new[1]) and np.isfinite(x_new[2])
            if c_new < cost[f] and finite:
                x[f] = x_new
                h[f] = h_new
                cost[f] = c_new
                lam[f] *= 0.1
            else:
                lam[f] *= 10.0
            step = np.sqrt(dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2])
            size = np.sqrt(x[f, 0] * x[f, 0] + x[f, 1] * x[f, 1] + x[f, 2] * x[f, 2])
            if not step <= step_tolerance * size:
                converged = False
        if converged:
            break
    # Back to W and the checks.
    p_W = np.zeros((F, 3))
    valid = np.zeros(F, np.bool_)
    rms_px = np.zeros(F)
    for f in range(F):
        a = anchor[f]
        rho = x[f, 2]
        rho_safe = rho if abs(rho) >= 1e-12 else 1e-12
        p_A0, p_A1, p_A2 = x[f, 0] / rho_safe, x[f, 1] / rho_safe, 1.0 / rho_safe
        finite = True
        for i in range(3):
            p_W[f, i] = R_WC[a, i, 0] * p_A0 + R_WC[a, i, 1] * p_A1 + R_WC[a, i, 2] * p_A2 + p_WC[a, i]
            if not np.isfinite(p_W[f, i]):
                finite = False
                p_W[f, i] = 0.0
        n_views = 0
        min_depth = np.inf
        baseline = 0.0
        for k in range(K):
            if mask[f, k]:
                n_views += 1
                min_depth = min(min_depth, h[f, k, 2] / rho_safe)
                nrm = np.sqrt(p_AC[f, k, 0] ** 2 + p_AC[f, k, 1] ** 2 + p_AC[f, k, 2] ** 2)
                baseline = max(baseline, nrm)
        depth_anchor = 1.0 / rho_safe
        rms_px[f] = np.sqrt(cost[f] / max(float(n_views), 1.0)) * focal_px
        valid[f] = (
            n_views >= 2
            and rho > 0.0
            and cond[f] < limits[3]
            and min_depth > limits[0]
            and depth_anchor < limits[1]
            and depth_anchor < limits[2] * baseline
            and rms_px[f] < limits[4]
            and finite
        )
    return p_W, valid, rms_px, cond
