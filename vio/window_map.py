"""Bookkeeping of the sliding-window optimizer: keyframes, the IMU links between them, landmark tracks.

Each :class:`Keyframe` holds its values and its observations (feature id -> normalized xy); the landmarks are
a dict feature id -> point in W. The functions here select features to triangulate, gather observations
into the index arrays the factors take, and drop a landmark with all its observations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.state import ImuValues


@dataclass
class Keyframe:
    """One keyframe of the window.

    Attributes:
        key: Unique id (it names the keyframe in the linear prior).
        t_s: Time (s, IMU clock).
        x: Its values.
        obs: Feature id -> undistorted normalized coordinates, shape (2,).
        still: It carries a zero-velocity factor.
    """

    key: int
    t_s: float
    x: ImuValues
    obs: dict[int, np.ndarray]
    still: bool = False


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
    keyframes: list[Keyframe], landmarks: dict[int, np.ndarray], min_track_length: int, max_landmarks: int
) -> list[int]:
    """Features seen in at least ``min_track_length`` keyframes that are not landmarks yet.

    Longest tracks first (then by id), as many as ``max_landmarks`` leaves room for.
    """
    counts: dict[int, int] = {}
    for kf in keyframes:
        for fid in kf.obs:
            if fid not in landmarks:
                counts[fid] = counts.get(fid, 0) + 1
    room = max_landmarks - len(landmarks)
    cand = sorted((c for c in counts if counts[c] >= min_track_length), key=lambda f: (-counts[f], f))
    return cand[: max(room, 0)]


def track_matrix(keyframes: list[Keyframe], fids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Observations of features ``fids`` (F) in every keyframe (K).

    Returns:
        ``(xy_norm (F, K, 2), mask (F, K))``, zero where ``mask`` is False.
    """
    K = len(keyframes)
    xy = np.zeros((len(fids), K, 2))
    mask = np.zeros((len(fids), K), dtype=bool)
    for k, kf in enumerate(keyframes):
        for f, fid in enumerate(fids):
            val = kf.obs.get(fid)
            if val is not None:
                xy[f, k], mask[f, k] = val, True
    return xy, mask


def observations(keyframes: list[Keyframe], lm_ids: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(kf index (M,), landmark index (M,), xy_norm (M, 2))`` of the landmarks ``lm_ids``."""
    index = {fid: j for j, fid in enumerate(lm_ids)}
    ks, ls, xys = [], [], []
    for k, kf in enumerate(keyframes):
        for fid, xy in kf.obs.items():
            j = index.get(fid)
            if j is not None:
                ks.append(k)
                ls.append(j)
                xys.append(xy)
    return np.array(ks, dtype=np.int64), np.array(ls, dtype=np.int64), np.array(xys).reshape(-1, 2)


def drop_landmark(keyframes: list[Keyframe], landmarks: dict[int, np.ndarray], fid: int) -> None:
    """Remove landmark ``fid`` and its observations in every keyframe."""
    landmarks.pop(fid, None)
    for kf in keyframes:
        kf.obs.pop(fid, None)
