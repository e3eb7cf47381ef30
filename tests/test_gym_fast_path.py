"""The Gymnasium hot-path speed-ups change no number: the fast env against the pre-speed-up code path.

The memoized truth (``ClosedLoopSim.truth``, the ``ground-truth`` feed, the crash test), the memoized gust
decay in plain floats, ``SE3Controller.thrusts`` and ``thrusts_from_estimate`` (no navigation record) and
the split physics step (``Simulation.step_checked``), the env's target memo, arena test and reward sums in
floats, the action check, the ``rot6d`` state vector and the error norms on floats and the wind force written
into the cached ``xfrc_applied`` row are patched back, and the IMU model runs although nothing
reads it, in the second env of each pair, to the code they replaced (copied below), and both envs are stepped
with the same seed and the same actions: observations, rewards, terminations and ``info`` must agree bit for
bit. (The SE(3) controller's float path is not bit-identical to its former numpy form, BLAS sums being fused
multiply-adds: tests/test_se3_float_path.py holds it to that form at round-off.)
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from viotb.controllers import se3
from viotb.controllers.types import NavState
from viotb.envs.gym import base, info, rewards
from viotb.envs.gym.base import VioQuadEnv
from viotb.envs.gym.hover import HoverEnv
from viotb.envs.run.closed_loop import _COS_MAX_TILT, ClosedLoopSim, TruthState
from viotb.envs.sim.simulation import Simulation
from viotb.vio.types import StateEstimate


def _old_truth(self):
    R_WB, p_WB = self.sim.pose()
    return TruthState(self.t_s, R_WB, p_WB, self.sim.velocity_W(), self.sim.angular_velocity_B())


def _old_feed_truth(self):
    tr = self.truth()
    self.estimator.feed_truth(
        StateEstimate(t_s=tr.t_s, R_WB=tr.R_WB, p_WB=tr.p_WB, v_WB=tr.v_WB, omega_B_rad_s=tr.omega_B)
    )


def _old_crashed(self, airborne):
    R_WB, p_WB = self.sim.pose()
    if R_WB[2, 2] < _COS_MAX_TILT:
        return True
    if self._bounds is not None:
        lo, hi = self._bounds
        if (p_WB < np.subtract(lo, 0.5)).any() or (p_WB > np.add(hi, 0.5)).any():
            return True
    return airborne and self.sim.in_collision()


def _old_apply_wind(self, dt):
    w = self.config.wind
    if w.gust_sigma_N <= 0.0 and not any(w.mean_force_W_N):
        return
    if w.gust_sigma_N > 0.0:
        a = np.exp(-dt / w.gust_time_constant_s)
        noise = self._rng_wind.standard_normal(3) * w.gust_sigma_N * np.sqrt(1.0 - a * a)
        noise[2] = 0.0
        self._wind_gust_W = a * np.asarray(self._wind_gust_W) + noise
    self.sim.data.xfrc_applied[self.sim._body_id, :3] = np.asarray(w.mean_force_W_N) + self._wind_gust_W


def _old_set_body_force_W(self, fx, fy, fz):
    self.data.xfrc_applied[self._body_id, :3] = (fx, fy, fz)


def _old_thrusts_from_estimate(self, t_s, est, setpoint):
    return self.update(t_s, NavState.from_estimate(est), setpoint).thrusts_N


def _old_step_checked(self, ctrl, n_steps=1):
    if ctrl is not None:
        self.data.ctrl[:] = ctrl
    mujoco.mj_step(self.model, self.data, n_steps)
    mujoco.mj_forward(self.model, self.data)


def _old_update_target(self):
    p, v = self._target_W(self._t_task)
    self._target_true_W, self._target_v_W = p, v
    self._target_est = self._R_EW @ p + self._t_EW
    self._target_v_est = self._R_EW @ v


def _old_outside_arena(self, p_W):
    return bool((p_W < np.array(self._arena_lo)).any() or (p_W > np.array(self._arena_hi)).any())


def _old_check_action(self, action):
    a = np.asarray(action, dtype=float)
    if a.shape != (4,) or not np.isfinite(a).all():
        raise ValueError("bad action")
    return a.clip(-1.0, 1.0)


def _old_state_vector(self):
    est, health = self._loop.estimate(), self._loop.health()
    var = est.cov.diagonal()
    parts = [
        est.p_WB - self._target_est,
        est.v_WB,
        np.concatenate([est.R_WB[:, 0], est.R_WB[:, 1]]),
        est.omega_B_rad_s,
        self._target_est,
        self._target_v_est,
        var[3:6],
        var[6:9],
        [float(health.tracked_features)],
    ]
    vec = np.nan_to_num(np.concatenate(parts, dtype=np.float32), nan=0.0, posinf=1e6, neginf=-1e6)
    return np.clip(vec, self._state_low, self._state_high)


def _assert_same(a, b, where):
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}[{k}]")
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=where)
    else:
        assert a == b or (a != a and b != b), f"{where}: {a!r} != {b!r}"  # NaN == NaN here


def _rollout(kwargs, actions, old: bool, monkeypatch):
    with monkeypatch.context() as m:
        if old:
            m.setattr(ClosedLoopSim, "truth", _old_truth)
            m.setattr(ClosedLoopSim, "_feed_truth", _old_feed_truth)
            m.setattr(ClosedLoopSim, "crashed", _old_crashed)
            m.setattr(ClosedLoopSim, "_apply_wind", _old_apply_wind)
            m.setattr(VioQuadEnv, "_reads_imu", lambda self: True)
            m.setattr(se3.SE3Controller, "thrusts", lambda self, t, x, sp: self.update(t, x, sp).thrusts_N)
            m.setattr(se3.SE3Controller, "thrusts_from_estimate", _old_thrusts_from_estimate)
            m.setattr(Simulation, "step_checked", _old_step_checked)
            m.setattr(VioQuadEnv, "_update_target", _old_update_target)
            m.setattr(VioQuadEnv, "_outside_arena", _old_outside_arena)
            m.setattr(VioQuadEnv, "_check_action", _old_check_action)
            m.setattr(VioQuadEnv, "_state_vector", _old_state_vector)
            m.setattr(info, "norm3", lambda v: float(np.linalg.norm(v)))
            m.setattr(base, "norm3", lambda v: float(np.linalg.norm(v)))
            m.setattr(Simulation, "set_body_force_W", _old_set_body_force_W)
            m.setattr(rewards, "_sum_sq_diff", lambda a, b: np.sum((a - b) ** 2))
        env = HoverEnv(**kwargs)
        out = [env.reset(seed=3)]
        for a in actions:
            step = env.step(a)
            out.append(step)
            if step[2]:
                break
        env.close()
    return out


@pytest.mark.parametrize(
    ("estimator", "action_type", "n_steps"),
    [
        ("ground-truth", "position", 70),
        ("ground-truth", "velocity", 40),
        ("msckf", "position", 25),
    ],  # 70: 280 gusts
)
def test_fast_path_matches_old_code_bit_for_bit(estimator, action_type, n_steps, monkeypatch):
    """Same seed, same actions: the patched-back old code and the fast code give identical steps."""
    rng = np.random.default_rng(7)
    actions = rng.uniform(-0.3, 0.3, size=(n_steps, 4)).astype(np.float32)
    kwargs = {"estimator": estimator, "frontend": "sim", "action_type": action_type}
    new = _rollout(kwargs, actions, old=False, monkeypatch=monkeypatch)
    old = _rollout(kwargs, actions, old=True, monkeypatch=monkeypatch)
    assert len(new) == len(old) > 10
    for k, (step_new, step_old) in enumerate(zip(new, old, strict=True)):
        for j, (x, y) in enumerate(zip(step_new, step_old, strict=True)):
            _assert_same(x, y, f"step {k} item {j}")


def test_truth_memo_follows_set_pose_and_stays_read_only():
    """A kinematic placement without a physics step must not return the previous pose (memo key)."""
    loop = ClosedLoopSim.__new__(ClosedLoopSim)  # only the truth readers are exercised below
    loop.sim = Simulation("quadrotor", "textured_room")
    loop._truth_key, loop._truth = None, None
    first = loop.truth()
    assert loop.truth() is first
    loop.sim.set_pose(np.eye(3), first.p_WB + np.array([0.3, 0.0, 0.0]))
    moved = loop.truth()
    np.testing.assert_allclose(moved.p_WB - first.p_WB, [0.3, 0.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError):
        moved.p_WB[0] = 0.0


def test_reward_sums_in_floats_equal_numpy_sums():
    """Under 8 entries numpy sums left to right, as the float path does; from 8 on it is numpy's sum."""
    rng = np.random.default_rng(2)
    for n in (1, 3, 4, 7, 8, 12):
        for _ in range(200):
            a, b = rng.normal(size=n) * 10.0 ** rng.uniform(-4, 4, n), rng.normal(size=n)
            assert rewards._sum_sq_diff(a, b) == float(np.sum((a - b) ** 2))
