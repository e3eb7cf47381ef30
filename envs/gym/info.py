"""The ``info`` dict of the viotb Gymnasium envs, in the two forms of ``VioEnvConfig.info``.

``full`` (the default): ground truth and diagnostics, arrays included (``p_true_W_m``, ``v_true_W_m_s``,
``R_true_WB``, ``target_W_m``), the health conditions and the reward terms both flat (``reward_<name>``)
and nested (``reward_components``). ``flat``: the scalar entries only (``t_s``, ``position_error_m``,
``estimate_error_m``, ``tracked_features``, ``termination_reason`` and ``reward_<name>``), the same values.
A vector env merges every key of every worker's ``info`` into per-key arrays and masks at every step
(Gymnasium's ``VectorEnv._add_info``: two small arrays per key and env, recursing into nested dicts), so
training on many envs asks for the short one; the scalars are what a training loop logs per step.
"""

from __future__ import annotations

import numpy as np
from viotb.envs.run.closed_loop import ClosedLoopSim
from viotb.envs.sim.checks import norm3


def step_info(
    loop: ClosedLoopSim,
    target_true_W: np.ndarray,
    R_EW: np.ndarray,
    t_EW: np.ndarray,
    components: dict[str, float],
    reason: str,
    mode: str,
) -> dict:
    """Ground truth and diagnostics of the current step (never part of the observation).

    Args:
        loop: The episode's closed loop (truth, estimate, health).
        target_true_W: Target position in the world frame (m), shape (3,).
        R_EW: Rotation of the world into the estimator frame, shape (3, 3).
        t_EW: Translation of the world into the estimator frame (m), shape (3,).
        components: Reward terms of the step, by name.
        reason: Termination reason, ``""`` while running.
        mode: One of ``viotb.envs.gym.config.INFO_MODES``.

    Returns:
        The info dict (see the module docstring).
    """
    tr = loop.truth()
    est = loop.estimate()
    health = loop.health()
    estimate_error_m = np.nan
    if est is not None:
        p_est_W = R_EW.T @ (est.p_WB - t_EW)
        estimate_error_m = norm3(p_est_W - tr.p_WB)
    info = {"t_s": tr.t_s}
    if mode == "full":
        info.update(
            {
                "p_true_W_m": tr.p_WB.copy(),
                "v_true_W_m_s": tr.v_WB.copy(),
                "R_true_WB": tr.R_WB.copy(),
                "target_W_m": target_true_W.copy(),
            }
        )
    info["position_error_m"] = norm3(tr.p_WB - target_true_W)
    info["estimate_error_m"] = estimate_error_m
    info["tracked_features"] = int(health.tracked_features)
    if mode == "full":
        info["conditions"] = tuple(health.conditions)
    info["termination_reason"] = reason
    if mode == "full":
        info["reward_components"] = dict(components)
    for name, value in components.items():
        info[f"reward_{name}"] = value
    return info
