"""The MSCKF feature update (Mourikis and Roumeliotis, ICRA 2007, sec. III-D/E; open_vins ``UpdaterMSCKF``).

For every feature whose track ended (or that is about to lose its oldest clone): triangulate it from all its
views, stack the reprojection residuals of every view, project the feature out with the left null space of
its Jacobian, gate each feature with a chi-square test, compress and update.

A view is a (clone, camera) pair. On a stereo rig cam1's views come after cam0's (view ``K + k`` is cam1 at
clone ``k``), each with its own extrinsics ``(R_BCi, p_BCi)``::

    p_Ci = R_BCi^T (R_WB_k^T (p_f_W - p_WB_k) - p_BCi),    z = p_Ci[:2] / p_Ci[2]

so the pose Jacobian of a cam1 row lands in the same clone block as cam0's. Rows are whitened to cam0's
normalized noise (cam1 rows times ``f1 / f0``) so the isotropic noise model holds. When the filter estimates
the cam0 extrinsic, cam1's extrinsic is held at its calibration (its rows have no extrinsic column).

KLT errors are not white: a track slides over the texture, so its error is a random walk on top of white
noise. Measured on the renders against the exact projection of each track's first 3-D point
(``benchmarks/klt_track_error.py``), the walk's variance grows with the image motion of the feature
(0.015-0.03 px^2 per px moved on the figure-8s) while the white part is ~0.1 px. With the KLT front end each
feature's views are whitened with that covariance (:func:`viotb.vio.update_helpers.random_walk_whitener`,
clock :func:`viotb.vio.update_helpers.track_path_px`) before the null-space projection, which makes the
update the generalized-least-squares one; the simulated front end's white noise is left as it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.feature_database import FeatureDatabase
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.state import EXTRINSIC_BLOCK, State, ekf_update
from viotb.vio.triangulation import triangulate
from viotb.vio.update_helpers import (
    Chi2Table,
    FeatureJacobian,
    clone_unobservable_basis,
    feature_jacobian,
    gram_compress,
    measurement_compress,
    nullspace_project,
    observability_projector,
    random_walk_whitener,
    track_path_px,
)


@dataclass(frozen=True)
class UpdateStats:
    """Bookkeeping of one MSCKF update.

    Attributes:
        candidates: Features considered.
        triangulated: Features that triangulated.
        used: Features that passed the gate and entered the update.
        rejected: Features rejected by the chi-square gate.
        rows: Measurement rows after null-space projection (before compression).
        inconsistent: Features whose views admit no common point (triangulation reprojection error above
            its gate), a divergence symptom when they dominate.
        nis_per_dof: Mean over the features that passed the gate of ``chi2 / dof`` (normalized innovation
            squared per degree of freedom; ~1 when consistent), NaN when none passed.
        nis_per_dof_all: The same mean over every triangulated candidate (rejected ones included).
    """

    candidates: int = 0
    triangulated: int = 0
    used: int = 0
    rejected: int = 0
    rows: int = 0
    inconsistent: int = 0
    nis_per_dof: float = float("nan")
    nis_per_dof_all: float = float("nan")


def right_row_weight(p: MsckfParams, focal_px: float, focal_right_px: float | None) -> float:
    """Weight of cam1's residual rows that whitens them to cam0's normalized white sigma.

    ``(f1 / f0) (sigma_0 / sigma_1)``: cam1's pixels are ``f1 / f0`` times finer, and its observations
    (found from cam0's every frame, :mod:`viotb.vio.frontend_stereo`) carry cam0's error plus the
    left-right match's, ``sigma_1 = p.right_pixel_sigma_px`` (None: ``p.pixel_sigma_px``).
    """
    ratio = 1.0 if focal_right_px is None else focal_right_px / focal_px
    if p.right_pixel_sigma_px is not None:
        ratio *= p.pixel_sigma_px / p.right_pixel_sigma_px
    return ratio


def track_random_walk_px2_per_px(p: MsckfParams) -> float:
    """Random-walk variance (px^2 per px of image motion) of the front end's tracks: KLT's, else 0."""
    return p.klt.track_random_walk_px2_per_px if p.frontend == "klt" else 0.0


def _stacked_jacobian(
    R_WB: np.ndarray,
    p_WB: np.ndarray,
    st: State,
    calib_right: CameraCalibration | None,
    p_f: np.ndarray,
    extrinsic: bool = True,
) -> FeatureJacobian:
    """Predictions and Jacobians of all views (cam0's K, then cam1's K), leading shape (F, C K).

    Args:
        R_WB: Clone orientations, shape (K, 3, 3).
        p_WB: Clone positions (m) in W, shape (K, 3).
        st: The state (cam0 extrinsic ``st.R_BC``, ``st.p_BC``).
        calib_right: Cam1 calibration, or None for a mono rig.
        p_f: Feature positions (m) in W, shape (F, 3).
        extrinsic: Also the extrinsic Jacobian (False: ``H_extrinsic`` None, the extrinsic is not estimated).
    """
    jac0 = feature_jacobian(R_WB[None], p_WB[None], st.R_BC, st.p_BC, p_f[:, None, :], extrinsic)
    if calib_right is None:
        return jac0
    R_BC1 = np.asarray(calib_right.R_BC, dtype=float)
    p_BC1 = np.asarray(calib_right.p_BC, dtype=float)
    jac1 = feature_jacobian(R_WB[None], p_WB[None], R_BC1, p_BC1, p_f[:, None, :], False)
    H_ext = None
    if extrinsic:
        H_ext = np.concatenate([jac0.H_extrinsic, np.zeros_like(jac0.H_extrinsic)], axis=1)
    return FeatureJacobian(
        np.concatenate([jac0.z_norm, jac1.z_norm], axis=1),
        np.concatenate([jac0.depth_m, jac1.depth_m], axis=1),
        np.concatenate([jac0.H_pose, jac1.H_pose], axis=1),
        H_ext,
        np.concatenate([jac0.H_feature, jac1.H_feature], axis=1),
    )


def window_observations(
    db: FeatureDatabase, ids: np.ndarray, times: np.ndarray, stereo: bool
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Observations of ``ids`` at the clone ``times``: cam0's K views, then cam1's K on a stereo rig.

    Returns:
        ``(xy (F, C K, 2), mask (F, C K), stereo)``; ``stereo`` is False (C = 1) when no cam1 view exists.
    """
    xy, mask = db.observations(ids, times)
    if stereo:
        xy1, mask1 = db.observations(ids, times, cam=1)
        stereo = bool(mask1.any())  # without cam1 views this is exactly the mono update
        if stereo:
            xy, mask = np.concatenate([xy, xy1], axis=1), np.concatenate([mask, mask1], axis=1)
    return xy, mask, stereo


def view_poses(st: State, calib_right: CameraCalibration | None) -> tuple[np.ndarray, np.ndarray]:
    """Camera poses of every view at the current clone estimates: ``(R_WC (C K, 3, 3), p_WC (C K, 3))``."""
    clones = list(st.clones.values())
    R_WB = np.stack([c.R_WB for c in clones])
    p_WB = np.stack([c.p_WB for c in clones])
    R_WC = R_WB @ st.R_BC
    p_WC = p_WB + R_WB @ st.p_BC
    if calib_right is not None:
        R_WC = np.concatenate([R_WC, R_WB @ calib_right.R_BC])
        p_WC = np.concatenate([p_WC, p_WB + R_WB @ np.asarray(calib_right.p_BC, dtype=float)])
    return R_WC, p_WC


def feature_system(
    st: State,
    xy: np.ndarray,
    mask: np.ndarray,
    p_f: np.ndarray,
    p: MsckfParams,
    focal_px: float,
    calib_right: CameraCalibration | None,
    focal_right_px: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals and Jacobians of features seen in the clone window (before any projection).

    Args:
        st: The state (its clones are the K views of each camera).
        xy: Observed normalized coordinates, shape (F, C K, 2) (:func:`window_observations`).
        mask: Valid views, shape (F, C K).
        p_f: Feature positions (m) in W, shape (F, 3), the linearization point.
        p: Settings (``update_linearization``, ``pixel_sigma_px``, the front end's track noise).
        focal_px: Cam0 focal length (px).
        calib_right: Cam1 calibration when the views include cam1's (C = 2), else None.
        focal_right_px: Cam1 focal length (px).

    Returns:
        ``(r (F, 2 C K), H_x (F, 2 C K, n_c), H_f (F, 2 C K, 3), cols (n_c,), clone_offsets (K,))``: rows
        whitened to cam0's normalized white sigma ``p.pixel_sigma_px / focal_px``, masked views zero;
        ``cols`` are the error-state columns of ``H_x`` (clone k at 6 k, then the extrinsic if estimated).
    """
    clones = list(st.clones.values())
    R_WB = np.stack([c.R_WB for c in clones])
    p_WB = np.stack([c.p_WB for c in clones])
    K = len(clones)
    stereo = calib_right is not None
    F, V = mask.shape
    right = calib_right
    has_ext = st.has_block(EXTRINSIC_BLOCK)
    # 3. Residuals at the current estimates; Jacobians where ``update_linearization`` says.
    fej = p.use_fej and p.update_linearization == "first_estimates"
    cur = _stacked_jacobian(R_WB, p_WB, st, right, p_f, has_ext and not fej)
    if fej:
        R_fej = np.stack([c.R_WB_fej for c in clones])
        p_fej = np.stack([c.p_WB_fej for c in clones])
        jac = _stacked_jacobian(R_fej, p_fej, st, right, p_f, has_ext)
    else:
        jac = cur
    w = mask[..., None].astype(float)
    if stereo:
        w[:, K:] *= right_row_weight(p, focal_px, focal_right_px)  # whiten cam1 rows to cam0's sigma
    r = ((xy - cur.z_norm) * w).reshape(F, 2 * V)
    H_f = (jac.H_feature * w[..., None]).reshape(F, 2 * V, 3)
    # The rows touch only the clone blocks and the extrinsic: steps 3-6 work on those columns ``cols``
    # of the error state (clone k at 6 k, then the extrinsic), the others are exactly zero.
    cols, clone_offsets = _update_columns(st)
    n_c = len(cols)
    H_x = np.zeros((F, V, 2, n_c))
    H_pose = jac.H_pose * w[..., None]
    for k in range(K):
        H_x[:, k::K, :, 6 * k : 6 * k + 6] = H_pose[:, k::K]  # this clone's view in every camera
    if has_ext:
        H_x[..., 6 * K :] = jac.H_extrinsic * w[..., None]
    H_x = H_x.reshape(F, 2 * V, n_c)
    q_px = track_random_walk_px2_per_px(p)
    if q_px > 0.0:
        # 3b. Correlated track noise (white + a random walk per pixel of image motion): whiten each
        #     feature's views to the white sigma before the projection, the generalized-least-squares update.
        focal_v = np.where(np.arange(V) < K, focal_px, focal_right_px or focal_px)
        W = random_walk_whitener(
            track_path_px(xy, mask, focal_v, K), mask, np.arange(V) // K, q_px / p.pixel_sigma_px**2
        )
        r = (W @ r.reshape(F, V, 2)).reshape(F, 2 * V)  # rows are (view, axis): W acts on the views
        H_f = (W @ H_f.reshape(F, V, 6)).reshape(F, 2 * V, 3)
        H_x = (W @ H_x.reshape(F, V, 2 * n_c)).reshape(F, 2 * V, n_c)
    return r, H_x, H_f, cols, clone_offsets


def _update_columns(st: State) -> tuple[np.ndarray, np.ndarray]:
    """The error-state columns an update touches and the clone blocks' offsets.

    Returns:
        ``(cols, clone_offsets (K,))``: clone k at 6 k, then the extrinsic if estimated.
    """
    clone_offsets = np.array([st.clone_block(float(t)).offset for t in st.clones])
    cols = (clone_offsets[:, None] + np.arange(6)).ravel()
    if st.has_block(EXTRINSIC_BLOCK):
        cols = np.concatenate([cols, st.block(EXTRINSIC_BLOCK).offset + np.arange(6)])
    return cols, clone_offsets


def _projected_rows_numba(
    st: State,
    xy: np.ndarray,
    mask: np.ndarray,
    p_f: np.ndarray,
    p: MsckfParams,
    focal_px: float,
    calib_right: CameraCalibration | None,
    focal_right_px: float | None,
    P_cc: np.ndarray,
    chi2_max: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps 3-5 by :func:`viotb.vio.msckf_kernels.feature_gate_kernel` (arguments as :func:`feature_system`).

    Returns:
        ``(chi2 (F,), dof (F,), passed (F,), gram (n_c, n_c), h_r (n_c,))``: the gate and the normal
        equations of the passed features' null-space rows.
    """
    from viotb.vio.msckf_kernels import feature_gate_kernel  # numba: not on the CLI's import path

    clones = list(st.clones.values())
    R_WB = np.stack([c.R_WB for c in clones])
    p_WB = np.stack([c.p_WB for c in clones])
    if p.use_fej and p.update_linearization == "first_estimates":
        R_jac, p_jac = np.stack([c.R_WB_fej for c in clones]), np.stack([c.p_WB_fej for c in clones])
    else:
        R_jac, p_jac = R_WB, p_WB
    K = len(clones)
    R_BC = [np.asarray(st.R_BC, dtype=float)]
    p_BC = [np.asarray(st.p_BC, dtype=float)]
    w_right = 1.0
    if calib_right is not None:
        R_BC.append(np.asarray(calib_right.R_BC, dtype=float))
        p_BC.append(np.asarray(calib_right.p_BC, dtype=float))
        w_right = right_row_weight(p, focal_px, focal_right_px)
    V = mask.shape[1]
    focal_v = np.where(np.arange(V) < K, focal_px, focal_right_px or focal_px).astype(float)
    return feature_gate_kernel(
        np.ascontiguousarray(xy, dtype=float),
        np.ascontiguousarray(mask, dtype=bool),
        np.ascontiguousarray(p_f, dtype=float),
        R_WB,
        p_WB,
        np.ascontiguousarray(R_jac),
        np.ascontiguousarray(p_jac),
        np.stack(R_BC),
        np.stack(p_BC),
        st.has_block(EXTRINSIC_BLOCK),
        float(w_right),
        track_random_walk_px2_per_px(p) / p.pixel_sigma_px**2,
        focal_v,
        np.ascontiguousarray(P_cc),
        (p.pixel_sigma_px / focal_px) ** 2,
        chi2_max,
    )


def msckf_update(
    st: State,
    db: FeatureDatabase,
    p: MsckfParams,
    chi2_table: Chi2Table,
    t_now: float,
    focal_px: float,
    calib_right: CameraCalibration | None = None,
    focal_right_px: float | None = None,
    use_oldest: bool = False,
) -> UpdateStats:
    """Update ``st`` with the features that leave the window at ``t_now`` (they leave ``db`` too).

    Args:
        st: The filter state (updated in place).
        db: Feature database (one layer per camera).
        p: Settings.
        chi2_table: 95 % chi-square quantiles.
        t_now: Time (s, camera clock) of the newest clone.
        focal_px: Cam0 focal length (px); ``p.pixel_sigma_px / focal_px`` is the normalized noise sigma.
        calib_right: Cam1 calibration for a stereo rig (None: mono, cam1 layer ignored).
        focal_right_px: Cam1 focal length (px) (default ``focal_px``).
        use_oldest: Also use the features seen in the oldest clone although the window is not full
            (``MsckfParams.max_update_gap_s``: the filter has gone too long without an update).

    Returns:
        What the update did.
    """
    stereo = calib_right is not None and db.num_cameras == 2
    # 0. Features whose tracks ended, plus those seen in the oldest clone when it is about to go.
    lost = db.features_lost(t_now)
    cand = lost
    times = st.clone_times
    if len(st.clones) > p.max_clones or (use_oldest and len(st.clones) >= p.min_track_length):
        cand = np.union1d(lost, db.features_seen_at(float(times[0])))
    if len(cand) == 0:
        return UpdateStats()
    # 1. Clean: observations at clone times only (the database is keyed by clone time) and tracks
    #    long enough (views of every camera count); the other lost features can never be used.
    lengths = db.track_lengths(cand)
    usable = lengths >= p.min_track_length
    db.remove_features(lost[~np.isin(lost, cand[usable])])
    cand, lengths = cand[usable], lengths[usable]
    if len(cand) == 0:
        return UpdateStats()
    order = np.argsort(-lengths, kind="stable")[: p.max_features_per_update]
    cand = cand[order]
    xy, mask, stereo = window_observations(db, cand, times, stereo)
    db.remove_features(cand)
    # 2. Triangulate every feature from all its views in the current clone estimates.
    R_WC, p_WC = view_poses(st, calib_right if stereo else None)
    tri = triangulate(R_WC, p_WC, xy, mask, p.triangulation, focal_px, p.update_kernels)
    ok = tri.valid
    n_cand = len(cand)
    n_bad = int(np.sum(tri.rms_error_px >= p.triangulation.max_reprojection_error_px))
    if not np.any(ok):
        return UpdateStats(candidates=n_cand, inconsistent=n_bad)
    xy, mask, p_f = xy[ok], mask[ok], tri.p_W[ok]
    F, V = mask.shape
    clones = list(st.clones.values())
    # The rows touch only the clone blocks and the extrinsic: steps 3-6 work on those columns ``cols``.
    cols, clone_offsets = _update_columns(st)
    n_c = len(cols)
    P_cc = st.cov[np.ix_(cols, cols)]
    Pi = None
    if p.use_fej and p.update_linearization == "current_oc":
        # 4b. Observability constraint: no information on global position/yaw at the first estimates,
        #     the directions the FEJ propagation keeps unobservable (Hesch et al. TRO 2014, OC-EKF). The
        #     constrained rows are ``H_o Pi``; steps 5 and 6 apply ``Pi`` to n_c x n_c matrices instead.
        R_fej = np.stack([c.R_WB_fej for c in clones])
        p_fej = np.stack([c.p_WB_fej for c in clones])
        U = clone_unobservable_basis(R_fej, p_fej, clone_offsets, st.dim)
        Pi = observability_projector(U[cols])  # U is zero off the clone blocks
        P_cc = Pi @ P_cc @ Pi
    sigma2 = (p.pixel_sigma_px / focal_px) ** 2
    right = calib_right if stereo else None
    if p.update_kernels == "numba":
        # 3-5 compiled, one call: residuals, Jacobians, whitening, null space and gate per feature.
        chi2_max = p.chi2_multiplier * chi2_table(np.arange(2 * V - 2))
        chi2, dof, passed, gram, h_r = _projected_rows_numba(
            st, xy, mask, p_f, p, focal_px, right, focal_right_px, P_cc, chi2_max
        )
    else:
        # 3. Residuals and Jacobians of every view (whitened), on the columns ``cols`` they touch.
        r, H_x, H_f, cols, clone_offsets = feature_system(
            st, xy, mask, p_f, p, focal_px, right, focal_right_px
        )
        # 4. Null-space projection removes the feature (padded rows are zero and drop out exactly).
        H_o, r_o = nullspace_project(H_x, H_f, r)
        # 5. Chi-square gate at 95 % per feature with dof = 2 m - 3 (m views over all cameras).
        HP = (H_o.reshape(-1, n_c) @ P_cc).reshape(H_o.shape)
        S = HP @ np.swapaxes(H_o, 1, 2)
        S[:, np.arange(S.shape[1]), np.arange(S.shape[1])] += sigma2
        chi2 = np.einsum("fi,fi->f", r_o, np.linalg.solve(S, r_o[..., None])[..., 0])
        dof = 2 * mask.sum(axis=1) - 3
        passed = chi2 < p.chi2_multiplier * chi2_table(dof)
    n_pass = int(passed.sum())
    nis = chi2 / dof
    stats = UpdateStats(
        n_cand,
        F,
        n_pass,
        int(F - n_pass),
        int(dof[passed].sum()),
        n_bad,
        float(np.mean(nis[passed])) if n_pass else float("nan"),
        float(np.mean(nis)),
    )
    if n_pass == 0:
        return stats
    # 6. Stack, compress (QR) and update.
    if p.update_kernels == "numba":
        # The kernel summed the passed features' normal equations: factor them (measurement_compress).
        H_c, r_c = gram_compress(gram, h_r, Pi)
    else:
        if n_pass == F:
            H_all, r_all = H_o.reshape(-1, n_c), r_o.reshape(-1)
        else:
            H_all, r_all = H_o[passed].reshape(-1, n_c), r_o[passed].reshape(-1)
        H_c, r_c = measurement_compress(H_all, r_all, Pi)
    if len(H_c) == 0:  # no direction carries information (all-zero rows): nothing to update
        return stats
    H_full = np.zeros((len(H_c), st.dim))
    H_full[:, cols] = H_c
    ekf_update(st, H_full, r_c, sigma2)
    # 7. Marginalizing the oldest clone is done by the caller after this update.
    return stats
