"""The IMU's share of the dynamic initialization's uncertainty: preintegration noise and bias random walk.

The dynamic solve (:mod:`viotb.vio.init_dynamic`) fits the reprojection errors with every frame pose
predicted from the preintegration from the first frame, taken as exact. The preintegrated increments do
carry noise: white measurement noise (Forster et al. TRO 2017, eqs. 59-63, the covariance of
:class:`~viotb.vio.preintegration.ImuPreintegration`) and the bias random walk, which makes the bias
differ from the one constant bias the solve estimates. Both enter the estimate to first order like a
measurement error of the frame poses. :func:`preintegration_error_cov` gives the joint covariance of the
error states ``e_k = [dtheta, dv, dp]`` (right perturbation, as in the preintegration) of the
preintegrations from the first frame to every frame; :mod:`viotb.vio.init_dynamic` propagates it to the
estimated scale, velocity and gravity direction (a first-order "sandwich" covariance of the estimator that
is actually used).

Composition of a preintegration ``0 -> i`` with ``i -> j`` (Forster eq. 33 with ``R_0i``): the error at j is
``e_j = Phi(j, i) e_i + (noise of i -> j)`` with (``R_i = dR_0i``, ``v_i = dv_0i``, ``p_i = dp_0i``,
``t = t_j - t_i``)::

    Phi(j, i) = [[(R_i^T R_j)^T,                       0,   0],
                 [-[v_j - v_i]x R_i,                   I,   0],
                 [-[p_j - p_i - v_i t]x R_i,           t I, I]]

so ``Cov(e_j, e_i) = Phi(j, i) Cov(e_i)``. A bias step ``db`` from ``t_i`` on changes only the part
``i -> j``: ``de_j = (J_b(0 -> j) - Phi(j, i) J_b(0 -> i)) db``, with ``J_b`` the 9x6 bias Jacobian
``[[d_R_d_bg, 0], [d_v_d_bg, d_v_d_ba], [d_p_d_bg, d_p_d_ba]]``. For the random walk (white steps of
density ``q``) the effect of a step between two consecutive targets is interpolated linearly in its time
between the effects of steps at the two targets.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.lie import skew
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.types import ImuNoise


def _bias_jacobian(pim: ImuPreintegration) -> np.ndarray:
    """``d e / d [bg, ba]`` of one preintegration, shape (9, 6) (rows ``[dtheta, dv, dp]``)."""
    J = np.zeros((9, 6))
    J[0:3, 0:3] = pim.d_R_d_bg
    J[3:6, 0:3], J[3:6, 3:6] = pim.d_v_d_bg, pim.d_v_d_ba
    J[6:9, 0:3], J[6:9, 3:6] = pim.d_p_d_bg, pim.d_p_d_ba
    return J


def transition(pim_i: ImuPreintegration, pim_j: ImuPreintegration) -> np.ndarray:
    """``Phi(j, i)`` of the module docstring: the error of ``0 -> i`` carried into ``0 -> j``, shape (9, 9).

    Args:
        pim_i: Preintegration from the common start to ``t_i``.
        pim_j: Preintegration from the same start to ``t_j >= t_i`` (same bias linearization point).
    """
    R_i, R_j = pim_i.delta_R, pim_j.delta_R
    v_i, p_i = pim_i.delta_v, pim_i.delta_p
    t = pim_j.dt_s - pim_i.dt_s
    Phi = np.eye(9)
    Phi[0:3, 0:3] = R_j.T @ R_i
    Phi[3:6, 0:3] = -skew(pim_j.delta_v - v_i) @ R_i
    Phi[6:9, 0:3] = -skew(pim_j.delta_p - p_i - v_i * t) @ R_i
    Phi[6:9, 3:6] = t * np.eye(3)
    return Phi


def preintegration_error_cov(pims: list[ImuPreintegration], noise: ImuNoise) -> np.ndarray:
    """Joint covariance of the errors of preintegrations from one start to increasing end times.

    Args:
        pims: Preintegrations sharing their start and bias linearization point, ordered by ``dt_s``
            (e.g. snapshots of one running preintegration), N of them.
        noise: IMU noise densities; the white-noise part is already in each ``pim.cov``, the random-walk
            densities add the bias drift.

    Returns:
        Covariance of ``[e_0, ..., e_{N-1}]``, ``e_k = [dtheta, dv, dp]`` of ``pims[k]``, shape (9N, 9N).
    """
    n = len(pims)
    Jb = [_bias_jacobian(pm) for pm in pims]
    C = np.zeros((9 * n, 9 * n))
    walk = np.concatenate(
        [
            np.full(3, noise.gyro_random_walk_rad_s2_sqrthz**2),
            np.full(3, noise.accel_random_walk_m_s3_sqrthz**2),
        ]
    )
    B_prev = None
    for i in range(n):
        # 1. White noise: Cov(e_j, e_i) = Phi(j, i) Cov(e_i) for j >= i.
        S_i = pims[i].cov
        C[9 * i : 9 * i + 9, 9 * i : 9 * i + 9] += S_i
        B = np.zeros((9 * n, 6))  # every error's change under a bias step at t_i
        for j in range(i + 1, n):
            Phi = transition(pims[i], pims[j])
            block = Phi @ S_i
            C[9 * j : 9 * j + 9, 9 * i : 9 * i + 9] += block
            C[9 * i : 9 * i + 9, 9 * j : 9 * j + 9] += block.T
            B[9 * j : 9 * j + 9] = Jb[j] - Phi @ Jb[i]
        # 2. Bias random walk over [t_{i-1}, t_i]: a step at s changes the errors by f(s), taken linear
        #    between B_prev (s = t_{i-1}) and B (s = t_i); integral of q f f^T ds over the interval.
        if B_prev is not None:
            q = walk * (pims[i].dt_s - pims[i - 1].dt_s)
            cross = (B_prev * q) @ B.T
            C += ((B_prev * q) @ B_prev.T + (B * q) @ B.T) / 3.0 + (cross + cross.T) / 6.0
        B_prev = B
    return 0.5 * (C + C.T)
