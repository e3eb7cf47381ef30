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
from viotb.vio.lie import log_so3, skew_batch
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
    R, v, p, t = _stack([pim_i, pim_j])
    return _transitions(R, v, p, t, 0, np.array([1]))[0]


def _stack(pims: list[ImuPreintegration]):
    """``(delta_R (N, 3, 3), delta_v (N, 3), delta_p (N, 3), dt_s (N,))`` of the preintegrations."""
    return (
        np.stack([pm.delta_R for pm in pims]),
        np.stack([pm.delta_v for pm in pims]),
        np.stack([pm.delta_p for pm in pims]),
        np.array([pm.dt_s for pm in pims]),
    )


def _transitions(R, v, p, t, i: int, js: np.ndarray) -> np.ndarray:
    """``Phi(j, i)`` for every ``j`` in ``js``, shape (len(js), 9, 9)."""
    m = len(js)
    dt = t[js] - t[i]
    Phi = np.tile(np.eye(9), (m, 1, 1))
    Phi[:, 0:3, 0:3] = np.transpose(R[js], (0, 2, 1)) @ R[i]
    Phi[:, 3:6, 0:3] = -skew_batch(v[js] - v[i]) @ R[i]
    Phi[:, 6:9, 0:3] = -skew_batch(p[js] - p[i] - dt[:, None] * v[i]) @ R[i]
    Phi[:, 6:9, 3:6] = dt[:, None, None] * np.eye(3)
    return Phi


def _reading_jacobian(x: np.ndarray) -> np.ndarray:
    """``d (dM x) / d vec(dM)`` for a 3x3 sensor-matrix error ``dM`` (columns stacked), shape (3, 9)."""
    return np.kron(x[None, :], np.eye(3))


def preintegration_error_cov(
    pims: list[ImuPreintegration],
    noise: ImuNoise,
    scale_sigma: float = 0.0,
    misalignment_sigma_rad: float = 0.0,
) -> np.ndarray:
    """Joint covariance of the errors of preintegrations from one start to increasing end times.

    Args:
        pims: Preintegrations sharing their start and bias linearization point, ordered by ``dt_s``
            (e.g. snapshots of one running preintegration), N of them.
        noise: IMU noise densities; the white-noise part is already in each ``pim.cov``, the random-walk
            densities add the bias drift.
        scale_sigma: 1-sigma of the uncalibrated scale factors of both sensors (reading ``(I + dM) x``,
            the diagonal of ``dM``), which the estimators do not estimate; 0: none.
        misalignment_sigma_rad: 1-sigma of the off-diagonal elements of ``dM`` (axis misalignment).
            A sensor-matrix error acts like a bias ``dM x(t)`` that follows the reading: here the mean
            reading of each interval between targets (rotation and velocity increments in the frame
            at its start), its effect the difference of the bias-step effects at the two ends.

    Returns:
        Covariance of ``[e_0, ..., e_{N-1}]``, ``e_k = [dtheta, dv, dp]`` of ``pims[k]``, shape (9N, 9N).
    """
    n = len(pims)
    R, v, p, t = _stack(pims)
    Jb = np.stack([_bias_jacobian(pm) for pm in pims])  # (n, 9, 6)
    C = np.zeros((n, 9, n, 9))
    walk = np.concatenate(
        [
            np.full(3, noise.gyro_random_walk_rad_s2_sqrthz**2),
            np.full(3, noise.accel_random_walk_m_s3_sqrthz**2),
        ]
    )
    W = np.zeros((9 * n, 9 * n))
    K = np.zeros((9 * n, 18))  # effect of vec(dM_gyro), vec(dM_accel)
    B_prev = None
    for i in range(n):
        # 1. White noise: Cov(e_j, e_i) = Phi(j, i) Cov(e_i) for j >= i.
        S_i = pims[i].cov
        C[i, :, i, :] += S_i
        js = np.arange(i + 1, n)
        B = np.zeros((n, 9, 6))  # every error's change under a bias step at t_i
        if js.size:
            Phi = _transitions(R, v, p, t, i, js)
            block = Phi @ S_i
            C[js, :, i, :] += block
            C[i, :, js, :] += np.transpose(block, (0, 2, 1))
            B[js] = Jb[js] - Phi @ Jb[i]
        # 2. Bias random walk over [t_{i-1}, t_i]: a step at s changes the errors by f(s), taken linear
        #    between B_prev (s = t_{i-1}) and B (s = t_i); integral of q f f^T ds over the interval.
        B = B.reshape(9 * n, 6)
        if B_prev is not None:
            q = walk * (t[i] - t[i - 1])
            cross = (B_prev * q) @ B.T
            W += ((B_prev * q) @ B_prev.T + (B * q) @ B.T) / 3.0 + (cross + cross.T) / 6.0
            # 3. Sensor-matrix errors: a bias pulse dM x over the interval, x its mean reading.
            dt = t[i] - t[i - 1]
            if dt > 0.0:
                w_mean = log_so3(R[i - 1].T @ R[i]) / dt
                f_mean = R[i - 1].T @ (v[i] - v[i - 1]) / dt
                pulse = B_prev - B
                K[:, 0:9] += pulse[:, 0:3] @ _reading_jacobian(w_mean)
                K[:, 9:18] += pulse[:, 3:6] @ _reading_jacobian(f_mean)
        B_prev = B
    lam = np.tile(np.where(np.eye(3).ravel(order="F") > 0, scale_sigma, misalignment_sigma_rad) ** 2, 2)
    C = C.reshape(9 * n, 9 * n) + W + (K * lam) @ K.T
    return 0.5 * (C + C.T)
