"""The keyframe rule shared by the MSCKF (which frames become clones) and the window (which become keyframes).

A frame becomes a keyframe when the median pixel motion of the features it shares with the last keyframe
reaches ``min_parallax_px``, when fewer than ``min_shared_fraction`` of the last keyframe's features are still
tracked, or after ``every_n_frames`` frames at the latest (VINS-Mono sec. IV-A; lesson ch. 8 "keyframe
selection"). Spacing the keyframes widens the baseline: a hovering drone moves millimetres per frame, too
little parallax to triangulate within a few consecutive frames.

With ``rotation_compensated`` the parallax is measured after removing the rotation since the keyframe
(VINS-Mono sec. IV-A: "short-term integration of gyroscope measurements ... to compensate rotation"): each
shared feature's reference bearing is rotated into the current camera (``R_CrCn``, given by the caller
from its gyro-propagated attitude) before its motion is measured, so a spin in place, which moves every
pixel but gives no baseline to triangulate, does not make keyframes (:func:`compensated_parallax_px`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.vio.frontend import Tracks


@dataclass(frozen=True)
class KeyframeParams:
    """Keyframe-rule settings (defaults: the MSCKF's; the window uses ``every_n_frames=3``, 10 px).

    Attributes:
        every_n_frames: A frame becomes a keyframe at least every n frames (1 = every frame).
        min_parallax_px: Median feature motion (px) since the last keyframe that makes a keyframe.
        min_shared_fraction: Fewer than this fraction of the last keyframe's features still tracked makes a
            keyframe.
        rotation_compensated: Measure the parallax with the rotation since the keyframe removed
            (:func:`compensated_parallax_px`; the caller passes the rotation to
            :meth:`KeyframeSelector.is_keyframe`). Off: raw pixel motion (:func:`shared_motion_px`).
    """

    every_n_frames: int = 6
    min_parallax_px: float = 3.0
    min_shared_fraction: float = 0.5
    rotation_compensated: bool = False


def shared_motion_px(ref: Tracks, now: Tracks) -> np.ndarray:
    """Pixel motion of the features tracked in both frames, in increasing id order.

    Args:
        ref: The earlier frame's tracks.
        now: The later frame's tracks.

    Returns:
        ``|uv_now - uv_ref|`` (px) of each shared feature, shape (S,).
    """
    _, i_ref, i_now = np.intersect1d(ref.ids, now.ids, return_indices=True)
    return np.linalg.norm(now.uv_px[i_now] - ref.uv_px[i_ref], axis=1)


def compensated_parallax_px(ref: Tracks, now: Tracks, R_CrCn: np.ndarray, focal_px: float) -> np.ndarray:
    """Rotation-compensated parallax of the features tracked in both frames, in increasing id order.

    The reference bearing ``[x, y, 1]`` (undistorted normalized coordinates) is rotated into the current
    camera, ``b_n = R_CrCn^T b_r``, and projected; the parallax is the distance to the measured normalized
    point, times ``focal_px``. A pure rotation gives zero; a bearing rotated behind the camera counts as
    infinite parallax.

    Args:
        ref: The earlier (keyframe) frame's tracks.
        now: The later frame's tracks.
        R_CrCn: Rotation of the current camera in the reference camera's frame, shape (3, 3).
        focal_px: Focal length (px) that turns normalized distances into pixels.

    Returns:
        Parallax (px) of each shared feature, shape (S,).
    """
    _, i_ref, i_now = np.intersect1d(ref.ids, now.ids, return_indices=True)
    xy_r = ref.xy_norm[i_ref]
    b_n = np.column_stack([xy_r, np.ones(len(xy_r))]) @ np.asarray(R_CrCn, dtype=float)  # rows: R^T b
    z = b_n[:, 2]
    ok = z > 1e-6
    pred = b_n[:, :2] / np.where(ok, z, 1.0)[:, None]
    d = np.linalg.norm(now.xy_norm[i_now] - pred, axis=1) * focal_px
    return np.where(ok, d, np.inf)


class KeyframeSelector:
    """Applies the keyframe rule to a stream of frames (see the module docstring).

    Args:
        params: Settings.
    """

    def __init__(self, params: KeyframeParams) -> None:
        """Start with no reference keyframe (the first frame tested is a keyframe)."""
        self.params = params
        self.reference: Tracks | None = None
        self.frames_since_keyframe = 0

    def is_keyframe(
        self, tracks: Tracks, R_CrCn: np.ndarray | None = None, focal_px: float | None = None
    ) -> bool:
        """Whether ``tracks``' frame is a keyframe (no state change; see :meth:`accept` and :meth:`skip`).

        Args:
            tracks: The frame's tracks.
            R_CrCn: With ``params.rotation_compensated``: the rotation of this frame's camera in the
                reference keyframe's camera frame, shape (3, 3) (ignored otherwise).
            focal_px: With ``params.rotation_compensated``: the focal length (px).

        Raises:
            ValueError: ``rotation_compensated`` without ``R_CrCn`` or ``focal_px``.
        """
        p = self.params
        ref = self.reference
        if ref is None or self.frames_since_keyframe + 1 >= p.every_n_frames:
            return True
        if p.rotation_compensated:
            if R_CrCn is None or focal_px is None:
                raise ValueError(
                    "KeyframeParams.rotation_compensated needs R_CrCn and focal_px in is_keyframe"
                )
            motion_px = compensated_parallax_px(ref, tracks, R_CrCn, focal_px)
        else:
            motion_px = shared_motion_px(ref, tracks)
        if len(motion_px) < max(p.min_shared_fraction * len(ref.ids), 1):
            return True
        return bool(np.median(motion_px) >= p.min_parallax_px)

    def accept(self, tracks: Tracks) -> None:
        """Record ``tracks``' frame as the new keyframe."""
        self.reference = tracks
        self.frames_since_keyframe = 0

    def skip(self) -> None:
        """Count one more frame that did not become a keyframe."""
        self.frames_since_keyframe += 1

    def forget_reference(self) -> None:
        """Drop the reference keyframe (the next frame tested becomes a keyframe)."""
        self.reference = None
