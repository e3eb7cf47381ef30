"""When the sliding-window optimizer has diverged: non-finite values, a runaway covariance, cost blow-ups."""

from __future__ import annotations

import numpy as np
from viotb.vio.state import POS, ImuValues
from viotb.vio.window_params import WindowParams


def divergence_reason(
    x: ImuValues,
    cov: np.ndarray,
    params: WindowParams,
    cost_per_residual: float,
    used: int,
    n_bad: int,
    blowups: int,
) -> tuple[str, int]:
    """Why the window diverged after a keyframe ("" when it did not), and the updated blow-up count.

    A keyframe is a blow-up when the final cost per measurement residual (prior excluded) exceeds
    ``params.max_cost_per_residual``, or when more than ``params.runaway_reject_ratio`` of its gated
    features (at least ``params.runaway_min_features``) were outliers or failed the triangulation gate;
    ``params.blowup_keyframes`` blow-ups in a row declare divergence.

    Args:
        x: The newest keyframe's values.
        cov: Its covariance, shape (NX, NX).
        params: The thresholds.
        cost_per_residual: The solve's final measurement cost per residual.
        used: Landmarks kept by the solve.
        n_bad: Features rejected at this keyframe (outliers and failed triangulations).
        blowups: Consecutive blow-up keyframes before this one.

    Returns:
        ``(reason, blowups)``.
    """
    vals = [x.R_WB, x.p_WB, x.v_WB, x.gyro_bias_rad_s, x.accel_bias_m_s2, cov]
    if not all(np.all(np.isfinite(a)) for a in vals):
        return "non-finite value in the newest keyframe state or covariance", blowups
    pos_sigma = float(np.sqrt(max(np.max(np.diag(cov)[POS : POS + 3]), 0.0)))
    if pos_sigma > params.max_position_sigma_m:
        return (
            f"position sigma {pos_sigma:.1f} m exceeds max_position_sigma_m={params.max_position_sigma_m}",
            blowups,
        )
    c = cost_per_residual
    gated = used + n_bad
    runaway = gated >= params.runaway_min_features and n_bad > params.runaway_reject_ratio * gated
    blowups = blowups + 1 if (c > params.max_cost_per_residual or runaway) else 0
    if blowups >= params.blowup_keyframes:
        return (
            f"cost blow-up in {blowups} consecutive keyframes: cost per measurement residual "
            f"{c:.1f} (limit {params.max_cost_per_residual}), {n_bad} of {gated} features rejected as "
            f"outliers or inconsistent (limit {params.runaway_reject_ratio:.0%})",
            blowups,
        )
    return "", blowups
