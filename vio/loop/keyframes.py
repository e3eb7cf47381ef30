"""Keyframes of the loop closer: selection, ORB features, and 3-D landmarks triangulated between keyframes.

A frame becomes a keyframe when the estimated body moved ``min_translation_m``, turned ``min_rotation_deg`` or
``max_interval_s`` passed since the last keyframe of its odometry sequence. Each keyframe keeps ORB keypoints
and binary descriptors, the pyramid level (octave) each was detected at, and a landmark per feature where
one is known. Landmarks are triangulated (linear DLT,
``cv2.triangulatePoints``) from ORB matches with the previous keyframes of the same sequence (the last one,
then older ones for features still without a landmark, a wider baseline), using the two
*estimated* poses and the camera calibration, so PnP needs nothing from the estimator's internals. They are
kept in the keyframe's body frame ``B`` (``landmarks_B``): a pose-graph correction that moves the keyframe
moves
its landmarks with it, and PnP against them gives the query's pose in the match body frame directly.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.lie import log_so3
from viotb.vio.loop.frames import projection_jacobian
from viotb.vio.loop.params import KeyframeParams


@dataclass
class Keyframe:
    """One keyframe (mutable: its map pose and landmarks are filled in after creation).

    Attributes:
        index: Position in the database.
        t_s: Time (s).
        sequence: Odometry sequence (a new one after each tracking loss; 0 for a loaded map).
        R_WB_odom: Estimated attitude in the odometry frame of its sequence, shape (3, 3).
        p_WB_odom: Estimated position in the odometry frame (m), shape (3,).
        keypoints_uv_px: Distorted pixel coordinates of the features, shape (N, 2) float32.
        descriptors: ORB descriptors, shape (N, 32) uint8.
        landmarks_B: Landmark of each feature in this keyframe's body frame (m), shape (N, 3); NaN rows
            where none.
        R_WB_map: Attitude in the map frame (pose graph), shape (3, 3), or None while its sequence is not
            localized.
        p_WB_map: Position in the map frame (m), shape (3,), or None.
        tf: Bag-of-words term frequencies, shape (W,), or None before the vocabulary exists.
        octaves: ORB pyramid level each feature was detected at, shape (N,) int; 0 for caller-given points;
            None (all 0) for keyframes of a map saved without it. A level-``o`` keypoint is located on a grid
            ``scale_factor ** o`` pixels wide, so its pixel noise grows by that factor.
        landmark_sigma_m_per_px: Standard deviation of each triangulated landmark (square root of its
            covariance's trace) per pixel of level-0 keypoint noise (m/px), shape (N,); inf where none, 0
            for a caller-given landmark (never replaced); None (a loaded map) for unknown.
    """

    index: int
    t_s: float
    sequence: int
    R_WB_odom: np.ndarray
    p_WB_odom: np.ndarray
    keypoints_uv_px: np.ndarray
    descriptors: np.ndarray
    landmarks_B: np.ndarray
    R_WB_map: np.ndarray | None = None
    p_WB_map: np.ndarray | None = None
    tf: np.ndarray | None = None
    octaves: np.ndarray | None = None
    landmark_sigma_m_per_px: np.ndarray | None = None

    def pixel_sigma_scale(self, scale_factor: float) -> np.ndarray:
        """Pixel-noise scale of each feature, ``scale_factor ** octave``, shape (N,)."""
        if self.octaves is None:
            return np.ones(len(self.keypoints_uv_px))
        return float(scale_factor) ** np.asarray(self.octaves, dtype=float)

    @property
    def has_landmark(self) -> np.ndarray:
        """Mask of features with a landmark, shape (N,) bool."""
        return np.isfinite(self.landmarks_B[:, 0])

    def landmarks_W(self, use_map: bool = True) -> np.ndarray:
        """Landmarks in the map frame (or the odometry frame), shape (M, 3) for the features that have one."""
        R, p = (self.R_WB_map, self.p_WB_map) if use_map and self.R_WB_map is not None else (None, None)
        if R is None:
            R, p = self.R_WB_odom, self.p_WB_odom
        return self.landmarks_B[self.has_landmark] @ R.T + p


def match_descriptors(
    desc_a: np.ndarray, desc_b: np.ndarray, ratio: float, max_hamming: int
) -> tuple[np.ndarray, np.ndarray]:
    """Lowe-ratio matches from ``desc_a`` (N, 32) to ``desc_b`` (M, 32).

    Returns:
        ``(ia, ib)``: indices of matched rows, each shape (K,), one match per row of ``a`` at most and no
        row of
        ``b`` used twice (the better one is kept).
    """
    if len(desc_a) == 0 or len(desc_b) < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(desc_a, desc_b, k=2)
    best: dict[int, tuple[float, int]] = {}
    for pair in knn:
        if len(pair) < 2:
            continue
        m, n = pair
        if m.distance <= max_hamming and m.distance < ratio * n.distance:
            if m.trainIdx not in best or m.distance < best[m.trainIdx][0]:
                best[m.trainIdx] = (m.distance, m.queryIdx)
    ib = np.array(sorted(best), dtype=np.int64)
    ia = np.array([best[i][1] for i in ib], dtype=np.int64)
    return ia, ib


def camera_pose(
    R_WB: np.ndarray, p_WB: np.ndarray, calib: CameraCalibration
) -> tuple[np.ndarray, np.ndarray]:
    """``(R_WC, p_WC)`` of the camera from the body pose and the extrinsics ``R_BC``, ``p_BC``."""
    return R_WB @ calib.R_BC, R_WB @ calib.p_BC + p_WB


class KeyframeDatabase:
    """Keyframes in insertion order, with selection, feature extraction and triangulation.

    Args:
        params: Keyframe parameters.
    """

    def __init__(self, params: KeyframeParams | None = None) -> None:
        """Empty database."""
        self.params = params or KeyframeParams()
        self.keyframes: list[Keyframe] = []
        self._orb = cv2.ORB_create(
            nfeatures=self.params.orb_n_features,
            scaleFactor=self.params.orb_scale_factor,
            fastThreshold=self.params.orb_fast_threshold,
        )
        self._last_of_sequence: dict[int, int] = {}

    def __len__(self) -> int:
        """Number of keyframes."""
        return len(self.keyframes)

    def last_of_sequence(self, sequence: int) -> Keyframe | None:
        """Most recent keyframe of an odometry sequence, or None."""
        index = self._last_of_sequence.get(sequence)
        return None if index is None else self.keyframes[index]

    def recent_of_sequence(self, sequence: int, n: int) -> list[Keyframe]:
        """Up to ``n`` most recent keyframes of an odometry sequence, newest first."""
        out: list[Keyframe] = []
        for kf in reversed(self.keyframes):
            if len(out) >= n:
                break
            if kf.sequence == sequence:
                out.append(kf)
        return out

    def is_keyframe(self, t_s: float, R_WB: np.ndarray, p_WB: np.ndarray, sequence: int) -> bool:
        """Whether a frame at this estimated pose should become a keyframe of ``sequence``."""
        last = self.last_of_sequence(sequence)
        if last is None:
            return True
        kp = self.params
        moved_m = float(np.linalg.norm(np.asarray(p_WB) - last.p_WB_odom))
        turned_deg = float(np.rad2deg(np.linalg.norm(log_so3(last.R_WB_odom.T @ R_WB))))
        return (
            moved_m >= kp.min_translation_m
            or turned_deg >= kp.min_rotation_deg
            or t_s - last.t_s >= kp.max_interval_s
        )

    def extract(
        self,
        image_u8: np.ndarray,
        R_WB: np.ndarray,
        p_WB: np.ndarray,
        points_W: np.ndarray | None = None,
        points_uv_px: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """ORB features of an image, plus descriptors at caller-given landmark observations.

        Args:
            image_u8: Grayscale image, shape (H, W) uint8.
            R_WB: Estimated attitude (odometry frame), shape (3, 3).
            p_WB: Estimated position (m), shape (3,).
            points_W: Landmarks known to the caller (odometry frame, m), shape (M, 3), or None.
            points_uv_px: Their pixels in this image, shape (M, 2), or None.

        Returns:
            ``(keypoints_uv_px (N, 2) float32, descriptors (N, 32) uint8, landmarks_B (N, 3) with NaN rows,
            octaves (N,) int8: the pyramid level of each feature, 0 for the caller's points)``.
        """
        kps, desc = self._orb.detectAndCompute(image_u8, None)
        uv = np.array([k.pt for k in kps], dtype=np.float32).reshape(-1, 2)
        octaves = np.array([k.octave for k in kps], dtype=np.int8)
        desc = np.zeros((0, 32), dtype=np.uint8) if desc is None else desc
        landmarks_B = np.full((len(uv), 3), np.nan)
        if points_W is not None and points_uv_px is not None and len(points_W):
            given = [
                cv2.KeyPoint(float(u), float(v), 31.0, -1, 0, 0, i) for i, (u, v) in enumerate(points_uv_px)
            ]
            kept, desc_given = self._orb.compute(image_u8, given)
            if desc_given is not None and len(kept):
                ids = np.array([k.class_id for k in kept])
                uv = np.vstack([uv, np.asarray(points_uv_px, dtype=np.float32)[ids]])
                desc = np.vstack([desc, desc_given])
                lm = (np.asarray(points_W, dtype=float)[ids] - p_WB) @ R_WB
                landmarks_B = np.vstack([landmarks_B, lm])
                octaves = np.concatenate([octaves, np.zeros(len(ids), dtype=np.int8)])
        return uv, np.ascontiguousarray(desc, dtype=np.uint8), landmarks_B, octaves

    def add(self, keyframe: Keyframe) -> None:
        """Append a keyframe (its ``index`` must be the next position)."""
        if keyframe.index != len(self.keyframes):
            raise ValueError(f"keyframe index {keyframe.index} != next position {len(self.keyframes)}")
        self.keyframes.append(keyframe)
        self._last_of_sequence[keyframe.sequence] = keyframe.index

    def triangulate(self, prev: Keyframe, new: Keyframe, calib: CameraCalibration) -> int:
        """Triangulate landmarks from matches between two keyframes and store them in both.

        Checks: positive depth in ``[min_depth_m, max_depth_m]`` in both cameras, ray parallax >=
        ``min_parallax_deg``, reprojection error <= ``max_reprojection_px`` in both. Each landmark's
        covariance is that of the two-view least-squares point, ``(sum_v J_v^T J_v / s_v^2)^-1`` per pixel
        of level-0 noise, with ``J_v`` the Jacobian of view ``v``'s projection (px per m) and ``s_v`` its
        keypoint's pyramid scale (``Keyframe.pixel_sigma_scale``): a pair of a wider baseline or finer
        keypoints gives a smaller one. A feature that already has a landmark keeps it unless the new one's
        standard deviation is smaller (a keyframe's landmarks improve as its later neighbours arrive);
        caller-given landmarks and those of keyframes without ``landmark_sigma_m_per_px`` are kept.

        Returns:
            Number of landmarks made or replaced in ``new`` (or ``prev``, whichever is more).
        """
        kp = self.params
        i_new, i_prev = match_descriptors(new.descriptors, prev.descriptors, kp.match_ratio, kp.max_hamming)
        if len(i_new) < 8:
            return 0
        cam = calib.camera
        xy_new = cam.undistort_points(new.keypoints_uv_px[i_new])
        xy_prev = cam.undistort_points(prev.keypoints_uv_px[i_prev])
        poses = [camera_pose(kf.R_WB_odom, kf.p_WB_odom, calib) for kf in (prev, new)]
        P = [np.hstack([R_WC.T, (-R_WC.T @ p_WC)[:, None]]) for R_WC, p_WC in poses]
        X = cv2.triangulatePoints(P[0], P[1], xy_prev.T.astype(float), xy_new.T.astype(float))
        with np.errstate(divide="ignore", invalid="ignore"):
            p_W = (X[:3] / X[3]).T
        ok = np.all(np.isfinite(p_W), axis=1)
        f_px = 0.5 * (cam.fx + cam.fy)
        rays = []
        info = np.zeros((len(p_W), 3, 3))  # (1/m^2) per 1/px^2 of level-0 noise
        views = ((prev, i_prev, xy_prev), (new, i_new, xy_new))
        for (R_WC, p_WC), (kf, idx, xy) in zip(poses, views, strict=True):
            p_C = (p_W - p_WC) @ R_WC
            z = p_C[:, 2]
            ok &= (z > kp.min_depth_m) & (z < kp.max_depth_m)
            with np.errstate(divide="ignore", invalid="ignore"):
                err_px = f_px * np.linalg.norm(p_C[:, :2] / z[:, None] - xy, axis=1)
                J = f_px * projection_jacobian(np.where(ok[:, None], p_C, 1.0)) @ R_WC.T
            ok &= err_px <= kp.max_reprojection_px
            scale2 = kf.pixel_sigma_scale(kp.orb_scale_factor)[idx] ** 2
            info += np.einsum("nki,nkj->nij", J, J) / scale2[:, None, None]
            rays.append(p_W - p_WC)
        with np.errstate(divide="ignore", invalid="ignore"):
            cos_par = np.sum(rays[0] * rays[1], axis=1) / (
                np.linalg.norm(rays[0], axis=1) * np.linalg.norm(rays[1], axis=1)
            )
        ok &= cos_par <= np.cos(np.deg2rad(kp.min_parallax_deg))
        sigma = np.full(len(p_W), np.inf)
        if ok.any():
            sigma[ok] = np.sqrt(np.trace(np.linalg.inv(info[ok]), axis1=1, axis2=2))
        made = 0
        for kf, idx in ((new, i_new[ok]), (prev, i_prev[ok])):
            lm_B = (p_W[ok] - kf.p_WB_odom) @ kf.R_WB_odom
            if kf.landmark_sigma_m_per_px is None:
                better = ~np.isfinite(kf.landmarks_B[idx, 0])
            else:
                better = sigma[ok] < kf.landmark_sigma_m_per_px[idx]
                kf.landmark_sigma_m_per_px[idx[better]] = sigma[ok][better]
            kf.landmarks_B[idx[better]] = lm_B[better]
            made = max(made, int(better.sum()))
        return made
