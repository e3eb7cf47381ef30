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
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.loop.frames import RigidTransform, horizontal_axis_B, loop_4dof, tilt_error_rad
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


def pnp_sigmas(p_C: np.ndarray, sigma_norm: float, z_C: np.ndarray) -> tuple[float, float]:
    """Heading and position standard deviations of a PnP pose from its inliers' geometry.

    Gauss-Newton covariance ``sigma^2 (J^T J)^-1`` of the camera pose under a perturbation
    ``p_C' = Exp(dtheta) p_C + dt`` of the inliers' camera-frame points, with ``J`` the Jacobian of their
    normalized projections: a view whose depths barely vary lets a rotation trade with a translation, which
    shows here as large sigmas even when the reprojection error is small.

    Args:
        p_C: Inlier landmarks in the query camera frame (m), shape (N, 3), positive depth.
        sigma_norm: Reprojection noise in normalized coordinates (px / focal length).
        z_C: World up expressed in the query camera frame, shape (3,) unit.

    Returns:
        ``(sigma about world z (rad), largest position sigma (m))``.
    """
    x, y, z = p_C[:, 0], p_C[:, 1], p_C[:, 2]
    d_proj = np.zeros((len(p_C), 2, 3))
    d_proj[:, 0, 0] = d_proj[:, 1, 1] = 1.0 / z
    d_proj[:, 0, 2], d_proj[:, 1, 2] = -x / z**2, -y / z**2
    skew = np.zeros((len(p_C), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -z, y, -x
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = z, -y, x
    J = np.concatenate([-d_proj @ skew, d_proj], axis=2).reshape(-1, 6)  # d proj / d(dtheta, dt)
    cov = sigma_norm**2 * np.linalg.pinv(J.T @ J)
    yaw_var = float(z_C @ cov[:3, :3] @ z_C)
    return float(np.sqrt(max(yaw_var, 0.0))), float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)))


def verify_candidate(
    query_uv_px: np.ndarray,
    query_desc: np.ndarray,
    R_WBq_odom: np.ndarray,
    match: Keyframe,
    calib: CameraCalibration,
    keyframe_params: KeyframeParams,
    params: VerificationParams,
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
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, dist, rvec, tvec)
    R_CB = cv2.Rodrigues(rvec)[0]
    p_C = obj @ R_CB.T + tvec.ravel()
    with np.errstate(divide="ignore", invalid="ignore"):
        err_px = f_px * np.linalg.norm(p_C[:, :2] / p_C[:, 2:3] - img, axis=1)
    inliers = np.flatnonzero((err_px <= params.ransac_threshold_px) & (p_C[:, 2] > 0))
    if len(inliers) < max(params.min_inliers, params.min_inlier_ratio * len(iq)):
        return Verdict(None, "few inliers")
    rms_px = float(np.sqrt(np.mean(err_px[inliers] ** 2)))
    if rms_px > params.max_rms_px:
        return Verdict(None, "reprojection")
    T_Cq_Bm = RigidTransform(R_CB, tvec.ravel().copy())
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
    yaw_sigma_rad, t_sigma_m = pnp_sigmas(p_C[inliers], max(rms_px, 0.5) / f_px, z_C)
    verified = VerifiedPose(T_mq, len(inliers), len(iq), rms_px, float(np.rad2deg(yaw_sigma_rad)), t_sigma_m)
    return Verdict(verified, "ok")
