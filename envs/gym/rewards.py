"""Reward terms of the Gymnasium tasks, one small function each, computed from ground truth (the referee)."""

from __future__ import annotations

import numpy as np


def reward_tracking(position_error_m: float, weight: float, scale_m: float) -> float:
    """``weight * exp(-|e_p| / scale_m)``: in ``(0, weight]``, largest on the target."""
    return float(weight * np.exp(-position_error_m / scale_m))


def _sum_sq_diff(a: np.ndarray, b: np.ndarray) -> float:
    """``np.sum((a - b) ** 2)``; under 8 entries in floats, left to right as numpy sums them (no arrays)."""
    d = (a - b).tolist()
    if len(d) >= 8:  # numpy's pairwise summation starts at 8 entries
        return float(np.sum(np.square(d)))
    total = 0.0
    for x in d:
        total += x * x
    return total


def cost_effort(action: np.ndarray, neutral_action: np.ndarray, weight: float) -> float:
    """``-weight * |a - a_hover|^2``: action away from the one that holds a hover."""
    return float(-weight * _sum_sq_diff(action, neutral_action))


def cost_smoothness(action: np.ndarray, previous_action: np.ndarray, weight: float) -> float:
    """``-weight * |a_k - a_{k-1}|^2``: action changes between policy steps."""
    return float(-weight * _sum_sq_diff(action, previous_action))


def cost_crash(failed: bool, weight: float) -> float:
    """``-weight`` when the episode failed (crash, arena, divergence), else 0."""
    return -float(weight) if failed else 0.0


def reward_waypoints(n_reached: int, weight: float) -> float:
    """``weight`` per waypoint reached during this step."""
    return float(weight * n_reached)
