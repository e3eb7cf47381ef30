"""Test helpers: the IMU state's box-plus and box-minus, written out independently of ``State._boxplus``.

The error is ``[dtheta (body), dp, dv, dbg, dba]``, shape (15,), as in :class:`viotb.vio.state.State`.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.lie import exp_so3, log_so3
from viotb.vio.state import ImuValues


def boxplus(x: ImuValues, d: np.ndarray) -> ImuValues:
    """``x`` moved by the error ``d`` (15,): the rotation on the right, the rest added."""
    return ImuValues(
        x.R_WB @ exp_so3(d[0:3]),
        x.p_WB + d[3:6],
        x.v_WB + d[6:9],
        x.gyro_bias_rad_s + d[9:12],
        x.accel_bias_m_s2 + d[12:15],
    )


def boxminus(a: ImuValues, b: ImuValues) -> np.ndarray:
    """The error (15,) that takes ``b`` to ``a`` (box-plus of b and it gives a)."""
    return np.concatenate(
        [
            log_so3(b.R_WB.T @ a.R_WB),
            a.p_WB - b.p_WB,
            a.v_WB - b.v_WB,
            a.gyro_bias_rad_s - b.gyro_bias_rad_s,
            a.accel_bias_m_s2 - b.accel_bias_m_s2,
        ]
    )
