"""Drift correction ``T_W_corrected_from_W_odom`` and its blending over time.

The pose graph yields a new 4-DOF correction each time a loop is accepted. Applying it at once would make the
published pose jump; :class:`CorrectionBlender` moves from the correction in force to the new one over
``duration_s``: SLERP on the rotation, linear on the translation, so a controller sees a smooth pose.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.loop.frames import RigidTransform, interpolate


class CorrectionBlender:
    """Blends successive corrections ``T_W_corrected_from_W_odom`` in over ``duration_s``.

    Args:
        duration_s: Blend time of a new correction (s); 0 applies it at once.
    """

    def __init__(self, duration_s: float = 1.0) -> None:
        """Identity correction, nothing to blend."""
        if duration_s < 0:
            raise ValueError(f"duration_s must be >= 0, got {duration_s}")
        self.duration_s = float(duration_s)
        self._from = RigidTransform.identity()
        self._to = RigidTransform.identity()
        self._t_start_s = -np.inf

    @property
    def target(self) -> RigidTransform:
        """The latest correction (reached at the end of the blend)."""
        return self._to

    def set_target(self, t_s: float, T_new: RigidTransform, snap: bool = False) -> None:
        """Start blending from the correction in force at ``t_s`` to ``T_new``; ``snap`` applies it at.

        once.
        """
        self._from = T_new if snap else self.value(t_s)
        self._to = T_new
        self._t_start_s = float(t_s)

    def reexpress(self, T_new_from_old: RigidTransform) -> None:
        """The odometry frame moved: carry the corrections over so that every corrected pose stays put.

        A pose ``x_old`` of the former odometry frame is ``x_new = T_new_from_old @ x_old`` now; the
        correction in force and the one being blended to become ``T @ T_new_from_old^-1``, so that
        ``T' @ x_new = T @ x_old``.
        """
        inv = T_new_from_old.inverse()
        self._from, self._to = self._from @ inv, self._to @ inv

    def value(self, t_s: float) -> RigidTransform:
        """Correction in force at ``t_s`` (s)."""
        if self.duration_s == 0 or t_s >= self._t_start_s + self.duration_s:
            return self._to
        alpha = float(np.clip((t_s - self._t_start_s) / self.duration_s, 0.0, 1.0))
        return interpolate(self._from, self._to, alpha)
