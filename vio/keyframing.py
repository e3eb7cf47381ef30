"""The keyframe rule shared by the MSCKF (which frames become clones) and the window (which become keyframes).

A frame becomes a keyframe when the median pixel motion of the features it shares with the last keyframe
reaches ``min_parallax_px``, when fewer than ``min_shared_fraction`` of the last keyframe's features are still
tracked, or after ``every_n_frames`` frames at the latest (VINS-Mono sec. IV-A; lesson ch. 8 "keyframe
selection"). Spacing the keyframes widens the baseline: a hovering drone moves millimetres per frame, too
little parallax to triangulate within a few consecutive frames.
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
    """

    every_n_frames: int = 6
    min_parallax_px: float = 3.0
    min_shared_fraction: float = 0.5


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

    def is_keyframe(self, tracks: Tracks) -> bool:
        """Whether ``tracks``' frame is a keyframe (no state change; see :meth:`accept` and :meth:`skip`)."""
        p = self.params
        ref = self.reference
        if ref is None or self.frames_since_keyframe + 1 >= p.every_n_frames:
            return True
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
