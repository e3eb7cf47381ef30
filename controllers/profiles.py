"""Time profiles of the setpoint generators in :mod:`viotb.controllers.setpoints`.

The rest-to-rest minimum-jerk blend (Flash and Hogan, J. Neurosci. 1985), a move sampled with it, and the
time warps whose rate ramps smoothly from 0 to 1 (and back).
"""

from __future__ import annotations

import numpy as np
from viotb.controllers.types import FlatOutput


def min_jerk_profile(tau: float) -> tuple[float, float, float, float]:
    """Rest-to-rest minimum-jerk blend ``s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5`` and its 3 derivatives.

    Args:
        tau: Normalised time, clamped to [0, 1].

    Returns:
        ``(s, ds/dtau, d2s/dtau2, d3s/dtau3)``; the first two derivatives vanish at both ends; the third is
        zero outside ``[0, 1)`` (at rest before the start and from the end on).
    """
    t = min(max(tau, 0.0), 1.0)
    s = t**3 * (10.0 - 15.0 * t + 6.0 * t * t)
    ds = 30.0 * t * t * (1.0 - t) ** 2
    d2s = 60.0 * t * (1.0 - t) * (1.0 - 2.0 * t)
    d3s = 60.0 * (1.0 - 6.0 * t + 6.0 * t * t) if 0.0 <= tau < 1.0 else 0.0
    return s, ds, d2s, d3s


def min_jerk_segment(
    p0: np.ndarray | list, p1: np.ndarray | list, yaw0: float, yaw1: float, duration_s: float, t_s: float
) -> FlatOutput:
    """Sample a rest-to-rest minimum-jerk move from ``(p0, yaw0)`` to ``(p1, yaw1)`` at ``t_s``.

    ``p0`` and ``p1`` (m) are 3-vectors, as arrays or lists of floats.
    """
    s, ds, d2s, d3s = min_jerk_profile(t_s / duration_s)
    a = p0 if type(p0) is list else np.asarray(p0, dtype=float).tolist()
    b = p1 if type(p1) is list else np.asarray(p1, dtype=float).tolist()
    dp = [y - x for y, x in zip(b, a, strict=True)]
    dyaw, T = yaw1 - yaw0, duration_s
    T2, T3 = T**2, T**3
    # Per axis in plain floats: the same operations as the 3-vector expressions, without numpy's overhead.
    return FlatOutput.from_floats(
        [x + s * d for x, d in zip(a, dp, strict=True)],
        [d * ds / T for d in dp],
        [d * d2s / T2 for d in dp],
        [d * d3s / T3 for d in dp],
        yaw0 + s * dyaw,
        dyaw * ds / T,
    )


def phase_ramp(t_s: float, ramp_s: float) -> tuple[float, float, float, float]:
    """Time warp whose rate rises from 0 to 1 over ``ramp_s`` by the min-jerk blend, and its derivatives.

    ``w(t) = ramp_s * (2.5 tau^4 - 3 tau^5 + tau^6)`` for ``tau = t / ramp_s < 1`` (the blend's integral),
    ``w(t) = t - ramp_s / 2`` after. Returns ``(w, dw/dt, d2w/dt2, d3w/dt3)``.
    """
    if t_s <= 0.0:
        return 0.0, 0.0, 0.0, 0.0
    if t_s >= ramp_s:
        return t_s - 0.5 * ramp_s, 1.0, 0.0, 0.0
    tau = t_s / ramp_s
    s, ds, d2s, _ = min_jerk_profile(tau)
    return ramp_s * tau**4 * (2.5 - 3.0 * tau + tau * tau), s, ds / ramp_s, d2s / ramp_s**2


def phase_ramp_up_down(t_s: float, duration_s: float, ramp_s: float) -> tuple[float, float, float, float]:
    """:func:`phase_ramp` at the start, mirrored at the end.

    The warped time runs from 0 to ``duration_s - ramp_s`` with zero rate (and derivatives) at both ends.
    """
    if t_s <= 0.5 * duration_s:
        return phase_ramp(t_s, ramp_s)
    w, dw, d2w, d3w = phase_ramp(duration_s - t_s, ramp_s)
    return duration_s - ramp_s - w, dw, -d2w, d3w
