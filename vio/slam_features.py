"""SLAM features in the MSCKF: persistent landmarks in the EKF state (hybrid MSCKF/SLAM).

The MSCKF alone uses every feature once and forgets it, so nothing ties the slow yaw/position random walk
to the room. A feature tracked for longer than the clone window is instead kept in the state as a 3-D
point ``p_f`` in W (Mourikis and Roumeliotis, ICRA 2007, sec. I; Li and Mourikis, "Optimization-based
estimator design for vision-aided inertial navigation", RSS 2012 / IJRR 2013: the hybrid MSCKF/SLAM;
open_vins ``UpdaterSLAM`` with ``max_slam``). Lifecycle, with ``MsckfParams.max_slam_features > 0``:

1. Selection (:func:`take_new_landmarks`): when the window is full, the features seen in its oldest and
   in its newest clone (tracks spanning the whole window) and, on a stereo rig, in cam1 at least once,
   longest first, up to the free slots. Their window observations leave the MSCKF database.
2. Delayed initialization (:func:`initialize_landmarks`; open_vins ``UpdaterHelper`` / ``StateHelper::
   initialize``): triangulate from the whole track, stack the whitened residuals and Jacobians of every
   view ``r = H_x dx + H_f df + n`` (:func:`viotb.vio.msckf_update.feature_system`), and split them with the
   complete QR ``H_f = [Q1 Q2] [R1; 0]``. The top rows ``Q1^T r = (Q1^T H_x) dx + R1 df + n1`` define the
   landmark (``df = R1^-1 (Q1^T r - Q1^T H_x dx - n1)``: its covariance and cross-covariance follow); the
   bottom rows ``Q2^T r`` are the MSCKF update of the same track (tested equal to it), gated and applied
   after the landmark is in the state. A track whose landmark sigma exceeds
   ``MsckfParams.slam_max_init_sigma_ratio`` of its distance only makes that MSCKF update.
3. Update (:func:`update_landmarks`): at every clone, each landmark's observation in each camera (its own
   extrinsics), a chi-square gate per landmark (``2 C`` dof), one EKF update for all that pass. A landmark
   failing the gate :data:`MAX_GATE_FAILURES` frames in a row is marginalized (open_vins: at the first).
4. Marginalization (:func:`marginalize_lost_landmarks`): a landmark not seen in the current frame is
   dropped (rows and columns), as open_vins does when a SLAM track is lost.

Track noise: the KLT front end's track error is white noise plus a walk clocked by image motion (see
:mod:`viotb.vio.msckf_update`). The MSCKF whitens a feature's views with it; a landmark lives longer than
a window, so it carries the walk as states, one 2-vector per camera in its block (``SlamLandmark.
track_bias``, :func:`clock_track_walks`): ``z_c = h_c(x, p_f) + b_c + n``. Told only the white noise, 25
landmarks made the KLT headset look-around overconfident (NEES 17.7, 37.6 mm against 17.5 mm without
landmarks). The simulated front end's white noise has no walk states.

Observability (``MsckfParams.update_linearization``): the unobservable directions of VIO, global position
and yaw about gravity, move a landmark by ``dp_f = t`` and ``dp_f = alpha e_z x p_f``. With the default
``"current_oc"`` the Jacobians are evaluated at the current estimates (clone and landmark) and each
landmark's rows are projected, on the columns they touch (newest clone, landmark, extrinsic), onto the
complement of those directions taken at the *first* estimates: the clone's value when cloned and the
landmark's value when initialized (``SlamLandmark.p_W_fej``), as the MSCKF rows are (Hesch et al., TRO
2014). In the initialization the same projection is applied to ``[H_x H_f]`` before the split, so the
bottom rows annihilate the clone directions and the landmark moves with the clones along them. With
``"first_estimates"`` the Jacobians are evaluated at those first estimates instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from viotb.vio.camera import CameraCalibration
from viotb.vio.feature_database import FeatureDatabase
from viotb.vio.frontend import Tracks
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.msckf_update import (
    feature_system,
    right_row_weight,
    track_random_walk_px2_per_px,
    view_poses,
    window_observations,
)
from viotb.vio.state import (
    EXTRINSIC_BLOCK,
    State,
    add_diagonal_noise,
    augment_landmark,
    ekf_update,
    marginalize,
)
from viotb.vio.triangulation import triangulate
from viotb.vio.update_helpers import (
    Chi2Table,
    clone_unobservable_basis,
    feature_jacobian,
    measurement_compress,
    track_path_px,
)

# Consecutive gate failures that drop a landmark. open_vins drops it at the first; with a 95 % gate that
# is every 20th update of a consistent track, which cut the landmarks' lives short (headset look-around,
# simulated features, 8 s, seed 1, 25 landmarks: ATE 8.2 mm at 1, 7.4 at 2, 7.6 at 3).
MAX_GATE_FAILURES = 2


@dataclass(frozen=True)
class LandmarkObservations:
    """This frame's observations of the state's landmarks (M landmarks, C cameras).

    Attributes:
        ids: Landmark track ids, shape (M,).
        xy: Undistorted normalized coordinates in each camera, shape (M, C, 2) (0 where unseen).
        seen: Whether each camera sees it, shape (M, C).
    """

    ids: np.ndarray
    xy: np.ndarray
    seen: np.ndarray


@dataclass(frozen=True)
class SlamStats:
    """Bookkeeping of one frame's SLAM step.

    Attributes:
        landmarks: Landmarks in the state after the step.
        updated: Landmarks whose observations entered the update.
        rejected: Landmarks that failed the chi-square gate (and were marginalized).
        initialized: Landmarks added.
        init_rejected: Candidates whose track failed triangulation or the gate.
        marginalized: Landmarks dropped because their track was lost.
    """

    landmarks: int = 0
    updated: int = 0
    rejected: int = 0
    initialized: int = 0
    init_rejected: int = 0
    marginalized: int = 0


def landmark_observations(st: State, tracks: Tracks, num_cameras: int) -> LandmarkObservations:
    """Observations of the state's landmarks in ``tracks`` (cam1 only when ``num_cameras`` is 2)."""
    ids = np.fromiter(st.landmarks.keys(), dtype=np.int64, count=len(st.landmarks))
    xy = np.zeros((len(ids), num_cameras, 2))
    seen = np.zeros((len(ids), num_cameras), dtype=bool)
    for c in range(num_cameras):
        t_ids, t_xy, _ = tracks.camera(c)
        hit = np.isin(ids, t_ids)
        if np.any(hit):
            pos = {int(i): j for j, i in enumerate(np.asarray(t_ids).tolist())}
            rows = np.array([pos[int(i)] for i in ids[hit]])
            xy[hit, c] = np.asarray(t_xy)[rows]
            seen[hit, c] = True
    return LandmarkObservations(ids, xy, seen)


def marginalize_lost_landmarks(st: State, obs: LandmarkObservations) -> LandmarkObservations:
    """Drop the landmarks that no camera sees in this frame; returns the observations of the others."""
    lost = ~obs.seen.any(axis=1)
    for fid in obs.ids[lost].tolist():
        marginalize(st, st.landmark_block(int(fid)))
    keep = ~lost
    return LandmarkObservations(obs.ids[keep], obs.xy[keep], obs.seen[keep])


def take_new_landmarks(
    st: State, db: FeatureDatabase, p: MsckfParams, stereo: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Step 1: choose new landmarks and take their window observations out of ``db``.

    Args:
        st: The state, with the newest clone already added.
        db: The MSCKF feature database.
        p: Settings (``max_slam_features``, ``max_clones``).
        stereo: A stereo rig (candidates then need a cam1 view).

    Returns:
        ``(ids (F,), xy (F, C K, 2), mask (F, C K), stereo_views)`` of the chosen features
        (:func:`viotb.vio.msckf_update.window_observations`; empty when none).
    """
    empty = (np.zeros(0, dtype=np.int64), np.zeros((0, 0, 2)), np.zeros((0, 0), dtype=bool), False)
    free = p.max_slam_features - len(st.landmarks)
    if free <= 0 or len(st.clones) <= p.max_clones:
        return empty
    times = st.clone_times
    cand = np.intersect1d(db.features_seen_at(float(times[0])), db.features_seen_at(float(times[-1])))
    if len(cand) == 0:
        return empty
    xy, mask, stereo_views = window_observations(db, cand, times, stereo)
    K = len(times)
    ok = mask.sum(axis=1) >= p.min_track_length
    if stereo:  # a stereo view gives the landmark its metric depth at once
        ok &= mask[:, K:].any(axis=1) if stereo_views else False
    idx = np.flatnonzero(ok)
    idx = idx[np.argsort(-mask[idx].sum(axis=1), kind="stable")][:free]
    if len(idx) == 0:
        return empty
    db.remove_features(cand[idx])
    return cand[idx], xy[idx], mask[idx], stereo_views


def _projector(U: np.ndarray) -> np.ndarray:
    """Batched ``I - U (U^T U)^-1 U^T`` for ``U`` of shape (..., n, d): shape (..., n, n)."""
    Ut = np.swapaxes(U, -1, -2)
    Pi = -U @ np.linalg.solve(Ut @ U, Ut)
    n = U.shape[-2]
    Pi[..., np.arange(n), np.arange(n)] += 1.0
    return 0.5 * (Pi + np.swapaxes(Pi, -1, -2))


def _landmark_directions(p_f_W: np.ndarray) -> np.ndarray:
    """Unobservable directions on landmark blocks: ``dp_f = t`` and ``alpha e_z x p_f``, shape (F, 3, 4)."""
    p = np.asarray(p_f_W)
    U = np.zeros(p.shape[:-1] + (3, 4))
    U[..., :, :3] = np.eye(3)
    U[..., 0, 3] = -p[..., 1]
    U[..., 1, 3] = p[..., 0]
    return U


def initialize_landmarks(
    st: State,
    ids: np.ndarray,
    xy: np.ndarray,
    mask: np.ndarray,
    p: MsckfParams,
    chi2_table: Chi2Table,
    focal_px: float,
    calib_right: CameraCalibration | None,
    focal_right_px: float | None,
) -> tuple[int, int]:
    """Step 2: delayed initialization of the chosen tracks (see the module docstring).

    Args:
        st: The state (landmarks added, then updated with the tracks' remaining rows).
        ids: Track ids, shape (F,).
        xy: Window observations, shape (F, C K, 2).
        mask: Valid views, shape (F, C K).
        p: Settings.
        chi2_table: 95 % chi-square quantiles.
        focal_px: Cam0 focal length (px).
        calib_right: Cam1 calibration when the views include cam1's, else None.
        focal_right_px: Cam1 focal length (px).

    Returns:
        ``(initialized, rejected)`` counts.
    """
    if len(ids) == 0:
        return 0, 0
    # 2a. Triangulate from the whole track in the current clone estimates.
    R_WC, p_WC = view_poses(st, calib_right)
    tri = triangulate(R_WC, p_WC, xy, mask, p.triangulation, focal_px)
    ok = tri.valid
    n_rej = int(np.sum(~ok))
    if not np.any(ok):
        return 0, n_rej
    ids, xy, mask, p_f = ids[ok], xy[ok], mask[ok], tri.p_W[ok]
    # 2b. Whitened residuals and Jacobians of every view.
    r, H_x, H_f, cols, clone_offsets = feature_system(
        st, xy, mask, p_f, p, focal_px, calib_right, focal_right_px
    )
    n_c = len(cols)
    if p.use_fej and p.update_linearization == "current_oc":
        # 2c. Observability constraint on [H_x H_f] (clone directions at their first estimates, the
        #     landmark's at its initial value, which becomes its first estimate).
        clones = list(st.clones.values())
        R_fej = np.stack([c.R_WB_fej for c in clones])
        p_fej = np.stack([c.p_WB_fej for c in clones])
        U_c = clone_unobservable_basis(R_fej, p_fej, clone_offsets, st.dim)[cols]
        U = np.concatenate([np.broadcast_to(U_c, (len(ids),) + U_c.shape), _landmark_directions(p_f)], axis=1)
        H = np.concatenate([H_x, H_f], axis=2) @ _projector(U)
        H_x, H_f = H[..., :n_c], H[..., n_c:]
    # 2d. Split with the complete QR of H_f: top 3 rows define the landmark, the rest update the state.
    Q, R_f = np.linalg.qr(H_f, mode="complete")
    Qt = np.swapaxes(Q, 1, 2)
    H_t, r_t = Qt @ H_x, np.einsum("fij,fj->fi", Qt, r)
    H1, R1, r1 = H_t[:, :3], R_f[:, :3, :3], r_t[:, :3]
    H2, r2 = H_t[:, 3:], r_t[:, 3:]
    # 2e. Chi-square gate on the bottom rows (dof 2 m - 3, m views), as the MSCKF gates a feature.
    sigma2 = (p.pixel_sigma_px / focal_px) ** 2
    P_cc = st.cov[np.ix_(cols, cols)]
    S = H2 @ P_cc @ np.swapaxes(H2, 1, 2)
    S[:, np.arange(S.shape[1]), np.arange(S.shape[1])] += sigma2
    chi2 = np.einsum("fi,fi->f", r2, np.linalg.solve(S, r2[..., None])[..., 0])
    dof = 2 * mask.sum(axis=1) - 3
    well_posed = np.abs(np.diagonal(R1, axis1=1, axis2=2)).min(axis=1) > 1e-9 * np.abs(R1).max(axis=(1, 2))
    passed = (chi2 < p.chi2_multiplier * chi2_table(dof)) & well_posed
    n_rej += int(np.sum(~passed))
    if not np.any(passed):
        return 0, n_rej
    # 2f. Add the landmarks: df = -A dx_c - R1^-1 n1 with A = R1^-1 H1, so
    #     P_xf = -P_x,c A^T (exact for the landmarks added before, whose noise is independent) and
    #     P_ff = A P_cc A^T + sigma2 R1^-1 R1^-T; value p_f + R1^-1 r1 (open_vins initialize_invertible).
    q_px = track_random_walk_px2_per_px(p)
    K = len(st.clones)
    n_cams = mask.shape[1] // K
    focal_v = np.repeat([focal_px, focal_right_px or focal_px][:n_cams], K)
    path_px = track_path_px(xy, mask, focal_v, K) if q_px > 0.0 else None
    dist_m = np.linalg.norm(p_f - st.clones[next(reversed(st.clones))].p_WB, axis=1)
    n_init = 0
    for f in np.flatnonzero(passed):
        R1_inv = np.linalg.inv(R1[f])
        A = R1_inv @ H1[f]
        cov_xf = -st.cov[:, cols] @ A.T
        cov_ff = A @ P_cc @ A.T + sigma2 * (R1_inv @ R1_inv.T)
        if np.sqrt(np.linalg.eigvalsh(cov_ff)[-1]) > p.slam_max_init_sigma_ratio * dist_m[f]:
            n_rej += 1  # 2e'. too poorly conditioned for a point in W (see MsckfParams)
            continue
        last_xy = np.zeros((0, 2))
        if path_px is not None:
            # 2f'. Walk states (KLT): each camera's walk starts at its latest view with the variance it
            #      gathered along the window (q times the path), independent of the rest (an approximation:
            #      the window's views shared that walk).
            views = mask[f].reshape(n_cams, K)
            last = np.where(views.any(axis=1), K - 1 - np.argmax(views[:, ::-1], axis=1), -1)
            last_xy = np.where(
                (last >= 0)[:, None],
                xy[f].reshape(n_cams, K, 2)[np.arange(n_cams), np.maximum(last, 0)],
                np.nan,
            )
            walk = q_px * path_px[f].reshape(n_cams, K)[np.arange(n_cams), np.maximum(last, 0)]
            var_b = np.repeat(walk / focal_v.reshape(n_cams, K)[:, 0] ** 2, 2)
            cov_xf = np.concatenate([cov_xf, np.zeros((st.dim, len(var_b)))], axis=1)
            cov_ff = scipy.linalg.block_diag(cov_ff, np.diag(var_b))
        augment_landmark(st, int(ids[f]), p_f[f] + R1_inv @ r1[f], cov_xf, cov_ff, last_xy)
        n_init += 1
    # 2g. The remaining rows update the state (and, through the cross-covariance, the new landmarks).
    H_c, r_c = measurement_compress(H2[passed].reshape(-1, n_c), r2[passed].reshape(-1))
    if len(H_c):
        H_full = np.zeros((len(H_c), st.dim))
        H_full[:, cols] = H_c
        ekf_update(st, H_full, r_c, sigma2)
    return n_init, n_rej


def landmark_system(
    st: State,
    obs: LandmarkObservations,
    p: MsckfParams,
    t_now: float,
    focal_px: float,
    calib_right: CameraCalibration | None,
    focal_right_px: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals and Jacobians of the landmarks' observations at the newest clone (step 3's system).

    Args:
        st: The state.
        obs: Observations of M landmarks at ``t_now``.
        p: Settings (``update_linearization``).
        t_now: Camera time (s) of the clone the observations belong to.
        focal_px: Cam0 focal length (px).
        calib_right: Cam1 calibration (cam1 observations are used only when given).
        focal_right_px: Cam1 focal length (px).

    Returns:
        ``(H (M, 2 C, n_l), r (M, 2 C), idx (M, n_l))``: rows whitened to cam0's normalized sigma (unseen
        cameras' rows zero), the local columns being the clone ``[dtheta, dp]``, the landmark block
        ``[dp_f, db]`` and, when estimated, the extrinsic; ``idx`` are their error-state indices.
    """
    M = len(obs.ids)
    C = obs.seen.shape[1] if calib_right is not None else 1
    clone = st.clones[float(t_now)]
    lms = [st.landmarks[int(i)] for i in obs.ids]
    p_f = np.stack([lm.p_W for lm in lms]).reshape(M, 3)
    p_f_fej = np.stack([lm.p_W_fej for lm in lms]).reshape(M, 3)
    B = lms[0].track_bias.shape[0] if M else 0  # walk states per landmark: 0 or the rig's cameras
    bias = np.stack([lm.track_bias for lm in lms]).reshape(M, B, 2)
    first = p.use_fej and p.update_linearization == "first_estimates"
    R_lin, p_lin = (clone.R_WB_fej, clone.p_WB_fej) if first else (clone.R_WB, clone.p_WB)
    f_lin = p_f_fej if first else p_f
    has_ext = st.has_block(EXTRINSIC_BLOCK)
    n_f = 9 + 2 * B  # local columns: clone [dtheta, dp], landmark dp_f, walks db, then the extrinsic
    n_l = n_f + 6 if has_ext else n_f
    H = np.zeros((M, C, 2, n_l))
    r = np.zeros((M, C, 2))
    for c in range(C):
        R_BC, p_BC = (st.R_BC, st.p_BC) if c == 0 else (calib_right.R_BC, calib_right.p_BC)
        cur = feature_jacobian(clone.R_WB, clone.p_WB, R_BC, np.asarray(p_BC, dtype=float), p_f)
        jac = feature_jacobian(R_lin, p_lin, R_BC, np.asarray(p_BC, dtype=float), f_lin) if first else cur
        scale = 1.0 if c == 0 else right_row_weight(p, focal_px, focal_right_px)
        w = np.where(obs.seen[:, c], scale, 0.0)[:, None]
        z = cur.z_norm + (bias[:, c] if B else 0.0)  # z = h(x, p_f) + b_c + n
        r[:, c] = (obs.xy[:, c] - z) * w
        H[:, c, :, 0:6] = jac.H_pose * w[..., None]
        H[:, c, :, 6:9] = jac.H_feature * w[..., None]
        if B:
            H[:, c, :, 9 + 2 * c : 11 + 2 * c] = np.eye(2) * w[..., None]
        if has_ext and c == 0:  # cam1's extrinsic is held at its calibration, as in the MSCKF rows
            H[:, c, :, n_f:] = jac.H_extrinsic * w[..., None]
    H = H.reshape(M, 2 * C, n_l)
    r = r.reshape(M, 2 * C)
    if p.use_fej and p.update_linearization == "current_oc":
        U = np.zeros((M, n_l, 4))  # the walk and extrinsic rows are zero: frame-invariant quantities
        U[:, :6] = clone_unobservable_basis(clone.R_WB_fej[None], clone.p_WB_fej[None], np.zeros(1), 6)
        U[:, 6:9] = _landmark_directions(p_f_fej)
        H = H @ _projector(U)
    o_c = st.clone_block(float(t_now)).offset
    idx = np.zeros((M, n_l), dtype=int)
    idx[:, :6] = o_c + np.arange(6)
    o_l = np.array([st.landmark_block(int(i)).offset for i in obs.ids]).reshape(M, 1)
    idx[:, 6:n_f] = o_l + np.arange(3 + 2 * B)
    if has_ext:
        idx[:, n_f:] = st.block(EXTRINSIC_BLOCK).offset + np.arange(6)
    return H, r, idx


def clock_track_walks(
    st: State, obs: LandmarkObservations, q_px2_per_px: float, focal_c_px: np.ndarray
) -> None:
    """Grow each landmark's walk states by ``q`` per pixel its observation moved since the last one.

    The track error model of the MSCKF (:func:`viotb.vio.update_helpers.random_walk_whitener`): white noise
    plus a walk of variance ``q_px2_per_px`` px^2 per px of image motion, here carried as a state per camera
    (``db``, normalized coordinates: variance ``q dpath / f_c^2``). A camera without a previous observation
    is clocked with cam0's motion.

    Args:
        st: The state (covariance of the walk states grown in place; ``last_xy`` updated).
        obs: This frame's observations of the landmarks.
        q_px2_per_px: Walk variance per pixel moved (px^2 / px).
        focal_c_px: Focal length (px) of each camera, shape (C,).
    """
    for fid, xy, seen in zip(obs.ids.tolist(), obs.xy, obs.seen, strict=True):
        lm = st.landmarks[int(fid)]
        B = lm.track_bias.shape[0]
        if B == 0:
            continue
        step_px = np.linalg.norm(xy[:B] - lm.last_xy, axis=1) * focal_c_px[:B]
        step_px = np.where(np.isfinite(step_px), step_px, step_px[0] if np.isfinite(step_px[0]) else 0.0)
        step_px = np.where(seen[:B], step_px, 0.0)
        o = st.landmark_block(int(fid)).offset + 3
        add_diagonal_noise(
            st, o + np.arange(2 * B), np.repeat(q_px2_per_px * step_px / focal_c_px[:B] ** 2, 2)
        )
        lm.last_xy = np.where(seen[:B, None], xy[:B], lm.last_xy)


def update_landmarks(
    st: State,
    obs: LandmarkObservations,
    p: MsckfParams,
    chi2_table: Chi2Table,
    t_now: float,
    focal_px: float,
    calib_right: CameraCalibration | None,
    focal_right_px: float | None,
) -> tuple[int, int]:
    """Step 3: EKF update with every landmark's observations at the newest clone ``t_now``.

    Args:
        st: The state (updated in place; landmarks failing the gate are marginalized).
        obs: This frame's observations of the landmarks (every one seen by some camera).
        p: Settings.
        chi2_table: 95 % chi-square quantiles.
        t_now: Camera time (s) of the newest clone, the frame of ``obs``.
        focal_px: Cam0 focal length (px).
        calib_right: Cam1 calibration (cam1 observations are used only when given).
        focal_right_px: Cam1 focal length (px).

    Returns:
        ``(updated, rejected)`` landmark counts.
    """
    if len(obs.ids) == 0:
        return 0, 0
    C = obs.seen.shape[1] if calib_right is not None else 1
    q_px = track_random_walk_px2_per_px(p)
    if q_px > 0.0:
        clock_track_walks(st, obs, q_px, np.array([focal_px, focal_right_px or focal_px])[:C])
    H, r, idx = landmark_system(st, obs, p, t_now, focal_px, calib_right, focal_right_px)
    P_loc = st.cov[idx[:, :, None], idx[:, None, :]]
    sigma2 = (p.pixel_sigma_px / focal_px) ** 2
    S = H @ P_loc @ np.swapaxes(H, 1, 2)
    S[:, np.arange(2 * C), np.arange(2 * C)] += sigma2
    chi2 = np.einsum("fi,fi->f", r, np.linalg.solve(S, r[..., None])[..., 0])
    dof = 2 * obs.seen[:, :C].sum(axis=1)
    passed = chi2 < p.chi2_multiplier * chi2_table(dof)
    if np.any(passed):
        rows_seen = np.repeat(obs.seen[:, :C], 2, axis=1)  # (M, 2 C): drop unseen cameras' zero rows
        sel = passed[:, None] & rows_seen
        m_of_row = np.nonzero(sel)[0]
        H_full = np.zeros((len(m_of_row), st.dim))
        H_full[np.arange(len(m_of_row))[:, None], idx[m_of_row]] = H[sel]
        ekf_update(st, H_full, r[sel], sigma2)
    # A gate failure skips the observation; a landmark failing MAX_GATE_FAILURES frames in a row (an
    # outlier track, not the gate's 5 % tail) is marginalized.
    for fid, ok in zip(obs.ids.tolist(), passed.tolist(), strict=True):
        lm = st.landmarks[int(fid)]
        lm.gate_failures = 0 if ok else lm.gate_failures + 1
        if lm.gate_failures >= MAX_GATE_FAILURES:
            marginalize(st, st.landmark_block(int(fid)))
    return int(passed.sum()), int(np.sum(~passed))
