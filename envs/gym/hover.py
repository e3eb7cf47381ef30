"""Hover task (``viotb/Hover-v0``): hold a point against wind gusts on the VIO estimate."""

from __future__ import annotations

import numpy as np
from viotb.envs.gym.base import VioQuadEnv
from viotb.envs.gym.config import HoverEnvConfig


class HoverEnv(VioQuadEnv):
    """Hold a point against wind gusts, flying on the VIO estimate (``viotb/Hover-v0``).

    ## Description
    A 1.2 kg quadrotor in the textured room must hold ``start_p_W_m`` (1.5 m above the origin) while
    horizontal wind gusts push it; its observations come from the estimator (MSCKF on simulated features by
    default), so estimator drift shows up as hover error that the policy cannot see.

    Spaces, rewards, starts and episode end: see :class:`~viotb.envs.gym.base.VioQuadEnv`.
    """

    config_type = HoverEnvConfig

    def _target_W(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.config.start_p_W_m, dtype=float), np.zeros(3)
