"""Bookkeeping of the sliding-window optimizer: keyframes, the IMU links between them, landmark tracks.

Each :class:`Keyframe` holds its values and its observations (feature id -> normalized xy, one dict per
camera: ``obs`` for cam0, ``obs_right`` for cam1 of a stereo rig); the landmarks are a dict feature id ->
point in W. The functions here select features to triangulate, gather observations
into the index arrays the factors take, and drop a landmark with all its observations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.state import ImuValues
from viotb.vio.triangulation import TriangulationParams, triangulate


@dataclass
class Keyframe:
    """One keyframe of the window.

    Attributes:
        key: Unique id (it names the keyframe in the linear prior).
        t_s: Time (s, IMU clock).
        x: Its values.
        obs: Feature id -> undistorted normalized coordinates in cam0, shape (2,).
        still: It carries a zero-velocity factor.
        obs_right: Feature id -> undistorted normalized coordinates in cam1 (stereo rigs), shape (2,).
        x_fej: Its values when a marginalization prior first held it: the linearization point of its
            Jacobians from then on (first-estimate Jacobians), or None before.
        gyro_B_rad_s: The gyro reading (rad/s, bias not removed) at the keyframe's time, shape (3,), or
            None (online time-offset calibration, :mod:`viotb.vio.window_calib`).
    """

    key: int
    t_s: float
    x: ImuValues
    obs: dict[int, np.ndarray]
    still: bool = False
    obs_right: dict[int, np.ndarray] = field(default_factory=dict)
    x_fej: ImuValues | None = None
    gyro_B_rad_s: np.ndarray | None = None

    def camera_obs(self, cam: int) -> dict[int, np.ndarray]:
        """Observations of camera ``cam`` (0: ``obs``, 1: ``obs_right``)."""
        return self.obs if cam == 0 else self.obs_right


@dataclass
class ImuLink:
    """The IMU between two consecutive keyframes.

    Attributes:
        pre: Its preintegration (re-integrated when the bias moves far).
        readings: ``(t_s (n,), gyro_B_rad_s (n, 3), accel_B_m_s2 (n, 3))``.
    """

    pre: ImuPreintegration
    readings: tuple[np.ndarray, np.ndarray, np.ndarray]


def landmark_candidates(
    keyframes: list[Keyframe],
    landmarks: dict[int, np.ndarray],
    min_track_length: int,
    max_landmarks: int,
    stereo: bool = False,
) -> list[int]:
    """Features seen in at least ``min_track_length`` keyframes (cam0) that are not landmarks yet.

    With ``stereo``, a feature also qualifies as soon as one keyframe sees it in both cameras (the stereo
    baseline gives it a depth). Longest cam0 tracks first (then by id), as many as ``max_landmarks`` leaves
    room for.
    """
    counts: dict[int, int] = {}
    paired: set[int] = set()
    for kf in keyframes:
        for fid in kf.obs:
            if fid not in landmarks:
                counts[fid] = counts.get(fid, 0) + 1
                if stereo and fid in kf.obs_right:
                    paired.add(fid)
    room = max_landmarks - len(landmarks)
    cand = sorted(
        (c for c in counts if counts[c] >= min_track_length or c in paired), key=lambda f: (-counts[f], f)
    )
    return cand[: max(room, 0)]


def track_matrix(keyframes: list[Keyframe], fids: list[int], cam: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Observations of features ``fids`` (F) in every keyframe (K) in camera ``cam``.

    Returns:
        ``(xy_norm (F, K, 2), mask (F, K))``, zero where ``mask`` is False.
    """
    K = len(keyframes)
    xy = np.zeros((len(fids), K, 2))
    mask = np.zeros((len(fids), K), dtype=bool)
    for k, kf in enumerate(keyframes):
        kf_obs = kf.camera_obs(cam)
        for f, fid in enumerate(fids):
            val = kf_obs.get(fid)
            if val is not None:
                xy[f, k], mask[f, k] = val, True
    return xy, mask


def observations(
    keyframes: list[Keyframe], lm_ids: list[int], cam: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(kf index (M,), landmark index (M,), xy_norm (M, 2))`` of landmarks ``lm_ids`` in camera ``cam``.

    Keyframe by keyframe, each in its observations' insertion order.
    """
    lm = np.asarray(lm_ids, dtype=np.int64)
    order = np.argsort(lm, kind="stable")
    lm_sorted = lm[order]
    ks, ls, xys = [], [], []
    for k, kf in enumerate(keyframes):
        kf_obs = kf.camera_obs(cam)
        if not kf_obs or not len(lm):
            continue
        ids = np.fromiter(kf_obs.keys(), dtype=np.int64, count=len(kf_obs))
        pos = np.minimum(np.searchsorted(lm_sorted, ids), len(lm) - 1)
        hit = lm_sorted[pos] == ids
        if np.any(hit):
            ks.append(np.full(int(np.sum(hit)), k, dtype=np.int64))
            ls.append(order[pos[hit]])
            xys.append(np.array(list(kf_obs.values()), dtype=float).reshape(-1, 2)[hit])
    if not ks:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 2))
    return np.concatenate(ks), np.concatenate(ls), np.concatenate(xys)


def drop_landmark(keyframes: list[Keyframe], landmarks: dict[int, np.ndarray], fid: int) -> None:
    """Remove landmark ``fid`` and its observations (every camera) in every keyframe."""
    landmarks.pop(fid, None)
    for kf in keyframes:
        kf.obs.pop(fid, None)
        kf.obs_right.pop(fid, None)


def fix_first_estimates(keyframes: list[Keyframe]) -> list[ImuValues]:
    """Give every keyframe without one its current values as first estimate; return them all (in order).

    Called when a marginalization prior takes the keyframes: from then on their Jacobians are evaluated
    there (:attr:`Keyframe.x_fej`).
    """
    for kf in keyframes:
        if kf.x_fej is None:
            kf.x_fej = kf.x.copy()
    return [kf.x_fej for kf in keyframes]


def triangulate_new(
    keyframes: list[Keyframe],
    landmarks: dict[int, np.ndarray],
    limits: tuple[int, int, bool],
    cams: list[tuple[np.ndarray, np.ndarray]],
    params: TriangulationParams,
    focal_px: float,
) -> int:
    """Triangulate the :func:`landmark_candidates` into ``landmarks`` (in place); return the rejected count.

    Args:
        keyframes: The window.
        landmarks: Feature id -> point in W (m); the valid new points are added.
        limits: ``(min_track_length, max_landmarks, stereo)`` of :func:`landmark_candidates`.
        cams: ``(R_BC (3, 3), p_BC (3,) m)`` of cam0, then of cam1 on a stereo rig (its views after cam0's).
        params: Triangulation settings.
        focal_px: Focal length (px) of the reprojection gate.

    Returns:
        Candidates whose RMS reprojection error reached ``params.max_reprojection_error_px``.
    """
    cand = landmark_candidates(keyframes, landmarks, *limits)
    if not cand:
        return 0
    R_WB = np.stack([kf.x.R_WB for kf in keyframes])
    p_WB = np.stack([kf.x.p_WB for kf in keyframes])
    xys, masks, R_WC, p_WC = [], [], [], []
    for cam, (R_BC, p_BC) in enumerate(cams):
        xy, mask = track_matrix(keyframes, cand, cam=cam)
        xys.append(xy)
        masks.append(mask)
        R_WC.append(R_WB @ R_BC)
        p_WC.append(p_WB + R_WB @ p_BC)
    xy, mask = np.concatenate(xys, axis=1), np.concatenate(masks, axis=1)
    tri = triangulate(np.concatenate(R_WC), np.concatenate(p_WC), xy, mask, params, focal_px)
    for f, fid in enumerate(cand):
        if tri.valid[f]:
            landmarks[fid] = tri.p_W[f].copy()
    return int(np.sum(tri.rms_error_px >= params.max_reprojection_error_px))
