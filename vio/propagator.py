"""IMU buffer and error-state propagation of the MSCKF (open_vins ``Propagator`` shape).

Nominal model (W: z up, ``g_W = (0, 0, -9.81)``), with bias-corrected readings ``w = gyro - b_g`` and
``a = accel - b_a`` interpolated linearly over each IMU interval ``[t_k, t_k + dt]``::

    R(tau) = R_k Exp(theta(tau)),   theta(tau) = int_0^tau w,        (attitude along the interpolated rate)
    v' = R(tau) a(tau) + g_W,       p' = v

``Integration.DISCRETE`` holds ``R_k`` and the mean readings over the interval (Euler);
``Integration.RK4`` integrates the translational ODE with the classical Runge-Kutta 4 stages at
``tau = 0, dt/2, dt`` (``v += dt/6 (f0 + 4 fm + f1)``, ``p += v dt + dt^2/6 (f0 + 2 fm)``).

Error state ``[dtheta, dp, dv, dbg, dba]`` with ``R = R_hat Exp(dtheta)``. The transition matrix is the exact
derivative of the chosen integrator, written in the first-estimates form of open_vins ``Propagator``
(``docs/fej.dox``; Huang, Mourikis, Roumeliotis 2010)::

    Phi_tt = R_new^T R_old_fej
    Phi_vt = -[v_new - v_old_fej - g dt]x R_old_fej
    Phi_pt = -[p_new - p_old_fej - v_old_fej dt - g dt^2 / 2]x R_old_fej,     Phi_pv = I dt

which equals the plain Jacobian when the first estimates equal the current values and maps the yaw/position
null space at the old first estimates exactly onto the one at the new values.

Noise (Kalibr densities, see DESIGN.md): white gyro/accel noise acts over an interval like a bias offset of
variance ``density^2 / dt`` so it enters through the bias columns of ``Phi``; the random walks add
``density^2 dt`` to the bias blocks.
"""

from __future__ import annotations

from enum import Enum

import numpy as np
from viotb.vio.lie import (
    exp_so3,
    exp_so3_batch,
    right_jacobian_so3,
    right_jacobian_so3_batch,
    skew,
    skew_batch,
)
from viotb.vio.state import (
    BA,
    BG,
    IMU_DIM,
    POS,
    THETA,
    VEL,
    ImuValues,
    State,
    augment_clone,
    ekf_propagate,
    set_imu_fej,
)
from viotb.vio.types import ImuNoise, ImuSample, gravity_W


class Integration(str, Enum):
    """Integration method of the nominal state."""

    DISCRETE = "discrete"
    RK4 = "rk4"


def validate_imu_sample(sample: ImuSample, last_t_s: float | None) -> None:
    """Raise a ValueError naming the field, value and time for a non-finite or out-of-order sample."""
    t = float(sample.t_s)
    if not np.isfinite(t):
        raise ValueError(f"IMU sample time t_s={t} is not finite")
    for name, value in (("gyro_B_rad_s", sample.gyro_B_rad_s), ("accel_B_m_s2", sample.accel_B_m_s2)):
        arr = np.asarray(value, dtype=float)
        if arr.shape != (3,):
            raise ValueError(f"IMU sample at t={t:.6f} s: {name} must have shape (3,), got {arr.shape}")
        if not np.isfinite(arr).all():
            raise ValueError(f"IMU sample at t={t:.6f} s: {name}={arr.tolist()} is not finite")
    if last_t_s is not None and t <= last_t_s:
        raise ValueError(f"IMU timestamps must increase: got t={t:.9f} s after t={last_t_s:.9f} s")


class ImuBuffer:
    """Growable array buffer of IMU readings (no per-sample Python lists).

    Args:
        capacity: Initial capacity (samples); doubles when full.
    """

    def __init__(self, capacity: int = 2048) -> None:
        """Create an empty buffer."""
        self._t = np.empty(capacity)
        self._gyro = np.empty((capacity, 3))
        self._accel = np.empty((capacity, 3))
        self._n = 0

    def __len__(self) -> int:
        """Number of buffered readings."""
        return self._n

    @property
    def last_t_s(self) -> float | None:
        """Time of the newest reading, or None."""
        return float(self._t[self._n - 1]) if self._n else None

    def feed(self, sample: ImuSample) -> None:
        """Append one reading after validating it (ValueError on NaN/inf or non-increasing time)."""
        validate_imu_sample(sample, self.last_t_s)
        if self._n == self._t.shape[0]:
            cap = 2 * self._n
            self._t = np.resize(self._t, cap)
            self._gyro = np.resize(self._gyro, (cap, 3))
            self._accel = np.resize(self._accel, (cap, 3))
        self._t[self._n] = sample.t_s
        self._gyro[self._n] = sample.gyro_B_rad_s
        self._accel[self._n] = sample.accel_B_m_s2
        self._n += 1

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Views ``(t_s (N,), gyro (N, 3), accel (N, 3))`` of the buffered readings."""
        return self._t[: self._n], self._gyro[: self._n], self._accel[: self._n]

    def clean_older_than(self, t_s: float) -> None:
        """Drop readings older than ``t_s`` but keep the last one before it (needed to interpolate)."""
        k = int(np.searchsorted(self._t[: self._n], t_s, side="right")) - 1
        if k <= 0:
            return
        m = self._n - k
        self._t[:m] = self._t[k : self._n]
        self._gyro[:m] = self._gyro[k : self._n]
        self._accel[:m] = self._accel[k : self._n]
        self._n = m


def interpolate_readings(t_s: np.ndarray, values: np.ndarray, t_query: float) -> np.ndarray:
    """Linear interpolation of ``values`` (N, D) at ``t_query`` (held outside), as np.interp per column."""
    j = int(np.searchsorted(t_s, t_query, side="right")) - 1
    if j < 0:
        return values[0].copy()
    if j >= len(t_s) - 1 or t_s[j] == t_query:
        return values[j].copy()
    slope = (values[j + 1] - values[j]) / (t_s[j + 1] - t_s[j])
    return slope * (t_query - t_s[j]) + values[j]


def select_imu_readings(
    t_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray, t0_s: float, t1_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Readings covering ``[t0_s, t1_s]`` with interpolated end points (open_vins ``select_imu_readings``).

    Args:
        t_s: Reading times (s), shape (N,), increasing, N >= 1.
        gyro: shape (N, 3).
        accel: shape (N, 3).
        t0_s: Start time (s).
        t1_s: End time (s), > t0_s. Past the last reading the last value is held.

    Returns:
        ``(t (n,), gyro (n, 3), accel (n, 3))`` with ``t[0] = t0_s``, ``t[-1] = t1_s`` and n >= 2.
    """
    if len(t_s) == 0:
        raise ValueError("select_imu_readings: no IMU readings buffered")
    if not t1_s > t0_s:
        raise ValueError(f"select_imu_readings: t1_s={t1_s} must be after t0_s={t0_s}")
    i0 = int(np.searchsorted(t_s, t0_s, side="right"))  # readings strictly inside (t0_s, t1_s)
    i1 = max(i0, int(np.searchsorted(t_s, t1_s, side="left")))
    t_out = np.concatenate([[t0_s], t_s[i0:i1], [t1_s]])
    g_out = np.vstack(
        [interpolate_readings(t_s, gyro, t0_s), gyro[i0:i1], interpolate_readings(t_s, gyro, t1_s)]
    )
    a_out = np.vstack(
        [interpolate_readings(t_s, accel, t0_s), accel[i0:i1], interpolate_readings(t_s, accel, t1_s)]
    )
    return t_out, g_out, a_out


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

    Args:
        imu: State at the start of the interval (biases are held).
        w0: Bias-corrected angular rate (rad/s) at the start, shape (3,); ``w1`` at the end.
        w1: See ``w0``.
        a0: Bias-corrected specific force (m/s^2) at the start, shape (3,); ``a1`` at the end.
        a1: See ``a0``.
        dt: Interval length (s), > 0.
        method: Integration method.
        imu_fej: First estimates at the start (None: use ``imu``, i.e. the plain Jacobian).

    Returns:
        ``(new_state, phi)`` with ``phi`` (15, 15) the error-state transition matrix.
    """
    g = gravity_W()
    R0, p0, v0 = imu.R_WB, imu.p_WB, imu.v_WB
    phi = np.eye(IMU_DIM)
    if method == Integration.DISCRETE:
        w, a = 0.5 * (w0 + w1), 0.5 * (a0 + a1)
        theta = w * dt
        R1 = R0 @ exp_so3(theta)
        Ra = R0 @ a
        v1 = v0 + (g + Ra) * dt
        p1 = p0 + v0 * dt + 0.5 * (g + Ra) * dt * dt
        phi[VEL : VEL + 3, BA : BA + 3] = -R0 * dt
        phi[POS : POS + 3, BA : BA + 3] = -0.5 * R0 * dt * dt
        jr_theta = right_jacobian_so3(theta)
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
        # d f(tau) / d b_g = R(tau) [a(tau)]x Jr(theta(tau)) tau, since theta(tau) holds -b_g tau.
        Jm = Rm @ skew(am) @ right_jacobian_so3(theta_m) * half
        jr_theta = right_jacobian_so3(theta)
        J1 = R1 @ skew(a1) @ jr_theta * dt
        phi[VEL : VEL + 3, BG : BG + 3] = dt / 6.0 * (4.0 * Jm + J1)
        phi[POS : POS + 3, BG : BG + 3] = dt * dt / 6.0 * (2.0 * Jm)
        phi[VEL : VEL + 3, BA : BA + 3] = -dt / 6.0 * (R0 + 4.0 * Rm + R1)
        phi[POS : POS + 3, BA : BA + 3] = -dt * dt / 6.0 * (R0 + 2.0 * Rm)
    fej = imu if imu_fej is None else imu_fej
    phi[THETA : THETA + 3, THETA : THETA + 3] = R1.T @ fej.R_WB
    phi[THETA : THETA + 3, BG : BG + 3] = -jr_theta * dt
    phi[VEL : VEL + 3, THETA : THETA + 3] = -skew(v1 - fej.v_WB - g * dt) @ fej.R_WB
    phi[POS : POS + 3, THETA : THETA + 3] = (
        -skew(p1 - fej.p_WB - fej.v_WB * dt - 0.5 * g * dt * dt) @ fej.R_WB
    )
    phi[POS : POS + 3, VEL : VEL + 3] = np.eye(3) * dt
    new = ImuValues(R1, p1, v1, imu.gyro_bias_rad_s.copy(), imu.accel_bias_m_s2.copy())
    return new, phi


def discrete_noise(phi: np.ndarray, noise: ImuNoise, dt: float) -> np.ndarray:
    """Discrete process noise ``Q`` (15, 15) of one interval of length ``dt`` (s).

    White noise acts like a bias offset held over the interval with variance ``density^2 / dt`` (Kalibr), so
    its input matrix is the bias columns of ``phi`` (rows theta, p, v); the random walks add
    ``density^2 dt`` on the bias blocks.
    """
    Bg = phi[:9, BG : BG + 3]
    Ba = phi[:9, BA : BA + 3]
    Q = np.zeros((IMU_DIM, IMU_DIM))
    Q[:9, :9] = (noise.gyro_noise_density_rad_s_sqrthz**2 / dt) * (Bg @ Bg.T) + (
        noise.accel_noise_density_m_s2_sqrthz**2 / dt
    ) * (Ba @ Ba.T)
    Q[BG : BG + 3, BG : BG + 3] = np.eye(3) * noise.gyro_random_walk_rad_s2_sqrthz**2 * dt
    Q[BA : BA + 3, BA : BA + 3] = np.eye(3) * noise.accel_random_walk_m_s3_sqrthz**2 * dt
    return Q


def _rotate(R: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Stacked ``R[k] @ x[k]``: ``R`` (m, 3, 3), ``x`` (m, 3) -> (m, 3)."""
    return (R @ x[:, :, None])[:, :, 0]


def integrate_batch(
    imu: ImuValues,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: np.ndarray,
    method: Integration,
    imu_fej: ImuValues | None = None,
) -> tuple[ImuValues, np.ndarray]:
    """:func:`integrate_step` over consecutive intervals at once: the mean chained, ``Phi`` stacked.

    Only the rotation and position chains are Python loops (a 3x3 product, two 3-vector sums per interval,
    in the per-sample order of operations); the velocity is a running sum (``np.cumsum`` accumulates in
    order) and every transition block is computed for all intervals in one array operation.

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
        ``(state at the end, phi (m, 15, 15))``, ``phi[k]`` the transition of interval k.
    """
    g = gravity_W()
    m = dt.shape[0]
    dtc = dt[:, None]
    dt3 = dt[:, None, None]
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
    phi = np.zeros((m, IMU_DIM, IMU_DIM))
    phi.reshape(m, -1)[:, :: IMU_DIM + 1] = 1.0  # identity diagonals
    # 2. Velocity and position increments, and the bias columns of Phi.
    if method == Integration.DISCRETE:
        acc = g + _rotate(R0, 0.5 * (a0 + a1))
        dv = acc * dtc
        dp_acc = 0.5 * acc * dtc * dtc
        phi[:, VEL : VEL + 3, BA : BA + 3] = -R0 * dt3
        phi[:, POS : POS + 3, BA : BA + 3] = -0.5 * R0 * dt3 * dt3
    else:
        Rm = R0 @ Em
        am = 0.5 * (a0 + a1)
        f0 = _rotate(R0, a0) + g
        fm = _rotate(Rm, am) + g
        f1 = _rotate(R1, a1) + g
        dv = dtc / 6.0 * (f0 + 4.0 * fm + f1)
        dp_acc = dtc * dtc / 6.0 * (f0 + 2.0 * fm)
        # d f(tau) / d b_g = R(tau) [a(tau)]x Jr(theta(tau)) tau, since theta(tau) holds -b_g tau.
        Jm = Rm @ skew_batch(am) @ Jrm * (0.5 * dt3)
        J1 = R1 @ skew_batch(a1) @ Jr * dt3
        phi[:, VEL : VEL + 3, BG : BG + 3] = dt3 / 6.0 * (4.0 * Jm + J1)
        phi[:, POS : POS + 3, BG : BG + 3] = dt3 * dt3 / 6.0 * (2.0 * Jm)
        phi[:, VEL : VEL + 3, BA : BA + 3] = -dt3 / 6.0 * (R0 + 4.0 * Rm + R1)
        phi[:, POS : POS + 3, BA : BA + 3] = -dt3 * dt3 / 6.0 * (R0 + 2.0 * Rm)
    v = np.cumsum(np.vstack([imu.v_WB[None], dv]), axis=0)
    # p_{k+1} = (p_k + v_k dt_k) + dp_k in the per-sample order (a cumsum would group the terms otherwise).
    vdt = v[:-1] * dtc
    p = np.empty((m + 1, 3))
    p[0] = imu.p_WB
    for k in range(m):
        p[k + 1] = p[k] + vdt[k] + dp_acc[k]
    # 3. First-estimates blocks: interval 0 starts at the first estimates, the others at the chained values.
    fej = imu if imu_fej is None else imu_fej
    R0f, v0f, p0f = R0.copy(), v[:-1].copy(), p[:-1].copy()
    R0f[0], v0f[0], p0f[0] = fej.R_WB, fej.v_WB, fej.p_WB
    phi[:, THETA : THETA + 3, THETA : THETA + 3] = np.swapaxes(R1, 1, 2) @ R0f
    phi[:, THETA : THETA + 3, BG : BG + 3] = -Jr * dt3
    phi[:, VEL : VEL + 3, THETA : THETA + 3] = -skew_batch(v[1:] - v0f - g * dtc) @ R0f
    phi[:, POS : POS + 3, THETA : THETA + 3] = (
        -skew_batch(p[1:] - p0f - v0f * dtc - 0.5 * g * dtc * dtc) @ R0f
    )
    for i in range(3):
        phi[:, POS + i, VEL + i] = dt
    new = ImuValues(R[m].copy(), p[m], v[m], imu.gyro_bias_rad_s.copy(), imu.accel_bias_m_s2.copy())
    return new, phi


def discrete_noise_batch(phi: np.ndarray, noise: ImuNoise, dt: np.ndarray) -> np.ndarray:
    """Stacked :func:`discrete_noise`: ``phi`` (m, 15, 15), ``dt`` (m,) s -> ``Q`` (m, 15, 15)."""
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


def propagate_values(
    imu: ImuValues,
    t_s: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    method: Integration,
    noise: ImuNoise,
    imu_fej: ImuValues | None = None,
) -> tuple[ImuValues, np.ndarray, np.ndarray]:
    """Integrate selected readings (from :func:`select_imu_readings`) and accumulate ``Phi`` and ``Q``.

    The mean and every interval's ``Phi_k``, ``Q_k`` come from :func:`integrate_batch` and
    :func:`discrete_noise_batch`; the span's ``Phi = Phi_{m-1} ... Phi_0`` and
    ``Q = sum_k Phi_(m-1..k+1) Q_k Phi_(m-1..k+1)^T`` are accumulated in the recursion order of the
    per-sample filter, so the state covariance is propagated once per span (:func:`ekf_propagate`).
    Equal to chaining :func:`integrate_step` and :func:`discrete_noise` per interval to round-off
    (``tests/test_propagator.py``).

    Args:
        imu: State at ``t_s[0]``.
        t_s: Reading times (s), shape (n,), n >= 2.
        gyro: Raw gyro readings (rad/s), shape (n, 3) (biases are removed here).
        accel: Raw accelerometer readings (m/s^2), shape (n, 3).
        method: Integration method.
        noise: IMU noise densities.
        imu_fej: First estimates at ``t_s[0]`` (None: plain Jacobians).

    Returns:
        ``(state at t_s[-1], Phi (15, 15), Q (15, 15))`` over the whole span.
    """
    w = gyro - imu.gyro_bias_rad_s
    a = accel - imu.accel_bias_m_s2
    dt = np.diff(t_s)
    k = np.flatnonzero(dt > 0.0)  # zero-length intervals (duplicate end points) are skipped
    if k.size == 0:
        return imu.copy(), np.eye(IMU_DIM), np.zeros((IMU_DIM, IMU_DIM))
    if k.size == 1:
        # One interval (the per-control-tick prediction): the scalar step has less array overhead (1.7x).
        j, dt_j = int(k[0]), float(dt[k[0]])
        cur, phi1 = integrate_step(imu, w[j], w[j + 1], a[j], a[j + 1], dt_j, method, imu_fej)
        return cur, phi1, discrete_noise(phi1, noise, dt_j)
    dt = dt[k]
    cur, phi = integrate_batch(imu, w[k], w[k + 1], a[k], a[k + 1], dt, method, imu_fej)
    q = discrete_noise_batch(phi, noise, dt)
    phi_tot, q_tot = phi[0], q[0]
    for j in range(1, k.size):
        phi_tot = phi[j] @ phi_tot
        q_tot = phi[j] @ q_tot @ phi[j].T + q[j]
    return cur, phi_tot.copy(), q_tot.copy()


class Propagator:
    """Buffers IMU readings and propagates a :class:`State` to camera times.

    Args:
        noise: IMU noise densities (Kalibr).
        method: Integration method.
        use_fej: Evaluate the transition matrix at first estimates.
        keep_history_s: Readings older than the state time minus this are dropped (s).
    """

    def __init__(
        self,
        noise: ImuNoise,
        method: Integration = Integration.RK4,
        use_fej: bool = True,
        keep_history_s: float = 2.0,
    ) -> None:
        """Create an empty propagator."""
        self.noise = noise
        self.method = Integration(method)
        self.use_fej = use_fej
        self.keep_history_s = keep_history_s
        self.buffer = ImuBuffer()
        self.extrapolated_intervals = 0

    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer one reading (ValueError on NaN/inf values or non-increasing time)."""
        self.buffer.feed(sample)

    def readings(self, t0_s: float, t1_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Buffered readings over ``[t0_s, t1_s]`` with interpolated ends (:func:`select_imu_readings`)."""
        t, g, a = self.buffer.arrays()
        if self.buffer.last_t_s is not None and t1_s > self.buffer.last_t_s:
            self.extrapolated_intervals += 1
        return select_imu_readings(t, g, a, t0_s, t1_s)

    def omega_at(self, state: State, t_s: float) -> np.ndarray:
        """Bias-corrected angular rate (rad/s) in B at ``t_s``, shape (3,)."""
        t, g, _ = self.buffer.arrays()
        if len(t) == 0:
            return np.zeros(3)
        return interpolate_readings(t, g, t_s) - state.imu.gyro_bias_rad_s

    def propagate(self, state: State, t_s: float) -> None:
        """Propagate the state and covariance to ``t_s`` (IMU clock); no-op when ``t_s <= state.t_s``."""
        if t_s <= state.t_s:
            return
        t, g, a = self.readings(state.t_s, t_s)
        fej = state.imu_fej if self.use_fej else None
        new, phi, q = propagate_values(state.imu, t, g, a, self.method, self.noise, fej)
        state.imu = new
        state.t_s = float(t_s)
        ekf_propagate(state, phi, q)
        set_imu_fej(state)
        self.buffer.clean_older_than(state.t_s - self.keep_history_s)

    def predict(
        self, start_imu: ImuValues, start_t_s: float, t_s: float
    ) -> tuple[ImuValues, np.ndarray, np.ndarray]:
        """Propagate nominal values from ``start_t_s`` to ``t_s`` without touching any state.

        Returns:
            ``(values at t_s, Phi (15, 15), Q (15, 15))``; identity/zero when ``t_s <= start_t_s``.
        """
        if t_s <= start_t_s or len(self.buffer) == 0:
            return start_imu.copy(), np.eye(IMU_DIM), np.zeros((IMU_DIM, IMU_DIM))
        t, g, a = select_imu_readings(*self.buffer.arrays(), start_t_s, t_s)
        return propagate_values(start_imu, t, g, a, self.method, self.noise)

    def propagate_and_clone(self, state: State, t_cam_s: float) -> None:
        """Propagate to the IMU time ``t_cam_s + time_offset`` and clone the pose keyed by ``t_cam_s``."""
        t_imu = t_cam_s + state.time_offset_s
        self.propagate(state, t_imu)
        augment_clone(state, t_cam_s, self.omega_at(state, state.t_s))
