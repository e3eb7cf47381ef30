"""Linear-algebra kernels of the MSCKF update (open_vins ``UpdaterHelper``), batched over features.

Measurement of feature ``f`` in the clone ``(R_WB, p_WB)`` with camera extrinsic ``(R_BC, p_BC)``, in
undistorted normalized coordinates::

    p_B = R_WB^T (p_f_W - p_WB),    p_C = R_BC^T (p_B - p_BC),    z = p_C[:2] / p_C[2]

With right perturbations ``R_WB = R_hat Exp(dtheta)``, ``R_BC = R_hat Exp(dphi)`` the Jacobians are
``dz/dp_C = 1/Z [[1, 0, -x], [0, 1, -y]]`` times::

    dp_C/dtheta = R_BC^T [p_B]x        dp_C/dp_WB = -R_BC^T R_WB^T      dp_C/dp_f = R_BC^T R_WB^T
    dp_C/dphi   = [p_C]x               dp_C/dp_BC = -R_BC^T

The time offset enters through the clone covariance (see :func:`viotb.vio.state.augment_clone`), as in
open_vins, so the feature Jacobian has no direct time-offset column.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.stats
from viotb.vio.lie import skew_batch


@dataclass(frozen=True)
class FeatureJacobian:
    """Predicted measurements and Jacobians for a batch of (feature, clone) pairs (leading shape ``S``).

    Attributes:
        z_norm: Predicted undistorted normalized coordinates, shape S + (2,).
        depth_m: Depth ``p_C[2]`` (m), shape S.
        H_pose: Jacobian w.r.t. the clone error ``[dtheta, dp]``, shape S + (2, 6).
        H_extrinsic: Jacobian w.r.t. the extrinsic error ``[dphi_BC, dp_BC]``, shape S + (2, 6), or None
            when not asked for.
        H_feature: Jacobian w.r.t. ``p_f_W``, shape S + (2, 3).
    """

    z_norm: np.ndarray
    depth_m: np.ndarray
    H_pose: np.ndarray
    H_extrinsic: np.ndarray | None
    H_feature: np.ndarray


def feature_jacobian(
    R_WB: np.ndarray,
    p_WB: np.ndarray,
    R_BC: np.ndarray,
    p_BC: np.ndarray,
    p_f_W: np.ndarray,
    extrinsic: bool = True,
) -> FeatureJacobian:
    """Measurement prediction and Jacobians (open_vins ``get_feature_jacobian_full``, global-3D feature).

    All inputs broadcast against each other over leading dimensions.

    Args:
        R_WB: Clone orientations, shape (..., 3, 3).
        p_WB: Clone positions (m), shape (..., 3).
        R_BC: Camera-to-body rotation, shape (..., 3, 3).
        p_BC: Camera origin in B (m), shape (..., 3).
        p_f_W: Feature positions (m) in W, shape (..., 3).
        extrinsic: Also the extrinsic Jacobian (False: ``H_extrinsic`` is None, for a fixed extrinsic).

    Returns:
        The predictions and Jacobians.
    """
    R_BW = np.swapaxes(R_WB, -1, -2)
    R_CB = np.swapaxes(R_BC, -1, -2)
    p_B = np.einsum("...ij,...j->...i", R_BW, p_f_W - p_WB)
    p_C = np.einsum("...ij,...j->...i", R_CB, p_B - p_BC)
    Z = p_C[..., 2]
    Z_safe = np.where(np.abs(Z) < 1e-12, 1e-12, Z)
    z = p_C[..., :2] / Z_safe[..., None]
    dz_dpc = np.zeros(z.shape[:-1] + (2, 3))
    inv_z = 1.0 / Z_safe
    dz_dpc[..., 0, 0] = inv_z
    dz_dpc[..., 1, 1] = inv_z
    dz_dpc[..., 0, 2] = -z[..., 0] * inv_z
    dz_dpc[..., 1, 2] = -z[..., 1] * inv_z
    dz_dpb = dz_dpc @ R_CB
    H_f = dz_dpb @ R_BW
    H_pose = np.concatenate([dz_dpb @ skew_batch(p_B), -H_f], axis=-1)
    H_ext = None
    if extrinsic:
        H_ext = np.concatenate([dz_dpc @ skew_batch(p_C), -np.broadcast_to(dz_dpb, dz_dpc.shape)], axis=-1)
    return FeatureJacobian(z, Z, H_pose, H_ext, H_f)


def nullspace_project(H_x: np.ndarray, H_f: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project out the feature: left-multiply by the left null space of ``H_f`` (batched).

    With the complete QR ``H_f = [Q1 Q2] [R1; 0]`` (Householder, Golub and Van Loan, "Matrix Computations",
    Alg. 5.2.1; open_vins uses the equivalent Givens sweep of Alg. 5.2.4), ``Q2^T H_f = 0`` and
    ``Q2^T r = Q2^T H_x dx + Q2^T n`` no longer depends on the feature error (Mourikis and Roumeliotis 2007,
    eq. 23-24). ``Q2`` is orthonormal, so isotropic noise stays isotropic.

    Args:
        H_x: State Jacobian, shape (..., m, n).
        H_f: Feature Jacobian, shape (..., m, 3) of rank 3, m > 3.
        r: Residual, shape (..., m).

    Returns:
        ``(H_o, r_o)`` with shapes (..., m - 3, n) and (..., m - 3).
    """
    if H_f.shape[-2] <= H_f.shape[-1]:
        raise ValueError(f"nullspace_project: H_f has {H_f.shape[-2]} rows, needs more than {H_f.shape[-1]}")
    Q, _ = np.linalg.qr(H_f, mode="complete")
    k = H_f.shape[-1]
    Q2t = np.swapaxes(Q[..., :, k:], -1, -2)
    return Q2t @ H_x, np.einsum("...ij,...j->...i", Q2t, r)


def measurement_compress(
    H: np.ndarray, r: np.ndarray, right: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Compress a tall system to ``(T, r_c)`` with ``T^T T = H^T H`` and ``T^T r_c = H^T r`` (at most n rows).

    Mourikis and Roumeliotis 2007 (eq. 26-27) use the thin QR ``H = Q1 T``, ``r_c = Q1^T r``. An
    isotropic-noise EKF update depends on the system only through ``H^T H`` and ``H^T r``, so any factor of
    the Gram matrix gives the same update. Here ``T`` is the pivoted Cholesky factor of the Gram matrix
    (LAPACK ``dpstrf``, Higham, "Accuracy and Stability of Numerical Algorithms", 2nd ed., sec. 10.3):
    ``P^T H^T H P = R^T R`` with ``R`` upper trapezoidal of the numerical rank ``k`` (the pivoting stops
    once the largest remaining diagonal is below ``1e-12`` of the largest), ``T = R P^T`` and ``r_c`` from
    the triangular solve ``R_k^T r_c = (P^T H^T r)_k``. The Gram product is one BLAS-3 call (``m n^2``
    flops against ``2 m n^2`` for Householder QR, which is also mostly BLAS-2 at these shapes), and the
    factorization is ``n^3 / 3`` (20 us at n = 72, against 400 us for a symmetric eigendecomposition). The
    Gram matrix carries the same absolute round-off as ``T^T T`` of a backward-stable QR (``eps |H|^2``), and
    the directions dropped hold no information at that precision (the unobservable directions that the
    observability constraint removed are exactly such). Systems that are not taller than wide are
    returned as they are.

    With ``right`` (symmetric, n x n) the system compressed is ``(H right, r)``, without forming
    ``H right``: its Gram matrix is ``right H^T H right`` (the observability-constrained rows ``H Pi`` of
    :func:`observability_projector`).

    Args:
        H: shape (m, n).
        r: shape (m,).
        right: Optional symmetric matrix, shape (n, n), applied to ``H`` from the right.

    Returns:
        ``(H_c, r_c)`` with at most n rows.
    """
    m, n = H.shape
    if m <= n:
        return (H, r) if right is None else (H @ right, r)
    return gram_compress(H.T @ H, H.T @ r, right)


def gram_compress(
    gram: np.ndarray, h_r: np.ndarray, right: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`measurement_compress` from the normal equations: ``T^T T = gram`` and ``T^T r_c = h_r``.

    Args:
        gram: ``H^T H``, shape (n, n), symmetric positive semidefinite.
        h_r: ``H^T r``, shape (n,).
        right: Optional symmetric matrix, shape (n, n), applied to ``H`` from the right (the system
            compressed is then ``(H right, r)``: Gram matrix ``right H^T H right``, ``right H^T r``).

    Returns:
        ``(T, r_c)`` with the numerical rank's rows (pivoted Cholesky, as :func:`measurement_compress`).
    """
    if right is not None:
        gram, h_r = right @ gram @ right, right @ h_r
    n = gram.shape[0]
    scale = float(np.max(np.diag(gram))) if n else 0.0
    if not scale > 0.0:
        return np.zeros((0, n)), np.zeros(0)
    R, piv, rank, info = scipy.linalg.lapack.dpstrf(gram, lower=0, tol=1e-12 * scale)
    if info < 0:
        raise ValueError(f"measurement_compress: dpstrf argument {-info} is invalid")
    piv = piv[:n] - 1  # LAPACK's 1-based pivots
    R_k = np.triu(R[:rank])  # the rows below the rank hold the unfactored remainder
    T = np.empty((rank, n))
    T[:, piv] = R_k
    r_c = scipy.linalg.solve_triangular(R_k[:, :rank], h_r[piv][:rank], trans="T", lower=False)
    return T, r_c


class Chi2Table:
    """95 % chi-square quantiles built once (open_vins builds ``chi_squared_table`` in its constructor).

    Args:
        max_dof: Largest degree of freedom needed.
        confidence: Quantile (0.95).
    """

    def __init__(self, max_dof: int = 500, confidence: float = 0.95) -> None:
        """Tabulate ``chi2.ppf(confidence, dof)`` for dof = 0..max_dof (dof 0 maps to 0)."""
        self.confidence = confidence
        self._table = np.concatenate([[0.0], scipy.stats.chi2.ppf(confidence, np.arange(1, max_dof + 1))])

    def __call__(self, dof: np.ndarray | int) -> np.ndarray:
        """Quantile(s) for ``dof`` (ValueError when out of the table)."""
        dof_arr = np.asarray(dof)
        if np.any(dof_arr < 0) or np.any(dof_arr >= len(self._table)):
            raise ValueError(f"Chi2Table: dof {dof} outside 0..{len(self._table) - 1}")
        return self._table[dof_arr]


def clone_unobservable_basis(R_WB: np.ndarray, p_WB: np.ndarray, offsets: np.ndarray, dim: int) -> np.ndarray:
    """The four unobservable directions of VIO (global position, yaw about gravity) on the clone blocks.

    Right perturbations ``R = R_hat Exp(dtheta)``: a global translation ``t`` moves every clone by
    ``dp = t``; a global yaw ``alpha`` about ``e_z`` (world z, gravity) gives ``dtheta_k = alpha R_k^T e_z``
    and ``dp_k = alpha e_z x p_k`` (Hesch, Kottas, Bowman, Roumeliotis, "Consistency analysis and
    improvement of vision-aided inertial navigation", TRO 2014; open_vins ``docs/fej.dox``). Other blocks
    are zero.

    Args:
        R_WB: Clone orientations at which the directions are evaluated, shape (K, 3, 3).
        p_WB: Clone positions (m), shape (K, 3).
        offsets: Error-state offset of each clone's ``[dtheta, dp]`` block, shape (K,).
        dim: Error-state dimension.

    Returns:
        ``U`` of shape (dim, 4): columns x, y, z translation and yaw.
    """
    o = np.asarray(offsets, dtype=int)[:, None] + np.arange(3)  # (K, 3) rows of each dtheta block
    U = np.zeros((dim, 4))
    U[o + 3, np.arange(3)] = 1.0  # dp = t
    U[o, 3] = np.asarray(R_WB)[:, 2, :]  # R_k^T e_z: the last row of R_k
    p = np.asarray(p_WB)
    U[o + 3, 3] = np.stack([-p[:, 1], p[:, 0], np.zeros(len(p))], axis=1)  # e_z x p_k
    return U


def observability_projector(U: np.ndarray) -> np.ndarray:
    """``Pi = I - U (U^T U)^-1 U^T``: the orthogonal projector onto the complement of the directions ``U``.

    ``H Pi`` is :func:`observability_constrain` of ``H`` (Hesch et al. TRO 2014, OC-EKF). ``Pi`` is
    symmetric and idempotent, so ``(H Pi) P (H Pi)^T = H (Pi P Pi) H^T``: the chi-square gate and the
    compressed update (:func:`measurement_compress` with ``right=Pi``) use ``Pi`` on ``n x n`` matrices
    instead of on every row.

    Args:
        U: Unobservable directions, shape (dim, d), full column rank.

    Returns:
        ``Pi``, shape (dim, dim).
    """
    Pi = -U @ np.linalg.solve(U.T @ U, U.T)
    Pi[np.diag_indices_from(Pi)] += 1.0
    return 0.5 * (Pi + Pi.T)


def observability_constrain(H: np.ndarray, U: np.ndarray) -> np.ndarray:
    """Smallest change of ``H`` (Frobenius norm) with ``H U = 0`` (Hesch et al. TRO 2014, OC-EKF).

    ``H* = H - H U (U^T U)^-1 U^T``: the rows keep their information about every direction except the
    unobservable ones ``U``, so an update with ``H*`` can never gain information about them.

    Args:
        H: Jacobians, shape (..., m, dim).
        U: Unobservable directions, shape (dim, d), full column rank.

    Returns:
        ``H*`` with the same shape as ``H``.
    """
    proj = np.linalg.solve(U.T @ U, U.T)  # (d, dim)
    rows = H.reshape(-1, H.shape[-1])  # one matrix product for every leading index
    return (rows - (rows @ U) @ proj).reshape(H.shape)


def random_walk_whitener(
    clock: np.ndarray, mask: np.ndarray, group: np.ndarray, rw_to_white_var: float
) -> np.ndarray:
    """Whitening matrices of tracks whose error is white noise plus a random walk along the track.

    The error of view ``k`` of one feature is ``w_k + sum_{j <= n_k} u_j`` with white ``w`` (variance
    ``s_w^2``) and random-walk steps ``u`` (variance ``s_rw^2`` per clock unit, e.g. per frame tracked), the
    walk restarting at the feature's first view in each camera (``group``): per image axis::

        R_kl = s_w^2 (delta_kl + q min(n_k, n_l) [group_k == group_l]),    q = s_rw^2 / s_w^2,

    with ``n_k`` the clock of view ``k`` minus that of the feature's first valid view in its group. The
    returned ``W = L^-1`` (``R / s_w^2 = L L^T``, Cholesky) makes ``W e`` white with variance ``s_w^2``, so
    whitening a feature's residual and Jacobians before the null-space projection gives the
    generalized-least-squares update (Mourikis and Roumeliotis 2007 assume white noise; for correlated noise
    the projection must follow the whitening). Masked views are decoupled (identity rows and columns), so
    their zero rows stay zero.

    Args:
        clock: Clock of each view (e.g. frame index), shape (F, V).
        mask: Valid views, shape (F, V), bool.
        group: Camera of each view, shape (V,), int.
        rw_to_white_var: ``q = s_rw^2 / s_w^2`` per clock unit (>= 0).

    Returns:
        ``W``, shape (F, V, V), lower triangular.
    """
    if rw_to_white_var < 0.0:
        raise ValueError(f"random_walk_whitener: rw_to_white_var must be >= 0, got {rw_to_white_var}")
    clock = np.asarray(clock, dtype=float)
    m = np.asarray(mask, dtype=bool)
    group = np.asarray(group)
    n = np.zeros_like(clock)
    for g in np.unique(group):
        cols = group == g
        c = np.where(m[:, cols], clock[:, cols], np.inf)
        first = np.min(c, axis=1, keepdims=True)
        n[:, cols] = np.where(m[:, cols], clock[:, cols] - np.where(np.isfinite(first), first, 0.0), 0.0)
    same = (group[:, None] == group[None, :])[None]
    both = m[:, :, None] & m[:, None, :]
    R = rw_to_white_var * np.minimum(n[:, :, None], n[:, None, :]) * (same & both)
    R += np.eye(clock.shape[1])[None]
    L = np.linalg.cholesky(R)
    return np.linalg.inv(L)


def track_path_px(
    xy: np.ndarray, mask: np.ndarray, focal_px: np.ndarray, views_per_camera: int
) -> np.ndarray:
    """Image path (px) each feature has travelled at each view since its first valid view in that camera.

    Views are ordered by time within each camera (``views_per_camera`` consecutive views per camera); the
    path sums the distances between consecutive valid views, so a masked view in between is skipped.

    Args:
        xy: Normalized coordinates, shape (F, V, 2).
        mask: Valid views, shape (F, V), bool.
        focal_px: Focal length (px) of each view's camera, shape (V,).
        views_per_camera: Views of one camera (``V`` is a multiple of it).

    Returns:
        Path length (px), shape (F, V); 0 at masked views and at each first view.
    """
    F, V = mask.shape
    mask = np.asarray(mask, dtype=bool)
    out = np.zeros((F, V))
    rows = np.arange(F)[:, None]
    for c0 in range(0, V, views_per_camera):
        cols = slice(c0, c0 + views_per_camera)
        m = mask[:, cols]
        # Previous valid view of the same camera (-1: none), by a running max of the valid view indices.
        last = np.maximum.accumulate(np.where(m, np.arange(c0, c0 + views_per_camera), -1), axis=1)
        prev = np.concatenate([np.full((F, 1), -1), last[:, :-1]], axis=1)
        step = np.linalg.norm(xy[:, cols] - xy[rows, np.maximum(prev, 0)], axis=2) * focal_px[cols]
        step = np.where(m & (prev >= 0) & np.isfinite(step), step, 0.0)
        out[:, cols] = np.where(m, np.cumsum(step, axis=1), 0.0)
    return out
