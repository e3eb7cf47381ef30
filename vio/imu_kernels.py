"""Compiled IMU propagation: the mean, the transitions, the noise and their chain (issue #15, sixth pass).

Numba kernels (:func:`viotb.vio.jit.njit`) of the numpy functions in :mod:`viotb.vio.imu_integration`, which
stay the reference their tests compare against (``tests/test_imu_kernels.py``, 1e-9 relative). Each kernel
writes the reference's formulas term by term in the reference's order of operations; only the 3 x 3 and
15 x 15 products differ, summed here in index order where numpy's BLAS may group them otherwise (a last-bit
difference). The products of the transitions skip their structural zeros: adding ``0 * x`` changes no sum,
so the result is the dense product's (a transition has 87 of 225 entries non-zero with RK4).

Entry points (all arrays float64, frames and units as in :mod:`viotb.vio.imu_integration`):

- :func:`mean_step`: one interval's nominal state (:func:`~viotb.vio.imu_integration.integrate_mean`), as
  one record (:data:`RECORD_ROWS`): each kernel hands back few arrays, since numba boxes every returned
  array at a cost of about half a microsecond;
- :func:`step_phis_qs`: stacked transitions and noises of recorded intervals
  (:func:`~viotb.vio.imu_integration.step_transitions` and ``discrete_noise_batch``), and
  :func:`step_chain` the same followed by their chain;
- :func:`propagate_span`: a span's mean, ``Phi`` and ``Q`` (``propagate_values`` without intrinsics);
- :func:`chain_totals`: the running products ``Phi_k ... Phi_0`` and noises of a prediction chain.
"""

from __future__ import annotations

import math

import numpy as np
from viotb.vio.jit import njit
from viotb.vio.state import BA, BG, IMU_DIM, POS, THETA, VEL

_EXP_SMALL_RAD = 1e-8  # lie._SMALL_ANGLE_RAD: exp_so3's series below it
_JR_SMALL_RAD = 1e-6  # right_jacobian_so3's series below it


@njit
def _rodrigues(phi: np.ndarray, right_jacobian: bool) -> np.ndarray:
    """``exp_so3(phi)`` or ``right_jacobian_so3(phi)`` (3, 3) as :mod:`viotb.vio.lie` computes them."""
    x, y, z = phi[0], phi[1], phi[2]
    angle = math.sqrt(x * x + y * y + z * z)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    div6 = False  # right_jacobian_so3's series writes k @ k / 6, the others (c2 k) @ k
    if right_jacobian:
        if angle < _JR_SMALL_RAD:
            c1, c2, div6 = -0.5, 1.0, True
        else:
            c1 = -((1.0 - math.cos(angle)) / angle**2)
            c2 = (angle - math.sin(angle)) / angle**3
    elif angle < _EXP_SMALL_RAD:
        c1, c2 = 1.0, 0.5
    else:
        c1 = math.sin(angle) / angle
        c2 = (1.0 - math.cos(angle)) / angle**2
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            kk = (c2 * k[i, 0]) * k[0, j] + (c2 * k[i, 1]) * k[1, j] + (c2 * k[i, 2]) * k[2, j]
            eye = 1.0 if i == j else 0.0
            out[i, j] = (eye + c1 * k[i, j]) + (kk / 6.0 if div6 else kk)
    return out


@njit
def _mm3(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` of 3 x 3 matrices, summed in index order."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return out


@njit
def _mv3(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``A @ x`` of a 3 x 3 matrix and a 3-vector."""
    out = np.empty(3)
    for i in range(3):
        out[i] = A[i, 0] * x[0] + A[i, 1] * x[1] + A[i, 2] * x[2]
    return out


@njit
def _skew_mm3(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``A @ skew(v)`` (3, 3), the product's terms in index order (the zero terms are exact)."""
    return _mm3(A, np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]))


@njit
def _mean(
    R0: np.ndarray,
    p0: np.ndarray,
    v0: np.ndarray,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: float,
    rk4: bool,
    g: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One interval's nominal state, as :func:`~viotb.vio.imu_integration.integrate_mean` (unpacked).

    Args:
        R0: Start orientation ``R_WB``, shape (3, 3); ``p0`` (m), ``v0`` (m/s) position and velocity in W.
        p0: See ``R0``.
        v0: See ``R0``.
        w0: Corrected angular rates (rad/s) in B at the start and end, shape (3,).
        w1: See ``w0``.
        a0: Corrected specific forces (m/s^2) in B at the start and end, shape (3,).
        a1: See ``a0``.
        dt: Interval length (s), > 0.
        rk4: RK4 (else DISCRETE).
        g: Gravity in W (m/s^2), shape (3,).

    Returns:
        ``(R1, p1, v1, theta, theta_m, Rm, am)``; DISCRETE leaves ``theta_m``, ``am`` zero and ``Rm`` ``R0``.
    """
    theta_m = np.zeros(3)
    am = np.zeros(3)
    if not rk4:
        theta = np.empty(3)
        acc = np.empty(3)
        for i in range(3):
            theta[i] = (0.5 * (w0[i] + w1[i])) * dt
            am[i] = 0.5 * (a0[i] + a1[i])
        R1 = _mm3(R0, _rodrigues(theta, False))
        Ra = _mv3(R0, am)
        v1, p1 = np.empty(3), np.empty(3)
        for i in range(3):
            acc[i] = g[i] + Ra[i]
            v1[i] = v0[i] + acc[i] * dt
            p1[i] = (p0[i] + v0[i] * dt) + ((0.5 * acc[i]) * dt) * dt
        return R1, p1, v1, theta, np.zeros(3), R0.copy(), np.zeros(3)
    half = 0.5 * dt
    theta = np.empty(3)
    for i in range(3):
        theta_m[i] = w0[i] * half + ((w1[i] - w0[i]) * (half * half)) / (2.0 * dt)
        theta[i] = (0.5 * (w0[i] + w1[i])) * dt
        am[i] = 0.5 * (a0[i] + a1[i])
    Rm = _mm3(R0, _rodrigues(theta_m, False))
    R1 = _mm3(R0, _rodrigues(theta, False))
    f0, fm, f1 = _mv3(R0, a0), _mv3(Rm, am), _mv3(R1, a1)
    v1, p1 = np.empty(3), np.empty(3)
    for i in range(3):
        s0, sm, s1 = f0[i] + g[i], fm[i] + g[i], f1[i] + g[i]
        v1[i] = v0[i] + (dt / 6.0) * ((s0 + 4.0 * sm) + s1)
        p1[i] = (p0[i] + v0[i] * dt) + ((dt * dt) / 6.0) * (s0 + 2.0 * sm)
    return R1, p1, v1, theta, theta_m, Rm, am


RECORD_ROWS = 17
"""Rows of a :func:`mean_step` record (each a 3-vector): ``R1`` 0-2, ``p1`` 3, ``v1`` 4, ``theta`` 5,
``theta_m`` 6, ``Rm`` 7-9, ``am`` 10, the start ``R0`` 11-13, ``p0`` 14, ``v0`` 15, and ``a1`` 16."""


@njit
def mean_step(
    R0: np.ndarray,
    p0: np.ndarray,
    v0: np.ndarray,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: float,
    rk4: bool,
    g: np.ndarray,
) -> np.ndarray:
    """:func:`_mean` packed into one record, shape (RECORD_ROWS, 3) (one array to hand back to Python).

    The arguments are :func:`_mean`'s; the record also keeps the start state and ``a1``, which the
    interval's transition needs (:func:`step_phis_qs` takes stacked records).
    """
    R1, p1, v1, theta, theta_m, Rm, am = _mean(R0, p0, v0, w0, w1, a0, a1, dt, rk4, g)
    rec = np.empty((RECORD_ROWS, 3))
    rec[0:3] = R1
    rec[3] = p1
    rec[4] = v1
    rec[5] = theta
    rec[6] = theta_m
    rec[7:10] = Rm
    rec[10] = am
    rec[11:14] = R0
    rec[14] = p0
    rec[15] = v0
    rec[16] = a1
    return rec


@njit
def _fill_phi(
    phi: np.ndarray,
    dt: float,
    R0: np.ndarray,
    R1: np.ndarray,
    theta: np.ndarray,
    v1: np.ndarray,
    p1: np.ndarray,
    R0f: np.ndarray,
    v0f: np.ndarray,
    p0f: np.ndarray,
    rk4: bool,
    Rm: np.ndarray,
    am: np.ndarray,
    a1: np.ndarray,
    theta_m: np.ndarray,
    g: np.ndarray,
) -> None:
    """Write one interval's 15 x 15 transition into ``phi`` (zeroed), as ``step_transition`` builds it."""
    for i in range(IMU_DIM):
        phi[i, i] = 1.0
    jr = _rodrigues(theta, True)
    if not rk4:
        for i in range(3):
            for j in range(3):
                phi[VEL + i, BA + j] = -R0[i, j] * dt
                phi[POS + i, BA + j] = ((-0.5 * R0[i, j]) * dt) * dt
    else:
        half = 0.5 * dt
        Jm = _mm3(_skew_mm3(Rm, am), _rodrigues(theta_m, True))
        J1 = _mm3(_skew_mm3(R1, a1), jr)
        for i in range(3):
            for j in range(3):
                jm, j1 = Jm[i, j] * half, J1[i, j] * dt
                phi[VEL + i, BG + j] = (dt / 6.0) * (4.0 * jm + j1)
                phi[POS + i, BG + j] = ((dt * dt) / 6.0) * (2.0 * jm)
                phi[VEL + i, BA + j] = (-dt / 6.0) * ((R0[i, j] + 4.0 * Rm[i, j]) + R1[i, j])
                phi[POS + i, BA + j] = ((-dt * dt) / 6.0) * (R0[i, j] + 2.0 * Rm[i, j])
    dv, dp = np.empty(3), np.empty(3)
    for i in range(3):
        dv[i] = (v1[i] - v0f[i]) - g[i] * dt
        dp[i] = ((p1[i] - p0f[i]) - v0f[i] * dt) - ((0.5 * g[i]) * dt) * dt
    Ktt = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            Ktt[i, j] = R1[0, i] * R0f[0, j] + R1[1, i] * R0f[1, j] + R1[2, i] * R0f[2, j]
    Kvt = _mm3(np.array([[0.0, -dv[2], dv[1]], [dv[2], 0.0, -dv[0]], [-dv[1], dv[0], 0.0]]), R0f)
    Kpt = _mm3(np.array([[0.0, -dp[2], dp[1]], [dp[2], 0.0, -dp[0]], [-dp[1], dp[0], 0.0]]), R0f)
    for i in range(3):
        for j in range(3):
            phi[THETA + i, THETA + j] = Ktt[i, j]
            phi[THETA + i, BG + j] = -jr[i, j] * dt
            phi[VEL + i, THETA + j] = -Kvt[i, j]
            phi[POS + i, THETA + j] = -Kpt[i, j]
        phi[POS + i, VEL + i] = dt


@njit
def _fill_q(q: np.ndarray, phi: np.ndarray, dt: float, noise: np.ndarray) -> None:
    """Write ``discrete_noise(phi, noise, dt)`` into ``q`` (zeroed).

    ``noise``: the four densities in ``ImuNoise`` order (gyro white, gyro walk, accel white, accel walk).
    """
    s_g = noise[0] ** 2 / dt
    s_a = noise[2] ** 2 / dt
    for i in range(9):
        for j in range(9):
            bg = phi[i, BG] * phi[j, BG] + phi[i, BG + 1] * phi[j, BG + 1] + phi[i, BG + 2] * phi[j, BG + 2]
            ba = phi[i, BA] * phi[j, BA] + phi[i, BA + 1] * phi[j, BA + 1] + phi[i, BA + 2] * phi[j, BA + 2]
            q[i, j] = s_g * bg + s_a * ba
    for i in range(3):
        q[BG + i, BG + i] = noise[1] ** 2 * dt
        q[BA + i, BA + i] = noise[3] ** 2 * dt


@njit
def _mm_sparse(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` (d, d), skipping the zero entries of ``A`` (the sums of the dense product, in order)."""
    d = A.shape[0]
    out = np.zeros((d, B.shape[1]))
    for i in range(d):
        for k in range(A.shape[1]):
            aik = A[i, k]
            if aik != 0.0:
                for j in range(B.shape[1]):
                    out[i, j] += aik * B[k, j]
    return out


@njit
def _mm_t_sparse(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B.T`` (d, d), skipping the zero entries of ``B``."""
    out = np.zeros((A.shape[0], B.shape[0]))
    for j in range(B.shape[0]):
        for k in range(B.shape[1]):
            bjk = B[j, k]
            if bjk != 0.0:
                for i in range(A.shape[0]):
                    out[i, j] += A[i, k] * bjk
    return out


@njit
def _link(phi: np.ndarray, q: np.ndarray, phi_tot: np.ndarray, q_tot: np.ndarray) -> tuple:
    """One step of the chain: ``(phi @ phi_tot, phi @ q_tot @ phi.T + q)``."""
    return _mm_sparse(phi, phi_tot), _mm_t_sparse(_mm_sparse(phi, q_tot), phi) + q


@njit
def chain_totals(
    phis: np.ndarray, qs: np.ndarray, phi0: np.ndarray, q0: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Running totals of a chain of transitions: ``Phi_k ... Phi_0 phi0`` and their noises.

    Args:
        phis: The links' transitions, shape (m, d, d); ``qs`` their noises (m, d, d).
        qs: See ``phis``.
        phi0: The total before the first link (d, d) (the identity at a chain's start); ``q0`` its noise.
        q0: See ``phi0``.

    Returns:
        ``[phi_tots, q_tots]``, shape (2, m, d, d): after link k, ``phi_tots[k] = phis[k] @ phi_tots[k-1]``
        and ``q_tots[k] = phis[k] @ q_tots[k-1] @ phis[k].T + qs[k]``.
    """
    m, d = phis.shape[0], phis.shape[1]
    out = np.empty((2, m, d, d))
    phi_tot, q_tot = phi0, q0
    for k in range(m):
        phi_tot, q_tot = _link(phis[k], qs[k], phi_tot, q_tot)
        out[0, k] = phi_tot
        out[1, k] = q_tot
    return out


@njit
def step_phis_qs(
    records: np.ndarray, dt: np.ndarray, rk4: bool, g: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """Plain-Jacobian transitions and noises of m recorded intervals: ``[phis, qs]``, shape (2, m, 15, 15).

    Args:
        records: The intervals' :func:`mean_step` records, shape (m, RECORD_ROWS, 3).
        dt: Interval lengths (s), shape (m,).
        rk4: RK4 (else DISCRETE: the records' mid-interval rows are not read).
        g: Gravity in W (m/s^2), shape (3,).
        noise: The four densities in ``ImuNoise`` order, shape (4,).
    """
    m = dt.shape[0]
    out = np.zeros((2, m, IMU_DIM, IMU_DIM))
    for k in range(m):
        r = records[k]
        R0, p0, v0 = r[11:14], r[14], r[15]  # the plain Jacobian: the first estimates are the start values
        _fill_phi(
            out[0, k], dt[k], R0, r[0:3], r[5], r[4], r[3], R0, v0, p0, rk4, r[7:10], r[10], r[16], r[6], g
        )
        _fill_q(out[1, k], out[0, k], dt[k], noise)
    return out


@njit
def step_chain(
    records: np.ndarray,
    dt: np.ndarray,
    rk4: bool,
    g: np.ndarray,
    noise: np.ndarray,
    phi0: np.ndarray,
    q0: np.ndarray,
) -> np.ndarray:
    """:func:`step_phis_qs` then :func:`chain_totals` in one call: the running totals, (2, m, 15, 15).

    Args:
        records: See :func:`step_phis_qs`.
        dt: See :func:`step_phis_qs`.
        rk4: See :func:`step_phis_qs`.
        g: See :func:`step_phis_qs`.
        noise: See :func:`step_phis_qs`.
        phi0: The total before the first interval, (15, 15); ``q0`` its noise.
        q0: See ``phi0``.
    """
    links = step_phis_qs(records, dt, rk4, g, noise)
    return chain_totals(links[0], links[1], phi0, q0)


@njit
def propagate_span(
    R0: np.ndarray,
    p0: np.ndarray,
    v0: np.ndarray,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: np.ndarray,
    fej_R: np.ndarray,
    fej_p: np.ndarray,
    fej_v: np.ndarray,
    rk4: bool,
    g: np.ndarray,
    noise: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """A span's mean, ``Phi`` and ``Q``: ``propagate_values`` without intrinsics, the same recursion order.

    Args:
        R0: Start orientation (3, 3), position (m) and velocity (m/s) in W (3,).
        p0: See ``R0``.
        v0: See ``R0``.
        w0: Corrected rates (rad/s) at the starts of the m intervals, shape (m, 3); ``w1`` at the ends.
        w1: See ``w0``.
        a0: Corrected specific forces (m/s^2) at the starts, shape (m, 3); ``a1`` at the ends.
        a1: See ``a0``.
        dt: Interval lengths (s), shape (m,), all > 0.
        fej_R: First estimates at the start: orientation (3, 3), position, velocity (3,).
        fej_p: See ``fej_R``.
        fej_v: See ``fej_R``.
        rk4: RK4 (else DISCRETE).
        g: Gravity in W (m/s^2), shape (3,).
        noise: The four densities in ``ImuNoise`` order, shape (4,).

    Returns:
        ``(state, [Phi, Q])`` over the span: ``state`` the end's ``R1`` (rows 0-2), ``p1`` (row 3), ``v1``
        (row 4), shape (5, 3); ``Phi``, ``Q`` (15, 15) each, stacked (2, 15, 15).
    """
    R, p, v = R0, p0, v0
    Rf, pf, vf = fej_R, fej_p, fej_v
    phi_tot, q_tot = np.eye(IMU_DIM), np.zeros((IMU_DIM, IMU_DIM))
    phi, q = np.zeros((IMU_DIM, IMU_DIM)), np.zeros((IMU_DIM, IMU_DIM))
    for k in range(dt.shape[0]):
        R1, p1, v1, theta, theta_m, Rm, am = _mean(R, p, v, w0[k], w1[k], a0[k], a1[k], dt[k], rk4, g)
        phi[:, :] = 0.0
        q[:, :] = 0.0
        _fill_phi(phi, dt[k], R, R1, theta, v1, p1, Rf, vf, pf, rk4, Rm, am, a1[k], theta_m, g)
        _fill_q(q, phi, dt[k], noise)
        if k == 0:
            phi_tot, q_tot = phi.copy(), q.copy()
        else:
            phi_tot, q_tot = _link(phi, q, phi_tot, q_tot)
        R, p, v = R1, p1, v1
        Rf, pf, vf = R1, p1, v1
    state = np.empty((5, 3))
    state[0:3] = R
    state[3] = p
    state[4] = v
    out = np.empty((2, IMU_DIM, IMU_DIM))
    out[0] = phi_tot
    out[1] = q_tot
    return state, out
