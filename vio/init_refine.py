"""Levenberg-Marquardt refinement of the dynamic initialization (step 6 of :mod:`viotb.vio.init_dynamic`).

Normalized reprojection errors over ``z = [v0 (3), dg (2), bg (3), ba (3)]`` and the feature positions,
the frame poses predicted from the zero-bias preintegration with the bias Jacobians (Forster et al. TRO
2017, eq. 44), the features eliminated by the Schur complement as in any bundle adjustment.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.lie import exp_so3
from viotb.vio.types import GRAVITY_M_S2

N_GLOBAL = 11
"""Global unknowns of the refinement: ``[v0 (3), dg (2), bg (3), ba (3)]``."""


def globals_of(z: np.ndarray, R_g: np.ndarray):
    """Unpack ``z = [v0, dg, bg, ba]``, ``g = 9.81 normalize(R_g [dg, 1])``."""
    u = R_g @ np.array([z[3], z[4], 1.0])
    n = float(np.linalg.norm(u))
    g = GRAVITY_M_S2 * u / n
    G = GRAVITY_M_S2 * (np.eye(3) - np.outer(u, u) / n**2) / n @ R_g[:, :2]
    return z[0:3], g, z[5:8], z[8:11], G


def frame_poses(win, v0: np.ndarray, g: np.ndarray, bg: np.ndarray, ba: np.ndarray):
    """Frame rotations ``R_B0Bk`` (K, 3, 3) and positions ``p_k`` in B0 (K, 3) at the biases."""
    R_k = np.stack([win.dR[k] @ exp_so3(win.JR_bg[k] @ bg) for k in range(len(win.dts))])
    t = win.dts[:, None]
    return R_k, v0 * t + 0.5 * g * t * t + win.dp + win.Jp_bg @ bg + win.Jp_ba @ ba


def reprojection(
    win, z_glob: np.ndarray, pf: np.ndarray, R_g: np.ndarray, sigma: float, with_pose: bool = False
):
    """Residuals and Jacobians of every observation, in units of ``sigma``.

    Args:
        win: The window.
        z_glob: ``[v0 (3), dg (2), bg (3), ba (3)]``.
        pf: Feature positions in B0 (m), shape (n_f, 3).
        R_g: Gravity-direction chart (see :func:`_globals`).
        sigma: Normalized image noise.
        with_pose: Also return ``J_pose (n_obs, 2, 6)``, the Jacobian for an error ``[dtheta, dp]`` of the
            observation's frame pose (``R_k Exp(dtheta)``, ``p_k + dp``).

    Returns:
        ``(r (n_obs, 2), J_glob (n_obs, 2, 11), J_feat (n_obs, 2, 3))`` (and ``J_pose``), the first three
        whitened along each track (``win.whiten``), ``J_pose`` per observation, not whitened; the gyro-bias
        Jacobian uses ``Exp(J (bg + d)) ~ Exp(J bg) Exp(J d)`` (Forster eq. 44 to first order).
    """
    v0, g, bg, ba, G = globals_of(z_glob, R_g)
    R_k, p_k = frame_poses(win, v0, g, bg, ba)
    of, oj = win.obs_frame, win.obs_feat
    Rk = R_k[of]
    q = pf[oj] - p_k[of] - Rk @ win.p_BC
    u = np.einsum("nji,nj->ni", Rk, q)  # in B_k
    p_C = u @ win.R_BC  # R_BC^T u
    z = np.where(np.abs(p_C[:, 2]) < 1e-6, 1e-6, p_C[:, 2])
    r = (p_C[:, :2] / z[:, None] - win.obs_xy) / sigma
    P = np.zeros((len(z), 2, 3))
    P[:, 0, 0] = P[:, 1, 1] = 1.0 / z
    P[:, :, 2] = -p_C[:, :2] / z[:, None] ** 2
    P /= sigma
    A = P @ win.R_BC.T @ np.transpose(Rk, (0, 2, 1))  # d r / d q, (n, 2, 3)
    t = win.dts[of][:, None, None]
    J_glob = np.zeros((len(z), 2, N_GLOBAL))
    J_glob[:, :, 0:3] = -A * t
    J_glob[:, :, 3:5] = -(A * (0.5 * t * t)) @ G
    skew_u = np.zeros((len(z), 3, 3))
    up = u + win.p_BC
    skew_u[:, 0, 1], skew_u[:, 0, 2], skew_u[:, 1, 2] = -up[:, 2], up[:, 1], -up[:, 0]
    skew_u -= np.transpose(skew_u, (0, 2, 1))
    d_u_d_bg = skew_u @ win.JR_bg[of] - np.transpose(Rk, (0, 2, 1)) @ win.Jp_bg[of]
    J_glob[:, :, 5:8] = P @ win.R_BC.T @ d_u_d_bg
    J_glob[:, :, 8:11] = -A @ win.Jp_ba[of]
    # Correlated track errors: whitened rows (win.whiten is the identity for white errors).
    r_w, J_glob_w, A_w = win.whiten(r), win.whiten(J_glob), win.whiten(A)
    if with_pose:
        return r_w, J_glob_w, A_w, np.concatenate([P @ win.R_BC.T @ skew_u, -A], axis=2)
    return r_w, J_glob_w, A_w


def normal_equations(win, r, J_glob, J_feat, w2: np.ndarray | None = None):
    """``J^T W J`` and ``J^T W r`` by blocks for rows ``[J_glob, J_feat]``, ``W`` per observation.

    Args:
        win: The window (which feature each observation belongs to).
        r: Residuals, shape (n_obs, 2).
        J_glob: Global columns, shape (n_obs, 2, G).
        J_feat: Feature columns, shape (n_obs, 2, 3).
        w2: Weight of each observation's rows, shape (n_obs,) (default: 1).

    Returns:
        ``(H_gg (G, G), H_gf (n_f, G, 3), H_ff (n_f, 3, 3), b_g (G,), b_f (n_f, 3))``.
    """
    JW_glob, JW_feat = J_glob, J_feat
    if w2 is not None:
        JW_glob, JW_feat = J_glob * w2[:, None, None], J_feat * w2[:, None, None]
    H_gg = np.einsum("nki,nkj->ij", JW_glob, J_glob)
    b_g = np.einsum("nki,nk->i", JW_glob, r)
    # The observations are grouped by feature (``_Window``): sums over each group.
    starts = win.feat_starts
    H_gf = np.add.reduceat(np.einsum("nki,nkj->nij", JW_glob, J_feat), starts, axis=0)
    H_ff = np.add.reduceat(np.einsum("nki,nkj->nij", JW_feat, J_feat), starts, axis=0)
    b_f = np.add.reduceat(np.einsum("nki,nk->ni", JW_feat, r), starts, axis=0)
    return H_gg, H_gf, H_ff, b_g, b_f


def schur_step(H_gg, H_gf, H_ff, b_g, b_f, lam: float):
    """Damped Schur step: ``(S (G, G) undamped-reduced, d_glob (G,), d_feat (n_f, 3))``."""
    H_ff_d = H_ff + lam * np.einsum("nii->ni", H_ff)[:, :, None] * np.eye(3) + 1e-12 * np.eye(3)
    H_ff_inv = np.linalg.inv(H_ff_d)
    W = H_gf @ H_ff_inv  # (n_f, 8, 3)
    S = H_gg - np.einsum("nij,nkj->ik", W, H_gf)
    rhs = b_g - np.einsum("nij,nj->i", W, b_f)
    S_d = S + lam * np.diag(np.diag(H_gg))
    d_glob = -np.linalg.solve(S_d, rhs)
    d_feat = -np.einsum("nij,nj->ni", H_ff_inv, b_f + np.einsum("nij,i->nj", H_gf, d_glob))
    return S, d_glob, d_feat


def refine(win, R_g, z_glob, pf, sigma: float, prior: np.ndarray, max_iter: int):
    """Levenberg-Marquardt over ``(z_glob, pf)``, a zero-mean prior of information ``diag(prior)`` on z_glob.

    Returns:
        ``(z_glob, pf, S, rms)``: ``S`` the reduced information of the reprojection errors alone at the
        solution (units of ``sigma``), ``rms`` the reprojection RMS in normalized coordinates.
    """

    def damped_system(r, Jg, Jf, z):
        H_gg, H_gf, H_ff, b_g, b_f = normal_equations(win, r, Jg, Jf)
        return H_gg + np.diag(prior), H_gf, H_ff, b_g + prior * z, b_f

    lam = 1e-3
    r, Jg, Jf = reprojection(win, z_glob, pf, R_g, sigma)
    cost = float(np.sum(r**2) + prior @ z_glob**2)
    for _ in range(max_iter):
        try:
            _, d_glob, d_feat = schur_step(*damped_system(r, Jg, Jf, z_glob), lam)
        except np.linalg.LinAlgError:
            break
        z_new, pf_new = z_glob + d_glob, pf + d_feat
        r_new, Jg_new, Jf_new = reprojection(win, z_new, pf_new, R_g, sigma)
        cost_new = float(np.sum(r_new**2) + prior @ z_new**2)
        if np.isfinite(cost_new) and cost_new < cost:
            done = cost - cost_new < 1e-6 * cost
            z_glob, pf, r, Jg, Jf, cost = z_new, pf_new, r_new, Jg_new, Jf_new, cost_new
            lam = max(lam / 10.0, 1e-9)
            if done:
                break
        else:
            lam *= 10.0
            if lam > 1e6:
                break
    try:
        S = schur_step(*normal_equations(win, r, Jg, Jf), 0.0)[0]
    except np.linalg.LinAlgError:
        S = np.zeros((N_GLOBAL, N_GLOBAL))
    rms = float(np.sqrt(np.mean(r**2))) * sigma
    return z_glob, pf, S, rms
