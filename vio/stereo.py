"""Stereo geometry of two calibrated cameras on one rig: relative pose, triangulation, left-right matching.

Frames: ``C0`` (left, the reference) and ``C1`` (right), each with its extrinsics ``(R_BCi, p_BCi)`` in the
body (IMU) frame B. Points map from C0 to C1 by ``p_C1 = R_C1C0 p_C0 + p_C1C0``::

    R_C1C0 = R_BC1^T R_BC0,        p_C1C0 = R_BC1^T (p_BC0 - p_BC1)

Triangulation works on unit bearings (``camera.unproject``), so it is the same for every camera model and
needs no rectification. The midpoint method takes the closest points of the two rays,
``lambda0 b0`` and ``c1 + lambda1 d1`` (``c1 = -R_C1C0^T p_C1C0`` the C1 centre in C0 and
``d1 = R_C1C0^T b1``), from the 2x2 normal equations; the linear DLT (Hartley and Zisserman, "Multiple View
Geometry", 2nd ed., sec. 12.2) works on normalized coordinates. The epipolar check measures the angle of the
right bearing off the epipolar plane spanned by the baseline and the left bearing.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.klt_flow import LK_NO_ERROR_PASS


def relative_pose(calib0: CameraCalibration, calib1: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Pose ``T_C1C0`` of camera 0 in camera 1 from the two camera-body extrinsics.

    Returns:
        ``(R_C1C0 (3, 3), p_C1C0 (3,) m)`` with ``p_C1 = R_C1C0 p_C0 + p_C1C0``.
    """
    R_C1C0 = calib1.R_BC.T @ calib0.R_BC
    p_C1C0 = calib1.R_BC.T @ (np.asarray(calib0.p_BC, dtype=float) - np.asarray(calib1.p_BC, dtype=float))
    return R_C1C0, p_C1C0


@dataclass(frozen=True)
class StereoPoints:
    """Triangulated stereo points in the left camera frame.

    Attributes:
        p_C0: Points in C0 (m), shape (N, 3).
        depth_m: Depth along the left optical axis, ``p_C0[:, 2]`` (m), shape (N,).
        valid: In front of both cameras with enough parallax, shape (N,) bool.
    """

    p_C0: np.ndarray
    depth_m: np.ndarray
    valid: np.ndarray


def triangulate_midpoint(
    b0_C0: np.ndarray,
    b1_C1: np.ndarray,
    R_C1C0: np.ndarray,
    p_C1C0: np.ndarray,
    min_parallax_rad: float = 1e-4,
) -> StereoPoints:
    """Midpoint triangulation of bearing pairs (any camera model).

    Args:
        b0_C0: Unit bearings in the left camera, shape (N, 3).
        b1_C1: Unit bearings in the right camera, shape (N, 3).
        R_C1C0: Rotation C0 -> C1, shape (3, 3).
        p_C1C0: C0 origin in C1 (m), shape (3,).
        min_parallax_rad: Smallest angle between the rays for a valid point (rad).

    Returns:
        The points; rows of invalid pairs hold the midpoint when it exists, else NaN.
    """
    b0 = np.atleast_2d(np.asarray(b0_C0, dtype=float))
    d1 = np.atleast_2d(np.asarray(b1_C1, dtype=float)) @ R_C1C0  # rows of R_C1C0^T b1
    c1 = -R_C1C0.T @ np.asarray(p_C1C0, dtype=float)
    a = np.sum(b0 * d1, axis=1)
    det = 1.0 - a * a  # = sin^2(parallax) for unit bearings
    b0c = b0 @ c1
    d1c = d1 @ c1
    with np.errstate(divide="ignore", invalid="ignore"):
        lam0 = (b0c - a * d1c) / det
        lam1 = (a * b0c - d1c) / det
        p_C0 = 0.5 * (lam0[:, None] * b0 + c1 + lam1[:, None] * d1)
    valid = (
        (det > np.sin(min_parallax_rad) ** 2)
        & (lam0 > 0.0)
        & (lam1 > 0.0)
        & np.all(np.isfinite(p_C0), axis=1)
    )
    return StereoPoints(p_C0, p_C0[:, 2].copy(), valid)


def triangulate_dlt(xy0: np.ndarray, xy1: np.ndarray, R_C1C0: np.ndarray, p_C1C0: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of normalized-coordinate pairs, with ``P0 = [I | 0]``, ``P1 = [R | t]``.

    Args:
        xy0: Undistorted normalized coordinates in the left camera, shape (N, 2).
        xy1: Undistorted normalized coordinates in the right camera, shape (N, 2).
        R_C1C0: Rotation C0 -> C1, shape (3, 3).
        p_C1C0: C0 origin in C1 (m), shape (3,).

    Returns:
        Points in C0 (m), shape (N, 3).
    """
    xy0 = np.atleast_2d(np.asarray(xy0, dtype=float))
    xy1 = np.atleast_2d(np.asarray(xy1, dtype=float))
    P0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = np.hstack([R_C1C0, np.asarray(p_C1C0, dtype=float).reshape(3, 1)])
    A = np.stack(
        [
            xy0[:, 0:1] * P0[2] - P0[0],
            xy0[:, 1:2] * P0[2] - P0[1],
            xy1[:, 0:1] * P1[2] - P1[0],
            xy1[:, 1:2] * P1[2] - P1[1],
        ],
        axis=1,
    )
    X = np.linalg.svd(A)[2][:, -1, :]
    return X[:, :3] / X[:, 3:4]


def epipolar_angle_rad(
    b0_C0: np.ndarray, b1_C1: np.ndarray, R_C1C0: np.ndarray, p_C1C0: np.ndarray
) -> np.ndarray:
    """Angle (rad) of each right bearing off its epipolar plane, shape (N,) (0 for a perfect match)."""
    c1 = -R_C1C0.T @ np.asarray(p_C1C0, dtype=float)
    normal = np.cross(c1, np.atleast_2d(b0_C0))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    d1 = np.atleast_2d(np.asarray(b1_C1, dtype=float)) @ R_C1C0
    return np.arcsin(np.clip(np.abs(np.sum(normal * d1, axis=1)), 0.0, 1.0))


@dataclass(frozen=True)
class StereoMatchParams:
    """Settings of the left-right KLT matcher.

    Attributes:
        win_size_px: KLT window side (px).
        max_level: KLT pyramid levels above the image.
        tracked_max_level: KLT pyramid levels for the points that have a prior depth (matched in the
            previous frame; None: ``max_level``). Their guess is within a pixel or two, inside the
            full-resolution window, so the coarse levels only cost time: on the stereo look-around (20 s,
            seed 0, every 5th frame; 93 % of the points have a prior) level 0 instead of 2 takes the
            matcher from 3.8-4.6 to 2.4 ms (CPU, loaded machine), accepts 10776 matches instead of 10775
            and moves them by 1e-3 px median (at most 0.04 px); the MSCKF's ATE on three look-arounds
            5.998 / 6.182 / 7.195 -> 5.988 / 6.179 / 7.190 mm.
        tracked_check_beyond_px: A point with a prior depth is tracked back right -> left only when its
            match lands farther than this (px) from its prediction at the prior depth (negative, the
            default: always); one KLT pass over almost no points instead of all. On the stereo
            look-around (20 s, seed 0) the backward pass refused 25 of 100078 such matches, and 99 % of
            them land within 0.52 px of the prediction (99.99 % within 1.3 px). The points without a prior
            (new tracks, lost matches) are always tracked back. 1.0 px with
            ``KltParams(anchor_zncc_at_final_warp=False)`` saves ~1.4 ms of 14.3 per stereo frame, but the
            look-around's world lock moved from 4.96 / 3.82 / 2.40 to 5.28 / 3.58 / 2.71 mm (seeds 0-2;
            README "MSCKF per frame"), so the default stays the full check.
        prior_depth_m: Depth of the initial guess of each right point (m).
        max_forward_backward_px: Largest distance of the right-to-left track from the left point (px).
        max_epipolar_px: Largest distance from the epipolar plane, as an angle times the right focal (px).
        min_depth_m: Nearest accepted depth (m).
        max_depth_m: Farthest accepted depth (m).
        lk_skip_error_pass: Run the KLT passes without OpenCV's error pass
            (:data:`viotb.vio.klt_flow.LK_NO_ERROR_PASS`): the same matches bit for bit, since a match must
            land inside the right image and track back within ``max_forward_backward_px`` of its left point.
    """

    win_size_px: int = 21
    max_level: int = 3
    tracked_max_level: int | None = 0
    tracked_check_beyond_px: float = -1.0
    prior_depth_m: float = 2.0
    max_forward_backward_px: float = 0.5
    max_epipolar_px: float = 1.5
    min_depth_m: float = 0.1
    max_depth_m: float = 50.0
    lk_skip_error_pass: bool = True


@dataclass(frozen=True)
class StereoMatches:
    """Left-right matches of left-image points.

    Attributes:
        uv1_px: Right pixels, shape (N, 2) (meaningless where ``mask`` is False).
        mask: Accepted matches, shape (N,) bool.
        p_C0: Triangulated points in the left camera (m), shape (N, 3).
        depth_m: Their depth along the left optical axis (m), shape (N,).
    """

    uv1_px: np.ndarray
    mask: np.ndarray
    p_C0: np.ndarray
    depth_m: np.ndarray


def _lk_settings(p: StereoMatchParams) -> dict:
    return {
        "winSize": (p.win_size_px, p.win_size_px),
        "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01),
        "flags": cv2.OPTFLOW_USE_INITIAL_FLOW | (LK_NO_ERROR_PASS if p.lk_skip_error_pass else 0),
    }


def left_right_klt(
    image0: np.ndarray,
    image1: np.ndarray,
    start_px: np.ndarray,
    guess_px: np.ndarray,
    level: int,
    unchecked_px: float,
    params: StereoMatchParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps 2-3 of :func:`match_stereo` for one group of points: KLT left -> right, then right -> left.

    Args:
        image0: Left gray image, uint8.
        image1: Right gray image, uint8.
        start_px: Left points, shape (K, 1, 2) float32.
        guess_px: Initial guesses in the right image, shape (K, 1, 2) float32.
        level: Pyramid levels.
        unchecked_px: A point is tracked back unless its match lands within this distance (px) of its
            guess (negative: every point).
        params: Settings (window, error pass).

    Returns:
        ``(right (K, 1, 2) float32, right status (K, 1) uint8, back (K, 1, 2) float32, back status (K, 1)
        uint8)``; a point not tracked back has its left point and status 1 as its back track.
    """
    lk = _lk_settings(params)
    fwd, s1, _ = cv2.calcOpticalFlowPyrLK(image0, image1, start_px, guess_px.copy(), maxLevel=level, **lk)
    back, s0 = start_px.copy(), np.ones((len(start_px), 1), dtype=np.uint8)
    moved = np.linalg.norm((fwd - guess_px).reshape(-1, 2), axis=1)
    check = np.flatnonzero(moved > unchecked_px)
    if len(check):
        bwd, s0c, _ = cv2.calcOpticalFlowPyrLK(
            image1, image0, fwd[check], start_px[check].copy(), maxLevel=level, **lk
        )
        back[check], s0[check] = bwd, s0c
    return fwd, s1, back, s0


def stereo_guess(
    uv0: np.ndarray,
    calib0: CameraCalibration,
    calib1: CameraCalibration,
    params: StereoMatchParams,
    prior_depth_m: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 1 of :func:`match_stereo`: each left point's bearing and its right guess at the prior depth.

    Args:
        uv0: Left pixels, shape (N, 2) float32.
        calib0: Left camera calibration.
        calib1: Right camera calibration.
        params: Settings (the default prior depth).
        prior_depth_m: Per-point depth (m), shape (N,), or None; non-finite or non-positive: the default.

    Returns:
        ``(b0 (N, 3) unit bearings in C0, guess (N, 2) float32 right pixels, has_prior (N,) bool)``.
    """
    R_C1C0, p_C1C0 = relative_pose(calib0, calib1)
    n = len(uv0)
    b0 = calib0.camera.unproject(uv0.astype(float))
    depth = np.full(n, params.prior_depth_m)
    has_prior = np.zeros(n, dtype=bool)
    if prior_depth_m is not None:
        given = np.asarray(prior_depth_m, dtype=float).reshape(n)
        has_prior = np.isfinite(given) & (given > 0.0)
        depth = np.where(has_prior, given, depth)
    with np.errstate(divide="ignore", invalid="ignore"):
        guess_C1 = (b0 * (depth[:, None] / b0[:, 2:3])) @ R_C1C0.T + p_C1C0
    guess = calib1.camera.project(guess_C1)
    guess = np.where(np.isfinite(guess) & (guess_C1[:, 2:3] > 0.0), guess, uv0).astype(np.float32)
    return b0, guess, has_prior


def klt_groups(p: StereoMatchParams, has_prior: np.ndarray) -> list[tuple[np.ndarray, int, float]]:
    """``(points (N,) bool, pyramid levels, tracked back unless within this distance (px) of the guess)``.

    One group when both kinds of point are treated alike, else the points with a prior depth first.
    """
    levels = p.max_level if p.tracked_max_level is None else p.tracked_max_level
    if levels != p.max_level or p.tracked_check_beyond_px >= 0.0:
        return [(has_prior, levels, p.tracked_check_beyond_px), (~has_prior, p.max_level, -1.0)]
    return [(np.ones(len(has_prior), dtype=bool), levels, -1.0)]


def match_stereo(
    image0: np.ndarray,
    image1: np.ndarray,
    uv0_px: np.ndarray,
    calib0: CameraCalibration,
    calib1: CameraCalibration,
    params: StereoMatchParams | None = None,
    prior_depth_m: np.ndarray | None = None,
) -> StereoMatches:
    """Track left-image points into the right image (KLT) and keep the geometrically consistent ones.

    Steps: 1. initial guess = the left bearing at ``prior_depth_m`` projected into the right camera;
    2. pyramidal KLT left -> right from that guess; 3. KLT right -> left, reject when it lands more than
    ``max_forward_backward_px`` from the left point; 4. reject right points outside the image or farther than
    ``max_epipolar_px`` from the epipolar plane; 5. triangulate (midpoint) and keep depths in range.

    Args:
        image0: Left gray image, uint8 (H0, W0).
        image1: Right gray image, uint8 (H1, W1).
        uv0_px: Left pixels, shape (N, 2).
        calib0: Left camera calibration.
        calib1: Right camera calibration.
        params: Settings.
        prior_depth_m: Per-point depth (m) of the initial guess, shape (N,) (e.g. the depth of the same
            track in the previous frame); non-finite entries use ``params.prior_depth_m``.

    Returns:
        The matches (all N rows; see ``mask``).
    """
    p = params if params is not None else StereoMatchParams()
    uv0 = np.asarray(uv0_px, dtype=np.float32).reshape(-1, 2)
    n = len(uv0)
    if n == 0:
        return StereoMatches(np.zeros((0, 2)), np.zeros(0, dtype=bool), np.zeros((0, 3)), np.zeros(0))
    R_C1C0, p_C1C0 = relative_pose(calib0, calib1)
    cam1 = calib1.camera
    # 1. Initial guess at the prior depth.
    b0, guess, has_prior = stereo_guess(uv0, calib0, calib1, p, prior_depth_m)
    # 2.-3. KLT forward and backward (the points with a prior depth on their own pyramid depth).
    uv1 = np.zeros((n, 1, 2), dtype=np.float32)
    back = np.zeros((n, 1, 2), dtype=np.float32)
    st1 = np.zeros((n, 1), dtype=np.uint8)
    st0 = np.zeros((n, 1), dtype=np.uint8)
    for sel, level, unchecked_px in klt_groups(p, has_prior):
        idx = np.flatnonzero(sel)
        if len(idx) == 0:
            continue
        start0 = uv0[idx].reshape(-1, 1, 2)
        guess0 = guess[idx].reshape(-1, 1, 2)
        res = left_right_klt(image0, image1, start0, guess0, level, unchecked_px, p)
        uv1[idx], st1[idx], back[idx], st0[idx] = res
    uv1 = uv1.reshape(-1, 2).astype(float)
    ok = (st1.ravel() == 1) & (st0.ravel() == 1)
    ok &= np.linalg.norm(back.reshape(-1, 2) - uv0, axis=1) <= p.max_forward_backward_px
    ok &= cam1.in_image(uv1)
    # 4. Epipolar check.
    b1 = cam1.unproject(uv1)
    ok &= np.all(np.isfinite(b1), axis=1) & np.all(np.isfinite(b0), axis=1)
    safe_b1 = np.where(ok[:, None], b1, b0)
    ok &= epipolar_angle_rad(b0, safe_b1, R_C1C0, p_C1C0) * cam1.fx <= p.max_epipolar_px
    # 5. Triangulate.
    pts = triangulate_midpoint(b0, safe_b1, R_C1C0, p_C1C0)
    ok &= pts.valid & (pts.depth_m >= p.min_depth_m) & (pts.depth_m <= p.max_depth_m)
    return StereoMatches(uv1, ok, pts.p_C0, pts.depth_m)
