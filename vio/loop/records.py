"""Records the loop closer hands out: accepted closures and per-frame timings."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LoopClosure:
    """A verified loop (or relocalization) between the current keyframe and an older one.

    Attributes:
        t_query_s: Time of the query keyframe (s).
        t_match_s: Time of the matched keyframe (s).
        p_xyz: Position of the query body in the match body frame (m), shape (3,).
        quat_xyzw: Rotation query body -> match body, Hamilton ``(x, y, z, w)``, shape (4,).
        inliers: PnP inliers.
        rms_px: RMS reprojection error of the inliers (px).
        relocalization: True when it localized a sequence (after tracking loss or into a loaded map).
    """

    t_query_s: float
    t_match_s: float
    p_xyz: np.ndarray
    quat_xyzw: np.ndarray
    inliers: int
    rms_px: float = 0.0
    relocalization: bool = False

    def as_row(self) -> dict[str, float | int | bool]:
        """Flat record (for ``loop_closures.csv``)."""
        row: dict[str, float | int | bool] = {"t_query_s": self.t_query_s, "t_match_s": self.t_match_s}
        row.update({f"p_{a}": float(v) for a, v in zip("xyz", self.p_xyz, strict=True)})
        row.update({f"q{a}": float(v) for a, v in zip("xyzw", self.quat_xyzw, strict=True)})
        row.update({"inliers": self.inliers, "rms_px": self.rms_px, "relocalization": self.relocalization})
        return row


@dataclass(frozen=True)
class FrameTiming:
    """Wall time spent on one frame (ms).

    Attributes:
        t_s: Frame time (s).
        total_ms: All of ``add_frame``.
        keyframe: Whether the frame became a keyframe.
        features_ms: ORB extraction and triangulation.
        query_ms: Bag-of-words quantization and scoring.
        verify_ms: PnP verification of the candidates.
        optimize_ms: Pose-graph solve (only when a loop was accepted).
    """

    t_s: float
    total_ms: float
    keyframe: bool = False
    features_ms: float = 0.0
    query_ms: float = 0.0
    verify_ms: float = 0.0
    optimize_ms: float = 0.0
