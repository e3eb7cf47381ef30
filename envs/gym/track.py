"""Track task (``viotb/Track-v0``): follow a moving figure-8 reference on the VIO estimate."""

from __future__ import annotations

import numpy as np
from viotb.controllers import FigureEight
from viotb.envs.gym.base import VioQuadEnv
from viotb.envs.gym.config import TrackEnvConfig


class TrackEnv(VioQuadEnv):
    """Follow a moving figure-8 reference on the VIO estimate (``viotb/Track-v0``).

    ## Description
    The target moves along a lemniscate of Gerono (``controllers.setpoints.FigureEight``) centred at
    ``start_p_W_m``, starting at rest there; the observation includes its position and velocity.

    Spaces, rewards, starts and episode end: see :class:`~viotb.envs.gym.base.VioQuadEnv`.
    """

    config_type = TrackEnvConfig

    def _task_reset(self, rng: np.random.Generator) -> None:
        cfg = self.config
        c = np.asarray(cfg.start_p_W_m, dtype=float)
        self._figure8 = FigureEight(
            center_xy_m=c[:2],
            size_m=np.asarray(cfg.figure8_size_m, dtype=float),
            period_s=cfg.figure8_period_s,
            altitude_m=float(c[2]),
            ramp_s=cfg.figure8_ramp_s,
        )

    def _target_W(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        s = self._figure8.sample(t_s)
        return np.array(s.p_W), np.array(s.v_W)
