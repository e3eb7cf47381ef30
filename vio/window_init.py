"""The window's first prior after a static initialization: tilt and horizontal accelerometer bias coupled.

A static initializer (open_vins' StaticInitializer, :mod:`viotb.vio.initialization`) takes the gravity
direction from the mean specific force ``f = R_WB^T (g z_W) + b_a`` and sets the horizontal accelerometer bias
to zero, so whatever horizontal bias the sensor has is read as tilt. With the error state ``R = R_est
Exp(dtheta)``, ``db = b - b_est`` and ``u = R_est^T z_W`` (up in B), ``R^T z_W = Exp(-dtheta) u ~ u - dtheta x
u``, and ``f`` is matched exactly by both states::

    g (u - dtheta x u) + b = g u + b_est   =>   db = g dtheta x u = A dtheta,   A = -g [u]x

(the rotation about ``u``, the yaw gauge, leaves the bias alone). The initializer reports the two errors as
independent (``cov_diag``: tilt 0.01 rad, bias 0.1 m/s^2 = 0.01 rad x g): to the window the gravity that a
tilt error leaks into the predicted acceleration is then not cancelled by the bias error that goes with it,
and its position covariance grows by centimetres in a hover whose error stays under a millimetre (position
NEES 0.1-0.3).
:func:`couple_static_tilt_bias` gives the prior that correlation: ``Cov(db, dtheta) = A P_tt``, ``Cov(db) = A
P_tt A^T`` plus the bias variance along ``u`` and a small independent horizontal part (the averaged
accelerometer noise and the bias drift over the still window; it keeps the prior invertible).
"""

from __future__ import annotations

import numpy as np
from viotb.vio.lie import skew
from viotb.vio.types import GRAVITY_M_S2


def couple_static_tilt_bias(cov: np.ndarray, R_WB: np.ndarray, independent_sigma_m_s2: float) -> np.ndarray:
    """The covariance of a static initialization with its tilt and horizontal accelerometer bias coupled.

    Args:
        cov: Initial covariance ``[dtheta, dp, dv, dbg, dba]``, shape (15, 15), with independent orientation
            and accelerometer-bias blocks (:func:`viotb.vio.state.read_init_record`).
        R_WB: Initial orientation, shape (3, 3).
        independent_sigma_m_s2: 1-sigma (m/s^2) of the horizontal bias left independent of the tilt (> 0).

    Returns:
        The coupled covariance, shape (15, 15): the orientation block as given, ``Cov(dba, dtheta) = A
        P_tt`` and ``Cov(dba) = A P_tt A^T + s_u^2 u u^T + sigma_i^2 (I - u u^T)`` with ``A = -g [u]x``,
        ``u = R_WB^T z_W`` and ``s_u^2 = u^T Cov(dba) u`` (module docstring).

    Raises:
        ValueError: A non-positive ``independent_sigma_m_s2``.
    """
    if not independent_sigma_m_s2 > 0.0:
        raise ValueError(f"independent_sigma_m_s2 must be > 0, got {independent_sigma_m_s2!r}")
    out = np.array(cov, dtype=float, copy=True)
    u = np.asarray(R_WB, dtype=float).T @ np.array([0.0, 0.0, 1.0])
    A = -GRAVITY_M_S2 * skew(u)
    P_tt = out[0:3, 0:3]
    s_u2 = float(u @ out[12:15, 12:15] @ u)
    horizontal = np.eye(3) - np.outer(u, u)
    out[12:15, 0:3] = A @ P_tt
    out[0:3, 12:15] = out[12:15, 0:3].T
    out[12:15, 12:15] = A @ P_tt @ A.T + s_u2 * np.outer(u, u) + independent_sigma_m_s2**2 * horizontal
    return 0.5 * (out + out.T)
