"""The compiled propagation (:mod:`viotb.vio.imu_kernels`) behind the records the estimator passes around.

Each function here returns what its numpy reference in :mod:`viotb.vio.imu_integration` returns, computed by
the kernels: :func:`mean_record` is ``integrate_mean``, :func:`step_links` is ``step_transitions`` with
``discrete_noise_batch``, :func:`propagate_span_values` is ``propagate_values`` without online intrinsics,
:func:`chain_links` the prediction chain's running totals. Equal to the references to 1e-9 relative
(``tests/test_imu_kernels.py``); the last bits differ where a 3 x 3 or 15 x 15 product is summed in another
order than numpy's BLAS sums it.
"""

from __future__ import annotations

import numpy as np
from viotb.vio import imu_kernels as kernels
from viotb.vio.imu_integration import Integration, StepMean
from viotb.vio.state import ImuValues
from viotb.vio.types import ImuNoise, gravity_W


def noise_vector(noise: ImuNoise) -> np.ndarray:
    """The four densities the kernels take, shape (4,).

    In ``ImuNoise`` order: gyro white (rad/s/sqrt(Hz)), gyro walk (rad/s^2/sqrt(Hz)), accel white
    (m/s^2/sqrt(Hz)), accel walk (m/s^3/sqrt(Hz)).
    """
    return np.array(
        [
            noise.gyro_noise_density_rad_s_sqrthz,
            noise.gyro_random_walk_rad_s2_sqrthz,
            noise.accel_noise_density_m_s2_sqrthz,
            noise.accel_random_walk_m_s3_sqrthz,
        ]
    )


def mean_record(
    imu: ImuValues,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: float,
    method: Integration,
    raw: np.ndarray | None = None,
) -> StepMean:
    """:func:`~viotb.vio.imu_integration.integrate_mean` by :func:`~viotb.vio.imu_kernels.mean_step`.

    Args:
        imu: State at the start of the interval (biases are held).
        w0: Corrected angular rates (rad/s) in B at the start and end, shape (3,).
        w1: See ``w0``.
        a0: Corrected specific forces (m/s^2) in B at the start and end, shape (3,).
        a1: See ``a0``.
        dt: Interval length (s), > 0.
        method: Integration method.
        raw: Kept in the record for the intrinsic columns; None without them.
    """
    rk4 = method == Integration.RK4
    rec = kernels.mean_step(imu.R_WB, imu.p_WB, imu.v_WB, w0, w1, a0, a1, float(dt), rk4, gravity_W())
    R1 = rec[0:3]
    new = ImuValues(R1, rec[3], rec[4], imu.gyro_bias_rad_s.copy(), imu.accel_bias_m_s2.copy())
    if not rk4:
        return StepMean(imu, new, method, dt, rec[5], R1, None, None, None, a1, raw, rec)
    return StepMean(imu, new, method, dt, rec[5], R1, rec[6], rec[7:10], rec[10], a1, raw, rec)


def _records(steps: list[StepMean]) -> np.ndarray:
    """The steps' kernel records stacked, shape (m, RECORD_ROWS, 3) (built from the fields where missing)."""
    rows = []
    for s in steps:
        if s.packed is not None:
            rows.append(s.packed)
            continue
        rec = np.zeros((kernels.RECORD_ROWS, 3))
        rec[0:3], rec[3], rec[4], rec[5] = s.R1, s.new.p_WB, s.new.v_WB, s.theta
        if s.method == Integration.RK4:
            rec[6], rec[7:10], rec[10] = s.theta_m, s.Rm, s.am
        rec[11:14], rec[14], rec[15], rec[16] = s.start.R_WB, s.start.p_WB, s.start.v_WB, s.a1
        rows.append(rec)
    return np.array(rows)


def step_links(steps: list[StepMean], noise: ImuNoise) -> tuple[np.ndarray, np.ndarray]:
    """Plain-Jacobian ``(Phi, Q)`` of recorded intervals of one method (no intrinsics), (m, 15, 15) each.

    :func:`~viotb.vio.imu_integration.step_transitions` and ``discrete_noise_batch`` by
    :func:`~viotb.vio.imu_kernels.step_phis_qs`.
    """
    rk4 = steps[0].method == Integration.RK4
    dt = np.array([s.dt for s in steps], dtype=float)
    out = kernels.step_phis_qs(_records(steps), dt, rk4, gravity_W(), noise_vector(noise))
    return out[0], out[1]


def step_chain_totals(
    steps: list[StepMean], noise: ImuNoise, phi0: np.ndarray, q0: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`step_links` then :func:`chain_links` in one kernel: the running totals, (m, 15, 15) each."""
    rk4 = steps[0].method == Integration.RK4
    dt = np.array([s.dt for s in steps], dtype=float)
    out = kernels.step_chain(_records(steps), dt, rk4, gravity_W(), noise_vector(noise), phi0, q0)
    return out[0], out[1]


def chain_links(
    phis: np.ndarray, qs: np.ndarray, phi0: np.ndarray, q0: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A chain's running totals ``(phi_tots, q_tots)``, (m, d, d) each (``imu_kernels.chain_totals``)."""
    out = kernels.chain_totals(
        np.ascontiguousarray(phis, dtype=float),
        np.ascontiguousarray(qs, dtype=float),
        np.ascontiguousarray(phi0, dtype=float),
        np.ascontiguousarray(q0, dtype=float),
    )
    return out[0], out[1]


def propagate_span_values(
    imu: ImuValues,
    w0: np.ndarray,
    w1: np.ndarray,
    a0: np.ndarray,
    a1: np.ndarray,
    dt: np.ndarray,
    method: Integration,
    noise: ImuNoise,
    imu_fej: ImuValues | None = None,
) -> tuple[ImuValues, np.ndarray, np.ndarray]:
    """A span's ``(state at the end, Phi (15, 15), Q (15, 15))``, as ``propagate_values`` (no intrinsics).

    Args:
        imu: State at the start of the first interval (biases are held).
        w0: Corrected rates (rad/s) at the interval starts, shape (m, 3); ``w1`` at the ends.
        w1: See ``w0``.
        a0: Corrected specific forces (m/s^2) at the starts, shape (m, 3); ``a1`` at the ends.
        a1: See ``a0``.
        dt: Interval lengths (s), shape (m,), all > 0.
        method: Integration method.
        noise: IMU noise densities.
        imu_fej: First estimates at the start (None: ``imu``).
    """
    fej = imu if imu_fej is None else imu_fej
    state, phq = kernels.propagate_span(
        imu.R_WB,
        imu.p_WB,
        imu.v_WB,
        np.ascontiguousarray(w0, dtype=float),
        np.ascontiguousarray(w1, dtype=float),
        np.ascontiguousarray(a0, dtype=float),
        np.ascontiguousarray(a1, dtype=float),
        np.ascontiguousarray(dt, dtype=float),
        fej.R_WB,
        fej.p_WB,
        fej.v_WB,
        method == Integration.RK4,
        gravity_W(),
        noise_vector(noise),
    )
    new = ImuValues(state[0:3], state[3], state[4], imu.gyro_bias_rad_s.copy(), imu.accel_bias_m_s2.copy())
    return new, phq[0], phq[1]


def warm_up() -> None:
    """Load (or, on a machine's first run, compile) every kernel with the argument types the filter uses.

    Numba loads a cached kernel on its first call in a process (about 0.7 s for the first, tens of ms
    for each further one). This module calls it when it is imported (with the estimator's modules, before
    any run is timed), so that the cost lands neither in the first control ticks of a flight nor in the
    first frames of a timed replay (``viotb regress``'s ``timing_ratio``). Costs tens of microseconds once
    loaded.
    """
    imu = ImuValues(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    w = np.array([[0.1, 0.2, 0.3], [0.2, 0.1, 0.0]])
    a = np.array([[0.0, 0.1, 9.8], [0.1, 0.0, 9.8]])
    noise = ImuNoise()
    for method in (Integration.RK4, Integration.DISCRETE):
        step = mean_record(imu, w[0], w[1], a[0], a[1], 0.005, method)
        phis, qs = step_links([step], noise)
        chain_links(phis, qs, np.eye(phis.shape[1]), np.zeros(phis.shape[1:]))
        step_chain_totals([step], noise, np.eye(phis.shape[1]), np.zeros(phis.shape[1:]))
        propagate_span_values(imu, w[:1], w[1:], a[:1], a[1:], np.array([0.005]), method, noise)


warm_up()  # at import: the kernels' one-off load, outside any timed loop (see warm_up)
