"""Random navigation states for the propagation and window tests (one generator, several spreads)."""

from __future__ import annotations

import numpy as np
from viotb.vio.lie import exp_so3
from viotb.vio.state import ImuValues


def random_imu_values(
    rng: np.random.Generator,
    sigma_p_m: float = 1.0,
    sigma_v_m_s: float = 1.0,
    sigma_bg_rad_s: float = 0.01,
    sigma_ba_m_s2: float = 0.1,
) -> ImuValues:
    """An IMU state: a random attitude (rotation vector ~ N(0, 1) rad), zero-mean normal p, v, biases."""
    return ImuValues(
        exp_so3(rng.normal(size=3)),
        rng.normal(0.0, sigma_p_m, 3),
        rng.normal(0.0, sigma_v_m_s, 3),
        rng.normal(0.0, sigma_bg_rad_s, 3),
        rng.normal(0.0, sigma_ba_m_s2, 3),
    )
