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

With online IMU intrinsics (:mod:`viotb.vio.imu_intrinsics`) the readings are ``w = T_g (gyro - b_g)``,
``a = T_a (accel - b_a)``, the bias columns are the above times ``T_g`` / ``T_a``, and ``Phi`` gains the
columns of the intrinsic blocks (:func:`~viotb.vio.imu_integration.intrinsic_columns`); the state's
``[imu, intrinsics]`` part is propagated together (:func:`~viotb.vio.state.ekf_propagate`).

Noise (Kalibr densities, see DESIGN.md): white gyro/accel noise acts over an interval like a bias offset of
variance ``density^2 / dt`` so it enters through the bias columns of ``Phi``; the random walks add
``density^2 dt`` to the bias blocks.
"""

from __future__ import annotations

import math

import numpy as np
from viotb.vio.imu_integration import (
    Integration,
    StepMean,
    discrete_noise,
    discrete_noise_batch,
    extend_transition,
    integrate_batch,
    integrate_mean,
    integrate_step,
    intrinsic_columns,
    step_transition,
    step_transitions,
    transition_batch,
)
from viotb.vio.imu_intrinsics import ImuIntrinsics, correct_readings
from viotb.vio.imu_kernels_calls import mean_record, propagate_span_values
from viotb.vio.state import (
    IMU_DIM,
    ImuValues,
    State,
    augment_clone,
    ekf_propagate,
    set_imu_fej,
)
from viotb.vio.types import ImuNoise, ImuSample

__all__ = [
    "ImuBuffer",
    "Integration",
    "Propagator",
    "StepMean",
    "discrete_noise",
    "discrete_noise_batch",
    "integrate_batch",
    "integrate_mean",
    "integrate_step",
    "interpolate_readings",
    "propagate_values",
    "select_imu_readings",
    "step_transition",
    "step_transitions",
    "transition_batch",
    "validate_imu_sample",
]


def validate_imu_sample(sample: ImuSample, last_t_s: float | None) -> None:
    """Raise a ValueError naming the field, value and time for a non-finite or out-of-order sample.

    A valid sample of two float64 (3,) arrays (every sample of the closed loop) is passed on plain floats;
    anything else takes the checks that name what is wrong.
    """
    t = float(sample.t_s)
    g, a = sample.gyro_B_rad_s, sample.accel_B_m_s2
    if type(g) is np.ndarray and type(a) is np.ndarray and g.shape == (3,) and a.shape == (3,):
        values = [t, *g.tolist(), *a.tolist()]
        finite = math.isfinite(sum(values)) or all(map(math.isfinite, values))  # exact (see below)
        if finite and (last_t_s is None or t > last_t_s) and g.dtype.kind in "fiu" and a.dtype.kind in "fiu":
            return
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


def propagate_values(
    imu: ImuValues,
    t_s: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    method: Integration,
    noise: ImuNoise,
    imu_fej: ImuValues | None = None,
    intrinsics: ImuIntrinsics | None = None,
    compiled: bool = True,
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
        intrinsics: Online IMU intrinsics (:mod:`viotb.vio.imu_intrinsics`): the readings are corrected
            with them and ``Phi``, ``Q`` cover ``[imu, intrinsic blocks]``; None: neither.
        compiled: Without intrinsics, compute all of it in the compiled kernel
            (:func:`~viotb.vio.imu_kernels_calls.propagate_span_values`, equal to the numpy path to 1e-9
            relative); False: the numpy functions above.

    Returns:
        ``(state at t_s[-1], Phi (d, d), Q (d, d))`` over the whole span, ``d = 15 + intrinsics.dim``.
    """
    w, a = correct_readings(intrinsics, gyro, accel, imu.gyro_bias_rad_s, imu.accel_bias_m_s2)
    dt = np.diff(t_s)
    k = np.flatnonzero(dt > 0.0)  # zero-length intervals (duplicate end points) are skipped
    d = IMU_DIM + (0 if intrinsics is None else intrinsics.dim)
    if k.size == 0:
        return imu.copy(), np.eye(d), np.zeros((d, d))
    if compiled and intrinsics is None:
        return propagate_span_values(imu, w[k], w[k + 1], a[k], a[k + 1], dt[k], method, noise, imu_fej)
    if k.size == 1 and intrinsics is None:
        # One interval (the per-control-tick prediction): the scalar step has less array overhead (1.7x).
        j, dt_j = int(k[0]), float(dt[k[0]])
        cur, phi1 = integrate_step(imu, w[j], w[j + 1], a[j], a[j + 1], dt_j, method, imu_fej)
        return cur, phi1, discrete_noise(phi1, noise, dt_j)
    dt = dt[k]
    cur, phi, parts = integrate_batch(imu, w[k], w[k + 1], a[k], a[k + 1], dt, method, imu_fej)
    if intrinsics is not None:
        wr, ar = gyro - imu.gyro_bias_rad_s, accel - imu.accel_bias_m_s2
        raw = np.stack([wr[k], wr[k + 1], ar[k], ar[k + 1]], axis=1)
        phi = extend_transition(phi, intrinsic_columns(method, dt, *parts, raw, intrinsics), intrinsics)
        return cur, *_chain_extended(phi, discrete_noise_batch(phi[:, :IMU_DIM, :IMU_DIM], noise, dt))
    q = discrete_noise_batch(phi, noise, dt)
    phi_tot, q_tot = phi[0], q[0]
    for j in range(1, k.size):
        phi_tot = phi[j] @ phi_tot
        q_tot = phi[j] @ q_tot @ phi[j].T + q[j]
    return cur, phi_tot.copy(), q_tot.copy()


def _chain_extended(phi: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The span's ``(Phi, Q)`` (d, d) from the intervals' ``[[A, C], [0, I]]`` (m, d, d) and Q (m, 15, 15).

    The intrinsic rows stay ``[0, I]`` and take no noise, so only ``A`` (15, 15), ``C`` (15, n) and the
    IMU noise are chained: ``C <- A_k C + C_k``, ``A <- A_k A``, ``Q <- A_k Q A_k^T + Q_k`` (the full
    product's blocks, in the same order).
    """
    A, C = phi[:, :IMU_DIM, :IMU_DIM], phi[:, :IMU_DIM, IMU_DIM:]
    a_tot, c_tot, q_tot = A[0], C[0], q[0]
    for j in range(1, phi.shape[0]):
        c_tot = A[j] @ c_tot + C[j]
        a_tot = A[j] @ a_tot
        q_tot = A[j] @ q_tot @ A[j].T + q[j]
    d = phi.shape[1]
    phi_tot, q_out = np.eye(d), np.zeros((d, d))
    phi_tot[:IMU_DIM, :IMU_DIM], phi_tot[:IMU_DIM, IMU_DIM:] = a_tot, c_tot
    q_out[:IMU_DIM, :IMU_DIM] = q_tot
    return phi_tot, q_out


class Propagator:
    """Buffers IMU readings and propagates a :class:`State` to camera times.

    Args:
        noise: IMU noise densities (Kalibr).
        method: Integration method.
        use_fej: Evaluate the transition matrix at first estimates.
        keep_history_s: Readings older than the state time minus this are dropped (s).
        compiled: Propagate and predict with the compiled kernels (:mod:`viotb.vio.imu_kernels`; online
            intrinsics keep the numpy path); False: the numpy reference functions.
    """

    def __init__(
        self,
        noise: ImuNoise,
        method: Integration = Integration.RK4,
        use_fej: bool = True,
        keep_history_s: float = 2.0,
        compiled: bool = True,
    ) -> None:
        """Create an empty propagator."""
        self.compiled = compiled
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
        """Corrected angular rate (rad/s) in B at ``t_s`` (bias and online intrinsics), shape (3,)."""
        t, g, _ = self.buffer.arrays()
        if len(t) == 0:
            return np.zeros(3)
        w = interpolate_readings(t, g, t_s) - state.imu.gyro_bias_rad_s
        return w if state.intrinsics is None else state.intrinsics.T_g @ w

    def propagate(self, state: State, t_s: float) -> None:
        """Propagate the state and covariance to ``t_s`` (IMU clock); no-op when ``t_s <= state.t_s``."""
        if t_s <= state.t_s:
            return
        t, g, a = self.readings(state.t_s, t_s)
        fej = state.imu_fej if self.use_fej else None
        new, phi, q = propagate_values(
            state.imu, t, g, a, self.method, self.noise, fej, state.intrinsics, self.compiled
        )
        state.imu = new
        state.t_s = float(t_s)
        ekf_propagate(state, phi, q)
        set_imu_fej(state)
        self.buffer.clean_older_than(state.t_s - self.keep_history_s)

    def predict(
        self, start_imu: ImuValues, start_t_s: float, t_s: float, intrinsics: ImuIntrinsics | None = None
    ) -> tuple[ImuValues, np.ndarray, np.ndarray]:
        """Propagate nominal values from ``start_t_s`` to ``t_s`` without touching any state.

        Returns:
            ``(values at t_s, Phi (d, d), Q (d, d))`` (``d`` as :func:`propagate_values`); identity/zero
            when ``t_s <= start_t_s``.
        """
        d = IMU_DIM + (0 if intrinsics is None else intrinsics.dim)
        if t_s <= start_t_s or len(self.buffer) == 0:
            return start_imu.copy(), np.eye(d), np.zeros((d, d))
        t, g, a = select_imu_readings(*self.buffer.arrays(), start_t_s, t_s)
        return propagate_values(start_imu, t, g, a, self.method, self.noise, None, intrinsics, self.compiled)

    def predict_mean(
        self, start_imu: ImuValues, start_t_s: float, t_s: float, intrinsics: ImuIntrinsics | None = None
    ) -> tuple[ImuValues, StepMean | tuple[np.ndarray, np.ndarray]]:
        """:meth:`predict` that leaves a single interval's ``Phi`` and ``Q`` to be built when needed.

        The same values as :meth:`predict`. The per-control-tick call (``start_t_s`` and ``t_s`` the two
        newest readings' times) takes those rows directly; :func:`select_imu_readings` returns the same ones.

        Returns:
            ``(values at t_s, step)``: ``step`` the interval's :class:`StepMean` (``Phi`` from
            :func:`step_transition`, ``Q`` from :func:`discrete_noise`) when ``[start_t_s, t_s]`` is one
            interval, else ``(Phi, Q)`` of the span as :meth:`predict` returns them.
        """
        n = len(self.buffer)
        if t_s <= start_t_s or n == 0:
            d = IMU_DIM + (0 if intrinsics is None else intrinsics.dim)
            return start_imu.copy(), (np.eye(d), np.zeros((d, d)))
        t, g, a = self.buffer.arrays()
        if n >= 2 and t[n - 2] == start_t_s and t[n - 1] == t_s:  # one interval (times increase)
            step = self._interval_mean(start_imu, t, g, a, n - 2, intrinsics)
            return step.new, step
        t, g, a = select_imu_readings(t, g, a, start_t_s, t_s)
        k = np.flatnonzero(np.diff(t) > 0.0)
        if k.size != 1:
            vals, phi, q = propagate_values(
                start_imu, t, g, a, self.method, self.noise, None, intrinsics, self.compiled
            )
            return vals, (phi, q)
        step = self._interval_mean(start_imu, t, g, a, int(k[0]), intrinsics)
        return step.new, step

    def _interval_mean(
        self,
        start_imu: ImuValues,
        t: np.ndarray,
        g: np.ndarray,
        a: np.ndarray,
        j: int,
        intrinsics: ImuIntrinsics | None = None,
    ) -> StepMean:
        """:func:`integrate_mean` over readings ``j``, ``j + 1``: ``t`` (n,) s, raw ``g``, ``a`` (n, 3)."""
        b_g, b_a = start_imu.gyro_bias_rad_s, start_imu.accel_bias_m_s2
        w, f = correct_readings(intrinsics, g[j : j + 2], a[j : j + 2], b_g, b_a)
        raw = None
        if intrinsics is not None:
            raw = np.vstack([g[j : j + 2] - b_g, a[j : j + 2] - b_a])
        dt = float(t[j + 1] - t[j])
        integrate = mean_record if self.compiled else integrate_mean
        return integrate(start_imu, w[0], w[1], f[0], f[1], dt, self.method, raw)

    def propagate_and_clone(self, state: State, t_cam_s: float) -> None:
        """Propagate to the IMU time ``t_cam_s + time_offset`` and clone the pose keyed by ``t_cam_s``."""
        t_imu = t_cam_s + state.time_offset_s
        self.propagate(state, t_imu)
        augment_clone(state, t_cam_s, self.omega_at(state, state.t_s))
