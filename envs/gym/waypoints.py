"""Waypoints task (``viotb/Waypoints-v0``): fly through random points on the VIO estimate."""

from __future__ import annotations

import numpy as np
from viotb.envs.gym.base import VioQuadEnv
from viotb.envs.gym.config import WaypointsEnvConfig
from viotb.envs.gym.rewards import reward_waypoints


class WaypointsEnv(VioQuadEnv):
    """Fly through a random sequence of points on the VIO estimate (``viotb/Waypoints-v0``).

    ## Description
    ``n_waypoints`` points are drawn uniformly in a box at reset; the target is the current point, and it
    advances when the TRUE position comes within ``reach_radius_m`` (the simulator is the referee). The
    observation's target switches then.

    Spaces, rewards, starts and episode end: see :class:`~viotb.envs.gym.base.VioQuadEnv`.
    """

    config_type = WaypointsEnvConfig

    def _task_reset(self, rng: np.random.Generator) -> None:
        cfg = self.config
        lo, hi = np.asarray(cfg.waypoint_low_W_m), np.asarray(cfg.waypoint_high_W_m)
        self.waypoints_W = rng.uniform(lo, hi, size=(cfg.n_waypoints, 3))
        self._index = 0

    def _target_W(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return self.waypoints_W[min(self._index, len(self.waypoints_W) - 1)].copy(), np.zeros(3)

    def _task_step(self, p_true_W: np.ndarray) -> tuple[dict[str, float], bool]:
        n = len(self.waypoints_W)
        reached = 0
        if (
            self._index < n
            and np.linalg.norm(p_true_W - self.waypoints_W[self._index]) < self.config.reach_radius_m
        ):
            reached = 1
            self._index += 1
        return {"waypoint": reward_waypoints(reached, self.config.rewards.waypoint)}, self._index >= n
