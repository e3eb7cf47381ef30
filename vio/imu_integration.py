"""One IMU interval, or a span of them, integrated: the nominal state and the error-state transition.

The model, the integrators and the first-estimates transition are described in :mod:`viotb.vio.propagator`
(which re-exports everything here). Each interval is split in two steps so that a caller that needs only
the mean, at IMU rate, does not pay for the Jacobians:

1. :func:`integrate_mean` integrates the nominal state and keeps the rotations and angles it computed
   (:class:`StepMean`);
2. :func:`step_transition` builds the interval's 15 x 15 transition ``Phi`` from that record, and
   :func:`step_transitions` the transitions of many such records in one array operation.

:func:`integrate_step` is the two in sequence; :func:`integrate_batch` chains a whole span and stacks its
``Phi``; :func:`discrete_noise` / :func:`discrete_noise_batch` give the process noise ``Q`` from ``Phi``.
"""

from __future__ import annotations

from enum import Enum
from typing import NamedTuple

import numpy as np
from viotb.vio.imu_intrinsics import ImuIntrinsics, input_jacobian
from viotb.vio.lie import (
    exp_so3,
    exp_so3_batch,
    right_jacobian_so3,
    right_jacobian_so3_batch,
    skew,
    skew_batch,
)
from viotb.vio.state import BA, BG, IMU_DIM, POS, THETA, VEL, ImuValues
from viotb.vio.types import ImuNoise, gravity_W


class Integration(str, Enum):
    """Integration method of the nominal state."""

    DISCRETE = "discrete"
    RK4 = "rk4"


class StepMean(NamedTuple):
    """One integrated interval: the new state and what its transition matrix is built from.

    Attributes:
        start: State at the start of the interval.
        new: State at the end.
        method: Integration method.
        dt: Interval length (s).
        theta: Rotation vector over the interval (rad), shape (3,).
        R1: End orientation ``R_WB``, shape (3, 3).
        theta_m: RK4: rotation vector to mid-interval (rad), shape (3,); None for DISCRETE.
        Rm: RK4: mid-interval orientation, shape (3, 3); None for DISCRETE.
        am: RK4: mean bias-corrected specific force (m/s^2), shape (3,); None for DISCRETE.
        a1: RK4: bias-corrected specific force at the end (m/s^2), shape (3,); None for DISCRETE.
        raw: With online IMU intrinsics: the bias-removed raw readings ``[w_m0, w_m1, a_m0, a_m1] - b``
            the corrected ones came from, shape (4, 3) (:func:`intrinsic_columns`); else None.
        packed: From the compiled path (:func:`viotb.vio.imu_kernels_calls.mean_record`): the kernel's
            record that the arrays above are views of (:data:`viotb.vio.imu_kernels.RECORD_ROWS`); else None.
    """

    start: ImuValues
    new: ImuValues
    method: Integration
    dt: float
    theta: np.ndarray
    R1: np.ndarray
    theta_m: np.ndarray | None
    Rm: np.ndarray | None
    am: np.ndarray | None
    a1: np.ndarray | None
    raw: np.ndarray | None = None
    packed: np.ndarray | None = None


def integrate_mean(
    imu: ImuValues,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: float,
    method: Integration,
    raw: np.ndarray | None = None,
) -> StepMean:
    """Integrate the nominal state over one IMU interval (no Jacobians).

    Args:
        imu: State at the start of the interval (biases are held).
        w0: Bias-corrected angular rate (rad/s) at the start, shape (3,); ``w1`` at the end.
        w1: See ``w0``.
        a0: Bias-corrected specific force (m/s^2) at the start, shape (3,); ``a1`` at the end.
        a1: See ``a0``.
        dt: Interval length (s), > 0.
        method: Integration method.
        raw: Kept in the record for the intrinsic columns (see :class:`StepMean`); None without them.

    Returns:
        The :class:`StepMean` record (``.new`` is the state at the end).
    """
    g = gravity_W()
    R0, p0, v0 = imu.R_WB, imu.p_WB, imu.v_WB
    theta_m = Rm = am = None
    if method == Integration.DISCRETE:
        w, a = 0.5 * (w0 + w1), 0.5 * (a0 + a1)
        theta = w * dt
        R1 = R0 @ exp_so3(theta)
        Ra = R0 @ a
        v1 = v0 + (g + Ra) * dt
        p1 = p0 + v0 * dt + 0.5 * (g + Ra) * dt * dt
    else:
        half = 0.5 * dt
        theta_m = w0 * half + (w1 - w0) * (half * half) / (2.0 * dt)
        theta = 0.5 * (w0 + w1) * dt
        Rm = R0 @ exp_so3(theta_m)
        R1 = R0 @ exp_so3(theta)
        am = 0.5 * (a0 + a1)
        f0, fm, f1 = R0 @ a0 + g, Rm @ am + g, R1 @ a1 + g
        v1 = v0 + dt / 6.0 * (f0 + 4.0 * fm + f1)
        p1 = p0 + v0 * dt + dt * dt / 6.0 * (f0 + 2.0 * fm)
    new = ImuValues(R1, p1, v1, imu.gyro_bias_rad_s.copy(), imu.accel_bias_m_s2.copy())
    return StepMean(imu, new, method, dt, theta, R1, theta_m, Rm, am, a1, raw)


def step_transition(step: StepMean, imu_fej: ImuValues | None = None) -> np.ndarray:
    """Error-state transition matrix ``Phi`` (15, 15) of one integrated interval.

    Args:
        step: The interval, from :func:`integrate_mean`.
        imu_fej: First estimates at the start (None: the start state, i.e. the plain Jacobian).
    """
    g = gravity_W()
    dt, R0, R1, theta = step.dt, step.start.R_WB, step.R1, step.theta
    v1, p1 = step.new.v_WB, step.new.p_WB
    phi = np.eye(IMU_DIM)
    if step.method == Integration.DISCRETE:
        phi[VEL : VEL + 3, BA : BA + 3] = -R0 * dt
        phi[POS : POS + 3, BA : BA + 3] = -0.5 * R0 * dt * dt
        jr_theta = right_jacobian_so3(theta)
    else:
        half, Rm, am = 0.5 * dt, step.Rm, step.am
        # d f(tau) / d b_g = R(tau) [a(tau)]x Jr(theta(tau)) tau, since theta(tau) holds -b_g tau.
        Jm = Rm @ skew(am) @ right_jacobian_so3(step.theta_m) * half
        jr_theta = right_jacobian_so3(theta)
        J1 = R1 @ skew(step.a1) @ jr_theta * dt
        phi[VEL : VEL + 3, BG : BG + 3] = dt / 6.0 * (4.0 * Jm + J1)
        phi[POS : POS + 3, BG : BG + 3] = dt * dt / 6.0 * (2.0 * Jm)
        phi[VEL : VEL + 3, BA : BA + 3] = -dt / 6.0 * (R0 + 4.0 * Rm + R1)
        phi[POS : POS + 3, BA : BA + 3] = -dt * dt / 6.0 * (R0 + 2.0 * Rm)
    fej = step.start if imu_fej is None else imu_fej
    phi[THETA : THETA + 3, THETA : THETA + 3] = R1.T @ fej.R_WB
    phi[THETA : THETA + 3, BG : BG + 3] = -jr_theta * dt
    phi[VEL : VEL + 3, THETA : THETA + 3] = -skew(v1 - fej.v_WB - g * dt) @ fej.R_WB
    phi[POS : POS + 3, THETA : THETA + 3] = (
        -skew(p1 - fej.p_WB - fej.v_WB * dt - 0.5 * g * dt * dt) @ fej.R_WB
    )
    phi[POS : POS + 3, VEL : VEL + 3] = np.eye(3) * dt
    return phi


def integrate_step(
    imu: ImuValues,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: float,
    method: Integration,
    imu_fej: ImuValues | None = None,
) -> tuple[ImuValues, np.ndarray]:
    """Integrate one IMU interval and return the new nominal state and the transition matrix.

    :func:`integrate_mean` then :func:`step_transition`; the arguments are theirs.

    Args:
        imu: See :func:`integrate_mean`.
        w0: See :func:`integrate_mean`.
        w1: See :func:`integrate_mean`.
        a0: See :func:`integrate_mean`.
        a1: See :func:`integrate_mean`.
        dt: See :func:`integrate_mean`.
        method: See :func:`integrate_mean`.
        imu_fej: First estimates at the start (None: use ``imu``, i.e. the plain Jacobian).

    Returns:
        ``(new_state, phi)`` with ``phi`` (15, 15) the error-state transition matrix.
    """
    step = integrate_mean(imu, w0, w1, a0, a1, dt, method)
    return step.new, step_transition(step, imu_fej)


def discrete_noise(phi: np.ndarray, noise: ImuNoise, dt: float) -> np.ndarray:
    """Discrete process noise ``Q`` of one interval of length ``dt`` (s), the shape of ``phi`` (d, d >= 15).

    White noise acts like a bias offset held over the interval with variance ``density^2 / dt`` (Kalibr), so
    its input matrix is the bias columns of ``phi`` (rows theta, p, v); the random walks add
    ``density^2 dt`` on the bias blocks.
    """
    Bg = phi[:9, BG : BG + 3]
    Ba = phi[:9, BA : BA + 3]
    Q = np.zeros(phi.shape)  # (15 + intrinsics, same): the intrinsic blocks take no process noise
    Q[:9, :9] = (noise.gyro_noise_density_rad_s_sqrthz**2 / dt) * (Bg @ Bg.T) + (
        noise.accel_noise_density_m_s2_sqrthz**2 / dt
    ) * (Ba @ Ba.T)
    Q[BG : BG + 3, BG : BG + 3] = np.eye(3) * noise.gyro_random_walk_rad_s2_sqrthz**2 * dt
    Q[BA : BA + 3, BA : BA + 3] = np.eye(3) * noise.accel_random_walk_m_s3_sqrthz**2 * dt
    return Q


def _rotate(R: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Stacked ``R[k] @ x[k]``: ``R`` (m, 3, 3), ``x`` (m, 3) -> (m, 3)."""
    return (R @ x[:, :, None])[:, :, 0]


def transition_batch(
    method: Integration,
    dt: np.ndarray,
    R0: np.ndarray,
    R1: np.ndarray,
    Jr: np.ndarray,
    v1: np.ndarray,
    p1: np.ndarray,
    fej: tuple[np.ndarray, np.ndarray, np.ndarray],
    rk4: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Stacked :func:`step_transition` of m intervals, shape (m, 15, 15).

    Args:
        method: Integration method.
        dt: Interval lengths (s), shape (m,).
        R0: Start orientations, shape (m, 3, 3); ``R1`` the end orientations.
        R1: See ``R0``.
        Jr: Right Jacobians of the intervals' rotation vectors, shape (m, 3, 3).
        v1: End velocities (m/s), shape (m, 3); ``p1`` the end positions (m).
        p1: See ``v1``.
        fej: First estimates at the interval starts ``(R (m, 3, 3), v (m, 3), p (m, 3))``.
        rk4: RK4 only: ``(Rm (m, 3, 3), am (m, 3), a1 (m, 3), Jrm (m, 3, 3))``, the mid-interval
            orientations, mean and end specific forces and the mid-interval right Jacobians.
    """
    g = gravity_W()
    m = dt.shape[0]
    dtc, dt3 = dt[:, None], dt[:, None, None]
    R0f, v0f, p0f = fej
    phi = np.zeros((m, IMU_DIM, IMU_DIM))
    phi.reshape(m, -1)[:, :: IMU_DIM + 1] = 1.0  # identity diagonals
    if method == Integration.DISCRETE:
        phi[:, VEL : VEL + 3, BA : BA + 3] = -R0 * dt3
        phi[:, POS : POS + 3, BA : BA + 3] = -0.5 * R0 * dt3 * dt3
    else:
        Rm, am, a1, Jrm = rk4
        # d f(tau) / d b_g = R(tau) [a(tau)]x Jr(theta(tau)) tau, since theta(tau) holds -b_g tau.
        Jm = Rm @ skew_batch(am) @ Jrm * (0.5 * dt3)
        J1 = R1 @ skew_batch(a1) @ Jr * dt3
        phi[:, VEL : VEL + 3, BG : BG + 3] = dt3 / 6.0 * (4.0 * Jm + J1)
        phi[:, POS : POS + 3, BG : BG + 3] = dt3 * dt3 / 6.0 * (2.0 * Jm)
        phi[:, VEL : VEL + 3, BA : BA + 3] = -dt3 / 6.0 * (R0 + 4.0 * Rm + R1)
        phi[:, POS : POS + 3, BA : BA + 3] = -dt3 * dt3 / 6.0 * (R0 + 2.0 * Rm)
    phi[:, THETA : THETA + 3, THETA : THETA + 3] = np.swapaxes(R1, 1, 2) @ R0f
    phi[:, THETA : THETA + 3, BG : BG + 3] = -Jr * dt3
    phi[:, VEL : VEL + 3, THETA : THETA + 3] = -skew_batch(v1 - v0f - g * dtc) @ R0f
    phi[:, POS : POS + 3, THETA : THETA + 3] = -skew_batch(p1 - p0f - v0f * dtc - 0.5 * g * dtc * dtc) @ R0f
    for i in range(3):
        phi[:, POS + i, VEL + i] = dt
    return phi


def step_transitions(steps: list[StepMean], intr: ImuIntrinsics | None = None) -> np.ndarray:
    """:func:`step_transition` (plain Jacobians) of many intervals of one method at once, (m, 15, 15).

    Equal to the per-interval matrices to round-off (the stacked Rodrigues and products are the same
    formulas; ``tests/test_imu_prediction.py``). With ``intr`` (the steps then carry ``raw``): the
    transitions extended by the intrinsic blocks (:func:`extend_transition`), (m, 15 + intr.dim, same).
    """
    method = steps[0].method
    dt = np.array([s.dt for s in steps])
    R0 = np.array([s.start.R_WB for s in steps])
    R1 = np.array([s.R1 for s in steps])
    v1 = np.array([s.new.v_WB for s in steps])
    p1 = np.array([s.new.p_WB for s in steps])
    fej = (R0, np.array([s.start.v_WB for s in steps]), np.array([s.start.p_WB for s in steps]))
    m = len(steps)
    rk4 = None
    if method == Integration.DISCRETE:
        Jr = right_jacobian_so3_batch(np.array([s.theta for s in steps]))
    else:
        # One Rodrigues call for the end and mid-interval angles together.
        Jr_both = right_jacobian_so3_batch(np.array([s.theta for s in steps] + [s.theta_m for s in steps]))
        Jr = Jr_both[:m]
        rk4 = (
            np.array([s.Rm for s in steps]),
            np.array([s.am for s in steps]),
            np.array([s.a1 for s in steps]),
            Jr_both[m:],
        )
    phi = transition_batch(method, dt, R0, R1, Jr, v1, p1, fej, rk4)
    if intr is None:
        return phi
    raw = np.array([s.raw for s in steps])
    return extend_transition(phi, intrinsic_columns(method, dt, R0, R1, Jr, rk4, raw, intr), intr)


def intrinsic_columns(
    method: Integration,
    dt: np.ndarray,
    R0: np.ndarray,
    R1: np.ndarray,
    Jr: np.ndarray,
    rk4: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
    raw: np.ndarray,
    intr: ImuIntrinsics,
) -> np.ndarray:
    """Transition columns of the estimated intrinsic blocks, shape (m, 15, intr.dim).

    The chain rule through the corrected readings (:mod:`viotb.vio.imu_intrinsics`): at the interval ends
    ``dw_j = H_j dT_g`` and ``da_j = A_j dT_a`` with ``H_j = kron(I, (w_mj - b_g)^T)``. The rotation vectors
    are linear in the rates, ``theta = dt (w_0 + w_1) / 2`` and (RK4) ``theta_m = dt (3 w_0 + w_1) / 8``, so
    ``d theta = G_1 dT_g``, ``d theta_m = G_m dT_g``; the attitude error is ``Jr(theta) d theta`` and each RK4
    stage ``f = R a + g_W`` moves by ``-R [a]x Jr d theta`` (gyro) or ``R da`` (accel); the stages are then
    summed with the integrator's own weights (``v: dt/6 (f0 + 4 fm + f1)``, ``p: dt^2/6 (f0 + 2 fm)``;
    DISCRETE holds ``R_0`` and the mean force). The bias columns are the special case ``H_j = -I``.

    Args:
        method: Integration method.
        dt: Interval lengths (s), shape (m,).
        R0: Start orientations, shape (m, 3, 3); ``R1`` the end orientations.
        R1: See ``R0``.
        Jr: Right Jacobians of the intervals' rotation vectors, shape (m, 3, 3).
        rk4: RK4 only: ``(Rm, am, a1, Jrm)`` as :func:`transition_batch` takes them (corrected forces).
        raw: Bias-removed raw readings ``[w_m0, w_m1, a_m0, a_m1] - b`` per interval, shape (m, 4, 3).
        intr: The intrinsics (which blocks, in order).
    """
    m = dt.shape[0]
    dt3 = dt[:, None, None]
    cols = np.zeros((m, IMU_DIM, intr.dim))
    k = 0
    if intr.gyro:
        H0, H1 = input_jacobian(raw[:, 0]), input_jacobian(raw[:, 1])
        G1 = 0.5 * dt3 * (H0 + H1)
        cols[:, THETA : THETA + 3, k : k + 9] = Jr @ G1
        if method == Integration.RK4:
            Rm, am, a1, Jrm = rk4
            Fm = -(Rm @ skew_batch(am) @ Jrm) @ (dt3 * (0.375 * H0 + 0.125 * H1))
            F1 = -(R1 @ skew_batch(a1) @ Jr) @ G1
            cols[:, VEL : VEL + 3, k : k + 9] = dt3 / 6.0 * (4.0 * Fm + F1)
            cols[:, POS : POS + 3, k : k + 9] = dt3 * dt3 / 6.0 * (2.0 * Fm)
        k += 9
    if intr.accel:
        A0, A1 = input_jacobian(raw[:, 2]), input_jacobian(raw[:, 3])
        Am = 0.5 * (A0 + A1)
        if method == Integration.DISCRETE:
            cols[:, VEL : VEL + 3, k : k + 9] = dt3 * (R0 @ Am)
            cols[:, POS : POS + 3, k : k + 9] = 0.5 * dt3 * dt3 * (R0 @ Am)
        else:
            Rm = rk4[0]
            cols[:, VEL : VEL + 3, k : k + 9] = dt3 / 6.0 * (R0 @ A0 + 4.0 * Rm @ Am + R1 @ A1)
            cols[:, POS : POS + 3, k : k + 9] = dt3 * dt3 / 6.0 * (R0 @ A0 + 2.0 * Rm @ Am)
    return cols


def extend_transition(phi: np.ndarray, cols: np.ndarray, intr: ImuIntrinsics) -> np.ndarray:
    """``[[Phi', C], [0, I]]`` over ``[imu, intrinsics]``, shape (m, 15 + n, 15 + n).

    ``Phi'`` is ``phi`` (m, 15, 15), built with the corrected readings, with the bias columns of the
    attitude, position and velocity rows times ``T_g`` / ``T_a`` (``dw = -T_g db_g``); ``C`` the
    :func:`intrinsic_columns` (m, 15, n); the intrinsics are constant.
    """
    m, n = phi.shape[0], intr.dim
    d = IMU_DIM + n
    ext = np.zeros((m, d, d))
    ext[:, :IMU_DIM, :IMU_DIM] = phi
    ext[:, :9, BG : BG + 3] = phi[:, :9, BG : BG + 3] @ intr.T_g
    ext[:, :9, BA : BA + 3] = phi[:, :9, BA : BA + 3] @ intr.T_a
    ext[:, :IMU_DIM, IMU_DIM:] = cols
    ext.reshape(m, -1)[:, (d + 1) * IMU_DIM :: d + 1] = 1.0
    return ext


def integrate_batch(
    imu: ImuValues,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: np.ndarray,
    method: Integration,
    imu_fej: ImuValues | None = None,
) -> tuple[ImuValues, np.ndarray, tuple]:
    """:func:`integrate_step` over consecutive intervals at once: the mean chained, ``Phi`` stacked.

    Only the rotation and position chains are Python loops (a 3x3 product, two 3-vector sums per interval,
    in the per-sample order of operations); the velocity is a running sum (``np.cumsum`` accumulates in
    order) and every transition block is computed for all intervals in one array operation
    (:func:`transition_batch`).

    Args:
        imu: State at the start of the first interval (biases are held).
        w0: Bias-corrected rates (rad/s) at the interval starts, shape (m, 3); ``w1`` at the ends.
        w1: See ``w0``.
        a0: Bias-corrected specific forces (m/s^2) at the starts, shape (m, 3); ``a1`` at the ends (like w).
        a1: See ``a0``.
        dt: Interval lengths (s), shape (m,), all > 0.
        method: Integration method.
        imu_fej: First estimates at the start of the first interval (None: ``imu``).

    Returns:
        ``(state at the end, phi (m, 15, 15), parts)``: ``phi[k]`` the transition of interval k, and
        ``parts = (R0, R1, Jr, rk4)`` what :func:`intrinsic_columns` takes (``rk4`` None for DISCRETE).
    """
    g = gravity_W()
    m = dt.shape[0]
    dtc = dt[:, None]
    # 1. Rotations at the interval starts (R[:-1]) and ends (R[1:]).
    theta = 0.5 * (w0 + w1) * dtc
    if method == Integration.DISCRETE:
        E = exp_so3_batch(theta)
        Jr = right_jacobian_so3_batch(theta)
    else:
        # One Rodrigues call for the end and mid-interval angles together.
        half = 0.5 * dtc
        both = np.vstack([theta, w0 * half + (w1 - w0) * (half * half) / (2.0 * dtc)])
        E_both, Jr_both = exp_so3_batch(both), right_jacobian_so3_batch(both)
        E, Em, Jr, Jrm = E_both[:m], E_both[m:], Jr_both[:m], Jr_both[m:]
    R = np.empty((m + 1, 3, 3))
    R[0] = imu.R_WB
    for k in range(m):
        R[k + 1] = R[k] @ E[k]
    R0, R1 = R[:-1], R[1:]
    # 2. Velocity and position increments.
    rk4 = None
    if method == Integration.DISCRETE:
        acc = g + _rotate(R0, 0.5 * (a0 + a1))
        dv = acc * dtc
        dp_acc = 0.5 * acc * dtc * dtc
    else:
        Rm = R0 @ Em
        am = 0.5 * (a0 + a1)
        f0 = _rotate(R0, a0) + g
        fm = _rotate(Rm, am) + g
        f1 = _rotate(R1, a1) + g
        dv = dtc / 6.0 * (f0 + 4.0 * fm + f1)
        dp_acc = dtc * dtc / 6.0 * (f0 + 2.0 * fm)
        rk4 = (Rm, am, a1, Jrm)
    v = np.cumsum(np.vstack([imu.v_WB[None], dv]), axis=0)
    # p_{k+1} = (p_k + v_k dt_k) + dp_k in the per-sample order (a cumsum would group the terms otherwise).
    vdt = v[:-1] * dtc
    p = np.empty((m + 1, 3))
    p[0] = imu.p_WB
    for k in range(m):
        p[k + 1] = p[k] + vdt[k] + dp_acc[k]
    # 3. Transitions; first estimates: interval 0 starts at the first estimates, the others at the chained
    # values.
    fej = imu if imu_fej is None else imu_fej
    R0f, v0f, p0f = R0.copy(), v[:-1].copy(), p[:-1].copy()
    R0f[0], v0f[0], p0f[0] = fej.R_WB, fej.v_WB, fej.p_WB
    phi = transition_batch(method, dt, R0, R1, Jr, v[1:], p[1:], (R0f, v0f, p0f), rk4)
    new = ImuValues(R[m].copy(), p[m], v[m], imu.gyro_bias_rad_s.copy(), imu.accel_bias_m_s2.copy())
    return new, phi, (R0, R1, Jr, rk4)


def discrete_noise_batch(phi: np.ndarray, noise: ImuNoise, dt: np.ndarray) -> np.ndarray:
    """Stacked :func:`discrete_noise`: ``phi`` (m, d, d), ``dt`` (m,) s -> ``Q`` (m, d, d), d >= 15."""
    Bg = phi[:, :9, BG : BG + 3]
    Ba = phi[:, :9, BA : BA + 3]
    s_g = (noise.gyro_noise_density_rad_s_sqrthz**2 / dt)[:, None, None]
    s_a = (noise.accel_noise_density_m_s2_sqrthz**2 / dt)[:, None, None]
    Q = np.zeros(phi.shape)
    Q[:, :9, :9] = s_g * (Bg @ np.swapaxes(Bg, 1, 2)) + s_a * (Ba @ np.swapaxes(Ba, 1, 2))
    for i in range(3):
        Q[:, BG + i, BG + i] = noise.gyro_random_walk_rad_s2_sqrthz**2 * dt
        Q[:, BA + i, BA + i] = noise.accel_random_walk_m_s3_sqrthz**2 * dt
    return Q
