"""Reward terms of the Gymnasium tasks, one small function each, computed from ground truth (the referee)."""

from __future__ import annotations

import numpy as np


def reward_tracking(position_error_m: float, weight: float, scale_m: float) -> float:
    """``weight * exp(-|e_p| / scale_m)``: in ``(0, weight]``, largest on the target."""
    return float(weight * np.exp(-position_error_m / scale_m))


def cost_effort(action: np.ndarray, neutral_action: np.ndarray, weight: float) -> float:
    """``-weight * |a - a_hover|^2``: action away from the one that holds a hover."""
    return float(-weight * np.sum((action - neutral_action) ** 2))


def cost_smoothness(action: np.ndarray, previous_action: np.ndarray, weight: float) -> float:
    """``-weight * |a_k - a_{k-1}|^2``: action changes between policy steps."""
    return float(-weight * np.sum((action - previous_action) ** 2))


def cost_crash(failed: bool, weight: float) -> float:
    """``-weight`` when the episode failed (crash, arena, divergence), else 0."""
    return -float(weight) if failed else 0.0


def reward_waypoints(n_reached: int, weight: float) -> float:
    """``weight`` per waypoint reached during this step."""
    return float(weight * n_reached)
