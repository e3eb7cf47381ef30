"""Geometric verification of a loop candidate: PnP RANSAC of the query's features on the match's landmarks.

The query's ORB descriptors are matched (Lowe ratio) to those of the candidate's features that carry a
landmark
``p_Bm`` (candidate body frame). PnP RANSAC (``cv2.solvePnPRansac``, AP3P minimal solver, on undistorted
normalized coordinates) then Levenberg-Marquardt refinement on the inliers give ``T_Cq_Bm``; the relative pose
of the query body in the match body is ``T_Bm_Bq = T_Cq_Bm^-1 T_BC^-1``. As in VINS-Mono's ``findConnection``
the result must have enough inliers (25, and a quarter of the matches) and a plausible relative pose (yaw
under 30 deg, bounded distance);
here also a small RMS reprojection error and roll/pitch that agree with the odometry's, which gravity makes
observable, so an image that looks alike but whose 3-D structure does not fit is refused.

The refinement then weights each inlier by its features' pyramid levels (``weight_by_octave``): an ORB
keypoint found at level ``o`` sits on a grid ``1.2 ** o`` pixels wide, so both the query's keypoint and the
match keypoint its landmark was triangulated from carry that much more noise; the residual's variance is
taken as ``s_q ** 2 + s_m ** 2`` (in level-0 units), and a weighted Gauss-Newton
(:func:`refine_pose_weighted`) minimises the whitened residuals, as ORB-SLAM's pose optimisation does with
its ``invSigma2`` per level (Mur-Artal et al. 2015, the motion-only bundle adjustment of its tracking).
Unweighted, the coarse levels (40-60 % of the inliers on 320x240 renders, f = 120 px) pulled a closure
6.7 cm / 0.98 deg off the truth where yaw trades with a lateral translation; weighted, 4.6 cm / 0.67 deg
(long-loop 40 s, seed 14; median error 0.75 -> 0.50 cm).

Optionally last (``gravity_aligned``, off by default), the pose is refined once more with roll and pitch
held at what the two odometries say (:func:`refine_yaw_translation`: relative yaw and translation free,
4 DOF, as in the pose graph and VINS-Mono's relocalization): gravity makes the tilt observable to each
odometry to ~0.1 deg, and left free on a view of little depth variation it traded with a lateral
translation (``fly-lights-out`` with KLT: the loops against the hover's keyframes 0.9-1.9 deg off the
odometry's tilt and 5-6 cm off the truth, following the drifting odometry, so that the drift rate fitted
on them had the wrong sign on seeds 5 and 8). Off by default: held, the closures of a moving loop got
worse (``long-loop``, ``VerificationParams.gravity_aligned``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.lie import exp_so3, rotz, skew_batch
from viotb.vio.loop.frames import (
    RigidTransform,
    heading_rad,
    horizontal_axis_B,
    loop_4dof,
    projection_jacobian,
    tilt_error_rad,
)
from viotb.vio.loop.keyframes import Keyframe, match_descriptors
from viotb.vio.loop.params import KeyframeParams, VerificationParams


@dataclass(frozen=True)
class VerifiedPose:
    """A verified relative pose between a query frame and a keyframe.

    Attributes:
        T_match_query: Pose of the query body in the match body frame, ``T_Bm_Bq``.
        inliers: PnP inliers.
        matches: Descriptor matches to landmarks tried.
        rms_px: RMS reprojection error of the inliers after refinement (px).
        yaw_sigma_deg: Standard deviation of the query's heading about world z that the inliers' geometry
            and ``rms_px`` give (``pnp_sigmas``, deg).
        translation_sigma_m: Largest standard deviation of the query's position (m).
    """

    T_match_query: RigidTransform
    inliers: int
    matches: int
    rms_px: float
    yaw_sigma_deg: float = 0.0
    translation_sigma_m: float = 0.0


@dataclass(frozen=True)
class Verdict:
    """Outcome of one verification.

    Attributes:
        pose: The verified pose, or None when refused.
        reason: ``"ok"`` or why it was refused.
    """

    pose: VerifiedPose | None
    reason: str


def pose_jacobian(p_C: np.ndarray) -> np.ndarray:
    """Jacobian of normalized projections under ``p_C' = Exp(dtheta) p_C + dt``, shape (N, 2, 6).

    Args:
        p_C: Points in the camera frame (m), shape (N, 3), positive depth.

    Returns:
        ``d (x / z, y / z) / d (dtheta, dt)`` per point (columns: rotation then translation).
    """
    d_proj = projection_jacobian(p_C)
    return np.concatenate([-d_proj @ skew_batch(p_C), d_proj], axis=2)


def pnp_sigmas(
    p_C: np.ndarray, sigma_norm: float, z_C: np.ndarray, weights: np.ndarray | None = None
) -> tuple[float, float]:
    """Heading and position standard deviations of a PnP pose from its inliers' geometry.

    Gauss-Newton covariance ``sigma^2 (J^T W J)^-1`` of the camera pose under a perturbation
    ``p_C' = Exp(dtheta) p_C + dt`` of the inliers' camera-frame points, with ``J`` the Jacobian of their
    normalized projections and ``W`` their weights (``sigma`` is then the noise of a unit-weight residual):
    a view whose depths barely vary lets a rotation trade with a translation, which shows here as large
    sigmas even when the reprojection error is small.

    Args:
        p_C: Inlier landmarks in the query camera frame (m), shape (N, 3), positive depth.
        sigma_norm: Reprojection noise of a unit-weight residual in normalized coordinates (px / focal
            length).
        z_C: World up expressed in the query camera frame, shape (3,) unit.
        weights: Inverse relative variances of the residuals, shape (N,); None for all 1.

    Returns:
        ``(sigma about world z (rad), largest position sigma (m))``.
    """
    J = pose_jacobian(p_C)
    w = np.ones(len(p_C)) if weights is None else np.asarray(weights, dtype=float)
    cov = sigma_norm**2 * np.linalg.pinv(np.einsum("n,nki,nkj->ij", w, J, J))
    yaw_var = float(z_C @ cov[:3, :3] @ z_C)
    return float(np.sqrt(max(yaw_var, 0.0))), float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)))


def refine_pose_weighted(
    points_B: np.ndarray,
    xy_norm: np.ndarray,
    weights: np.ndarray,
    R_CB: np.ndarray,
    p_CB: np.ndarray,
    iterations: int = 10,
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Gauss-Newton refinement of a camera pose on 3-D / 2-D correspondences.

    Minimises ``sum_i w_i |pi(R_CB X_i + p_CB) - x_i|^2`` with ``pi`` the normalized projection, stepping
    ``R <- Exp(dtheta) R``, ``p <- Exp(dtheta) p + dt`` (the perturbation of :func:`pose_jacobian`).

    Args:
        points_B: Landmarks in the source frame (m), shape (N, 3).
        xy_norm: Their observations in normalized (undistorted) coordinates, shape (N, 2).
        weights: Inverse relative variances, shape (N,), positive.
        R_CB: Initial rotation source -> camera, shape (3, 3).
        p_CB: Initial translation (m), shape (3,).
        iterations: Most Gauss-Newton steps (stops earlier once the step is below 1e-10).

    Returns:
        ``(R_CB (3, 3), p_CB (3,))``; the initial pose where the normal equations are singular.
    """
    R, p = np.asarray(R_CB, dtype=float), np.asarray(p_CB, dtype=float)
    w = np.asarray(weights, dtype=float)
    for _ in range(iterations):
        p_C = points_B @ R.T + p
        r = (p_C[:, :2] / p_C[:, 2:3] - xy_norm).reshape(-1, 2)
        J = pose_jacobian(p_C)
        H = np.einsum("n,nki,nkj->ij", w, J, J)
        g = np.einsum("n,nki,nk->i", w, J, r)
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return np.asarray(R_CB, dtype=float), np.asarray(p_CB, dtype=float)
        dR = exp_so3(step[:3])
        R, p = dR @ R, dR @ p + step[3:]
        if np.linalg.norm(step) < 1e-10:
            break
    return R, p


def refine_yaw_translation(
    points_B: np.ndarray,
    xy_norm: np.ndarray,
    weights: np.ndarray,
    A: np.ndarray,
    T_m: np.ndarray,
    yaw_rad: float,
    p_CB: np.ndarray,
    iterations: int = 10,
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Gauss-Newton refinement of a camera pose whose roll and pitch are known (4 DOF).

    The rotation is ``R_CB = A Rz(yaw) T_m`` (``T_m`` the match body's tilt, ``A = R_BC^T T_q^T`` the
    query's), so only the relative yaw about the vertical and the translation are free; residuals and
    weights as in :func:`refine_pose_weighted`. Roll and pitch are what gravity makes observable to both
    odometries; PnP with them free trades a tilt for a translation on a view of little depth variation
    (measured on ``fly-lights-out``: loops against hover keyframes 0.9-1.9 deg off the odometry's tilt and
    5-6 cm off the truth; 0.1-0.4 deg and 1-2 cm against the others).

    Args:
        points_B: Landmarks in the match body frame (m), shape (N, 3).
        xy_norm: Their observations in normalized (undistorted) coordinates, shape (N, 2).
        weights: Inverse relative variances, shape (N,), positive.
        A: ``R_BC^T T_q^T``, shape (3, 3).
        T_m: The match body's tilt (``R_WB`` without its heading), shape (3, 3).
        yaw_rad: Initial relative yaw (rad).
        p_CB: Initial translation (m), shape (3,).
        iterations: Most Gauss-Newton steps (stops earlier once the step is below 1e-10).

    Returns:
        ``(R_CB (3, 3), p_CB (3,))``; the initial pose where the normal equations are singular.
    """
    X = np.asarray(points_B, dtype=float) @ np.asarray(T_m).T  # the landmarks in the match's yaw frame
    w = np.asarray(weights, dtype=float)
    yaw, p = float(yaw_rad), np.asarray(p_CB, dtype=float).copy()
    dX = np.cross(np.array([0.0, 0.0, 1.0]), X)  # d (Rz X) / d yaw, before Rz
    for _ in range(iterations):
        R = A @ rotz(yaw)
        p_C = X @ R.T + p
        r = p_C[:, :2] / p_C[:, 2:3] - xy_norm
        d_proj = projection_jacobian(p_C)
        J = np.concatenate([d_proj @ (dX @ R.T)[:, :, None], d_proj], axis=2)  # (N, 2, 4)
        H = np.einsum("n,nki,nkj->ij", w, J, J)
        g = np.einsum("n,nki,nk->i", w, J, r)
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return A @ rotz(float(yaw_rad)) @ T_m, np.asarray(p_CB, dtype=float)
        yaw, p = yaw + step[0], p + step[1:]
        if np.linalg.norm(step) < 1e-10:
            break
    return A @ rotz(yaw) @ T_m, p


def _reprojection(
    points_B: np.ndarray, xy_norm: np.ndarray, R_CB: np.ndarray, p_CB: np.ndarray, f_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) and their reprojection errors (N,) in pixels (NaN/inf behind)."""
    p_C = points_B @ R_CB.T + p_CB
    with np.errstate(divide="ignore", invalid="ignore"):
        return p_C, f_px * np.linalg.norm(p_C[:, :2] / p_C[:, 2:3] - xy_norm, axis=1)


def _inliers_at(
    points_B: np.ndarray,
    xy_norm: np.ndarray,
    R_CB: np.ndarray,
    p_CB: np.ndarray,
    f_px: float,
    threshold_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inliers of a pose: in front of the camera and reprojected within ``threshold_px``.

    Returns:
        ``(mask (N,) bool, p_C (N, 3) m, err_px (N,))``.
    """
    p_C, err_px = _reprojection(points_B, xy_norm, R_CB, p_CB, f_px)
    return (err_px <= threshold_px) & (p_C[:, 2] > 0), p_C, err_px


def _align_tilt(
    obj, img, weights, R_CB, p_CB, R_WBq, R_WBm, calib, f_px, params
) -> tuple[np.ndarray, np.ndarray]:
    """The PnP pose refined with the odometries' roll and pitch held (:func:`refine_yaw_translation`).

    The tilt check is made on the free 6-DOF pose first (a pose far off the odometry's tilt is a wrong
    match); the inliers are those of the free pose.
    """
    tilt = tilt_error_rad(R_WBm @ (calib.R_BC @ R_CB).T, R_WBq)
    if np.rad2deg(tilt) > params.max_tilt_error_deg:
        return R_CB, p_CB  # refused by the tilt check that follows
    T_q = rotz(-heading_rad(R_WBq)) @ R_WBq
    T_m = rotz(-heading_rad(R_WBm)) @ R_WBm
    A = calib.R_BC.T @ T_q.T
    M = T_q @ calib.R_BC @ R_CB @ T_m.T  # ~ Rz(relative yaw)
    sel = _inliers_at(obj, img, R_CB, p_CB, f_px, params.ransac_threshold_px)[0]
    if sel.sum() < params.min_inliers:
        return R_CB, p_CB
    yaw0 = float(np.arctan2(M[1, 0], M[0, 0]))
    return refine_yaw_translation(obj[sel], img[sel], weights[sel], A, T_m, yaw0, p_CB)


def verify_candidate(
    query_uv_px: np.ndarray,
    query_desc: np.ndarray,
    R_WBq_odom: np.ndarray,
    match: Keyframe,
    calib: CameraCalibration,
    keyframe_params: KeyframeParams,
    params: VerificationParams,
    query_octaves: np.ndarray | None = None,
) -> Verdict:
    """PnP RANSAC of a query frame against a candidate keyframe's landmarks, with sanity checks.

    Args:
        query_uv_px: Query keypoints (distorted pixels), shape (N, 2).
        query_desc: Query ORB descriptors, shape (N, 32) uint8.
        R_WBq_odom: Query attitude from odometry (any yaw frame), shape (3, 3); its roll/pitch are checked.
        match: Candidate keyframe.
        calib: Camera calibration (intrinsics, distortion, ``R_BC``, ``p_BC``).
        keyframe_params: Matching thresholds (ratio, Hamming distance).
        params: Verification thresholds.
        query_octaves: ORB pyramid level of each query keypoint, shape (N,); None for all level 0.

    Returns:
        The verdict; ``pose.T_match_query`` is ``T_Bm_Bq``.
    """
    has = match.has_landmark
    if has.sum() < params.min_inliers:
        return Verdict(None, "few landmarks")
    lm_rows = np.flatnonzero(has)
    iq, il = match_descriptors(
        query_desc, match.descriptors[lm_rows], keyframe_params.match_ratio, keyframe_params.max_hamming
    )
    if len(iq) < params.min_inliers:
        return Verdict(None, "few matches")
    cam = calib.camera
    f_px = 0.5 * (cam.fx + cam.fy)
    obj = match.landmarks_B[lm_rows[il]].astype(np.float64)
    img = cam.undistort_points(query_uv_px[iq]).astype(np.float64)
    K, dist = np.eye(3), np.zeros(4)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj,
        img,
        K,
        dist,
        iterationsCount=params.ransac_iterations,
        reprojectionError=params.ransac_threshold_px / f_px,
        confidence=params.ransac_confidence,
        flags=cv2.SOLVEPNP_AP3P,
    )
    if not ok or inl is None or len(inl) < params.min_inliers:
        return Verdict(None, "few inliers")
    inl = inl.ravel()
    # Step 1: OpenCV's LM on the RANSAC inliers; step 2: the octave-weighted refinement on the inliers
    # at that pose.
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, dist, rvec, tvec)
    R_CB, p_CB = cv2.Rodrigues(rvec)[0], tvec.ravel().copy()
    weights = np.ones(len(iq))
    if params.weight_by_octave:
        s = keyframe_params.orb_scale_factor
        s_q = np.ones(len(query_uv_px)) if query_octaves is None else s ** np.asarray(query_octaves, float)
        s_m = match.pixel_sigma_scale(s)[lm_rows[il]]
        weights = 2.0 / (s_q[iq] ** 2 + s_m**2)
        sel = _inliers_at(obj, img, R_CB, p_CB, f_px, params.ransac_threshold_px)[0]
        if sel.sum() >= params.min_inliers:
            R_CB, p_CB = refine_pose_weighted(obj[sel], img[sel], weights[sel], R_CB, p_CB)
    if params.gravity_aligned:
        R_CB, p_CB = _align_tilt(
            obj, img, weights, R_CB, p_CB, R_WBq_odom, match.R_WB_odom, calib, f_px, params
        )
    sel, p_C, err_px = _inliers_at(obj, img, R_CB, p_CB, f_px, params.ransac_threshold_px)
    inliers = np.flatnonzero(sel)
    if len(inliers) < max(params.min_inliers, params.min_inlier_ratio * len(iq)):
        return Verdict(None, "few inliers")
    rms_px = float(np.sqrt(np.mean(err_px[inliers] ** 2)))
    if rms_px > params.max_rms_px:
        return Verdict(None, "reprojection")
    T_Cq_Bm = RigidTransform(R_CB, p_CB)
    T_B_C = RigidTransform(calib.R_BC, np.asarray(calib.p_BC, dtype=float))
    T_mq = T_Cq_Bm.inverse() @ T_B_C.inverse()
    dyaw, _ = loop_4dof(match.R_WB_odom, T_mq, horizontal_axis_B(match.R_WB_odom))
    if abs(np.rad2deg(dyaw)) > params.max_relative_yaw_deg:
        return Verdict(None, "relative yaw")
    if np.linalg.norm(T_mq.p) > params.max_relative_translation_m:
        return Verdict(None, "relative translation")
    tilt = tilt_error_rad(match.R_WB_odom @ T_mq.R, R_WBq_odom)
    if np.rad2deg(tilt) > params.max_tilt_error_deg:
        return Verdict(None, "tilt")
    z_C = (R_WBq_odom @ calib.R_BC).T @ np.array([0.0, 0.0, 1.0])
    w_in = weights[inliers]
    unit_rms_px = float(np.sqrt(np.mean(w_in * err_px[inliers] ** 2)))  # the noise of a unit weight
    yaw_sigma_rad, t_sigma_m = pnp_sigmas(p_C[inliers], max(unit_rms_px, 0.5) / f_px, z_C, w_in)
    verified = VerifiedPose(T_mq, len(inliers), len(iq), rms_px, float(np.rad2deg(yaw_sigma_rad)), t_sigma_m)
    return Verdict(verified, "ok")
