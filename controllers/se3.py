"""Geometric tracking controller on SE(3).

Lee, Leok and McClamroch, "Geometric tracking control of a quadrotor UAV on SE(3)", CDC 2010 (their
eqs. 15-16, rewritten for a z-up world), with the flatness feed-forward of the body rate from Mellinger and
Kumar, "Minimum snap trajectory generation and control for quadrotors", ICRA 2011 (sec. IV).
Layout follows rotorpy ``controllers/quadrotor_control.py``:

1. Desired force ``F_d = -k_p e_p - k_v e_v - k_i int(e_p) + m g e_3 + m a_d`` (W), with ``e_p = p - p_d``,
   ``e_v = v - v_d``; the horizontal part is limited to a maximum tilt.
2. Collective thrust ``T = F_d . R e_3`` (projection on the current body z axis ``b_3``).
3. Desired attitude ``R_d = [b_1d, b_2d, b_3d]``: ``b_3d = F_d / |F_d|``, ``b_2d = b_3d x b_1c / |.|`` with
   ``b_1c = (cos psi, sin psi, 0)``, ``b_1d = b_2d x b_3d``.
4. Errors ``e_R = 1/2 vee(R_d^T R - R^T R_d)``, ``e_w = w - R^T R_d w_d``; ``w_d`` from jerk and yaw rate.
5. Moments ``M = -k_R e_R - k_w e_w + w x J w - J (hat(w) R^T R_d w_d)`` (the ``dot w_d`` term needs snap and
   is taken as zero).
6. Mixer: motor thrusts with saturation (yaw given up first, see :mod:`viotb.controllers.mixer`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from viotb.controllers.mixer import Mixer
from viotb.controllers.types import ControlCommand, FlatOutput, NavState
from viotb.controllers.vehicle import VehicleParams
from viotb.vio.types import StateEstimate

_MAX_INTEGRATION_STEP_S = 0.1
"""Longer gaps between updates (e.g. after a pause) are not integrated."""
_NAV_SHAPES = ((3, 3), (3,), (3,), (3,))
"""Shapes of ``R_WB``, ``p_WB``, ``v_WB``, ``omega_B`` in a navigation state."""


def _arr(values: tuple[float, ...]) -> np.ndarray:
    return np.array(values, dtype=float)


@dataclass(frozen=True)
class SE3Gains:
    """Gains of :class:`SE3Controller`, tuned for the 1.2 kg ``models/quadrotor.xml`` at 200-500 Hz.

    Position loop: natural frequency about 3 rad/s (x, y) and 4 rad/s (z), damping ratio about 1, so a 1 m
    step settles in about 2 s without overshoot, and 3 cm of position noise moves the thrust by about 3 %.
    Attitude loop: about 20 rad/s, damping ratio 0.9 (roll, pitch) and 8.5 rad/s, ratio 1.05 (yaw); the rotor
    drag moment saturates near 0.19 N m, and a 90 deg yaw step settles in about 1 s without overshoot.

    Attributes:
        kp_N_m: Position gain (N/m), shape (3,).
        kv_N_s_m: Velocity gain (N s/m), shape (3,).
        ki_N_m_s: Integral gain on the position error (N/(m s)), shape (3,); zero disables the integral.
        integral_limit_N: Anti-windup clamp on each component of the integral force ``k_i int(e_p)`` (N).
        kR_Nm_rad: Attitude gain (N m/rad), shape (3,).
        kw_Nm_s_rad: Body-rate gain (N m s/rad), shape (3,).
        max_tilt_rad: Largest angle between the desired thrust and world z (rad).
        min_thrust_fraction: Floor on the vertical part of the desired force, as a fraction of ``m g``.
    """

    kp_N_m: np.ndarray = field(default_factory=lambda: _arr((10.8, 10.8, 19.2)))
    kv_N_s_m: np.ndarray = field(default_factory=lambda: _arr((7.2, 7.2, 9.6)))
    ki_N_m_s: np.ndarray = field(default_factory=lambda: _arr((0.0, 0.0, 0.0)))
    integral_limit_N: float = 2.0
    kR_Nm_rad: np.ndarray = field(default_factory=lambda: _arr((4.9, 4.9, 1.6)))
    kw_Nm_s_rad: np.ndarray = field(default_factory=lambda: _arr((0.44, 0.44, 0.4)))
    max_tilt_rad: float = np.deg2rad(35.0)
    min_thrust_fraction: float = 0.1

    def __post_init__(self) -> None:
        """Validate shapes and signs; store read-only float arrays."""
        for name in ("kp_N_m", "kv_N_s_m", "ki_N_m_s", "kR_Nm_rad", "kw_Nm_s_rad"):
            arr = np.array(getattr(self, name), dtype=float)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)) or np.any(arr < 0.0):
                raise ValueError(f"SE3Gains.{name}: need 3 finite non-negative values, got {arr.tolist()}")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        if not 0.0 < self.max_tilt_rad < np.pi / 2:
            raise ValueError(f"SE3Gains.max_tilt_rad must be in (0, pi/2), got {self.max_tilt_rad}")
        if not 0.0 < self.min_thrust_fraction <= 1.0:
            raise ValueError(
                f"SE3Gains.min_thrust_fraction must be in (0, 1], got {self.min_thrust_fraction}"
            )
        if not self.integral_limit_N >= 0.0:
            raise ValueError(f"SE3Gains.integral_limit_N must be >= 0, got {self.integral_limit_N}")


def _desired_axes(f0: float, f1: float, f2: float, yaw_rad: float) -> tuple[tuple[float, ...], ...]:
    """Columns ``(b_1d, b_2d, b_3d)`` of ``R_WB_d`` in plain floats (see :func:`desired_attitude`)."""
    n = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
    b30, b31, b32 = f0 / n, f1 / n, f2 / n
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    # b_2d = b_3d x b_1c with b_1c = (c, s, 0), normalised (nonzero: the tilt limit keeps b_3d off the plane).
    b20, b21, b22 = -b32 * s, b32 * c, b30 * s - b31 * c
    n2 = math.sqrt(b20 * b20 + b21 * b21 + b22 * b22)
    b20, b21, b22 = b20 / n2, b21 / n2, b22 / n2
    b1 = (b21 * b32 - b22 * b31, b22 * b30 - b20 * b32, b20 * b31 - b21 * b30)
    return b1, (b20, b21, b22), (b30, b31, b32)


def desired_attitude(force_W: np.ndarray, yaw_rad: float) -> np.ndarray:
    """Desired attitude ``R_WB_d`` (3, 3) with z axis along ``force_W`` (3,) and heading ``yaw_rad``.

    Lee et al. 2010, sec. III-A: ``b_2d = b_3d x b_1c`` normalised, ``b_1d = b_2d x b_3d``.
    """
    f0, f1, f2 = np.asarray(force_W, dtype=float).tolist()
    return np.array(_desired_axes(f0, f1, f2, float(yaw_rad))).T


def _attitude_error(R: list, b1: tuple, b2: tuple, b3: tuple) -> tuple[float, float, float]:
    """``e_R`` of :func:`attitude_error` for ``R`` as rows and ``R_d`` as columns, in plain floats.

    With ``A = R_d^T R`` (``A_ij = b_i . R[:, j]``), ``1/2 vee(A - A^T) = 1/2 (A_21 - A_12, A_02 - A_20,
    A_10 - A_01)``.
    """
    r0, r1, r2 = R
    a01 = b1[0] * r0[1] + b1[1] * r1[1] + b1[2] * r2[1]
    a02 = b1[0] * r0[2] + b1[1] * r1[2] + b1[2] * r2[2]
    a10 = b2[0] * r0[0] + b2[1] * r1[0] + b2[2] * r2[0]
    a12 = b2[0] * r0[2] + b2[1] * r1[2] + b2[2] * r2[2]
    a20 = b3[0] * r0[0] + b3[1] * r1[0] + b3[2] * r2[0]
    a21 = b3[0] * r0[1] + b3[1] * r1[1] + b3[2] * r2[1]
    return 0.5 * (a21 - a12), 0.5 * (a02 - a20), 0.5 * (a10 - a01)


def attitude_error(R_WB: np.ndarray, R_WB_desired: np.ndarray) -> np.ndarray:
    """Attitude error ``e_R = 1/2 vee(R_d^T R - R^T R_d)`` in B (3,) (Lee et al. 2010, eq. 10)."""
    b1, b2, b3 = np.asarray(R_WB_desired, dtype=float).T.tolist()
    return np.array(_attitude_error(np.asarray(R_WB, dtype=float).tolist(), b1, b2, b3))


def _desired_body_rate(
    b1: tuple, b2: tuple, b3: tuple, thrust_N: float, mass_kg: float, j: tuple | list, yaw_rate_rad_s: float
) -> tuple[float, float, float]:
    """:func:`desired_body_rate` in plain floats (``R_d`` as its columns, jerk ``j`` (3,))."""
    b3j = b3[0] * j[0] + b3[1] * j[1] + b3[2] * j[2]
    k = mass_kg / thrust_N
    h0, h1, h2 = k * (j[0] - b3j * b3[0]), k * (j[1] - b3j * b3[1]), k * (j[2] - b3j * b3[2])
    return (
        -(h0 * b2[0] + h1 * b2[1] + h2 * b2[2]),
        h0 * b1[0] + h1 * b1[1] + h2 * b1[2],
        yaw_rate_rad_s * b3[2],
    )


def desired_body_rate(R_d: np.ndarray, thrust_N: float, mass_kg: float, setpoint: FlatOutput) -> np.ndarray:
    """Desired body rate in the desired frame (rad/s), shape (3,) (Mellinger & Kumar 2011, sec. IV).

    ``h_w = m / T (j - (b_3d . j) b_3d)``, ``w_d = (-h_w . b_2d, h_w . b_1d, psi_dot (e_3 . b_3d))``.
    The roll and pitch parts are exact when the desired force is ``m (a - g)``; the yaw part is the usual
    approximation.

    Args:
        R_d: Desired attitude, shape (3, 3).
        thrust_N: Magnitude of the desired force (N).
        mass_kg: Vehicle mass (kg).
        setpoint: Supplies the jerk ``j_W`` (m/s^3) and the yaw rate (rad/s).
    """
    b1, b2, b3 = np.asarray(R_d, dtype=float).T.tolist()
    return np.array(
        _desired_body_rate(
            b1, b2, b3, float(thrust_N), float(mass_kg), setpoint.j_W.tolist(), setpoint.yaw_rate_rad_s
        )
    )


class SE3Controller:
    """Geometric SE(3) position and attitude controller (see the module docstring for the equations).

    The per-tick arithmetic runs on plain Python floats (3-vectors as tuples): a few hundred float
    operations cost less than the dozens of small numpy calls they replace (~1 us each). Sums of products are
    taken left to right, where numpy's ``@`` uses BLAS (fused multiply-adds), so a command may differ from
    the numpy formulation in the last bits.

    Args:
        vehicle: Mass, inertia and rotor parameters (read from the MJCF).
        gains: Controller gains.
        mixer: Motor mixer; built from ``vehicle`` when omitted.
    """

    def __init__(
        self, vehicle: VehicleParams, gains: SE3Gains | None = None, mixer: Mixer | None = None
    ) -> None:
        """Store parameters and reset the integral state."""
        self._vehicle = vehicle
        self._gains = gains if gains is not None else SE3Gains()
        self._mixer = mixer if mixer is not None else Mixer(vehicle)
        self._last_t_s: float | None = None
        # Constants of the gains and the vehicle as plain floats, built once (the gains are frozen).
        g = self._gains
        ki = g.ki_N_m_s
        limit = np.full(3, np.inf)
        np.divide(g.integral_limit_N, ki, out=limit, where=ki > 0.0)
        self._integral_limit_m_s = tuple(limit.tolist())
        self._integral_m_s = (0.0, 0.0, 0.0)
        self._kp = tuple(g.kp_N_m.tolist())
        self._kv = tuple(g.kv_N_s_m.tolist())
        self._ki = tuple(ki.tolist())
        self._kR = tuple(g.kR_Nm_rad.tolist())
        self._kw = tuple(g.kw_Nm_s_rad.tolist())
        self._J = tuple(tuple(row) for row in vehicle.inertia_kg_m2.tolist())
        self._gravity_W = tuple(vehicle.gravity_W_m_s2.tolist())
        self._mass_kg = vehicle.mass_kg
        self._tan_max_tilt = math.tan(g.max_tilt_rad)
        self._min_thrust_N = g.min_thrust_fraction * vehicle.hover_thrust_N

    @property
    def gains(self) -> SE3Gains:
        """The controller's gains."""
        return self._gains

    @property
    def integral_m_s(self) -> np.ndarray:
        """Integral of the position error (m s), shape (3,), as clamped by the anti-windup."""
        return np.array(self._integral_m_s)

    def reset(self) -> None:
        """Clear the integral state and the time of the last update."""
        self._integral_m_s = (0.0, 0.0, 0.0)
        self._last_t_s = None

    def update(self, t_s: float, state: NavState, setpoint: FlatOutput) -> ControlCommand:
        """Motor command for ``state`` tracking ``setpoint`` at time ``t_s`` (s)."""
        thrusts, axes = self._thrusts_and_axes(t_s, state, setpoint)
        # Report the wrench the motors actually produce.
        produced_collective, produced_moments = self._mixer.wrench(thrusts)
        return ControlCommand(
            thrusts_N=thrusts,
            collective_N=produced_collective,
            moments_B_Nm=produced_moments,
            R_WB_desired=np.array(axes).T,
        )

    def thrusts(self, t_s: float, state: NavState, setpoint: FlatOutput) -> np.ndarray:
        """Motor thrusts (N), shape (4,): ``update(...).thrusts_N`` without building the full command.

        For loops that use only the thrusts (the flight runner and the Gymnasium envs, every low-level tick);
        the integral state advances exactly as in :meth:`update`.
        """
        return self._thrusts_and_axes(t_s, state, setpoint)[0]

    def thrusts_from_estimate(self, t_s: float, estimate: StateEstimate, setpoint: FlatOutput) -> np.ndarray:
        """``thrusts(t_s, NavState.from_estimate(estimate), setpoint)`` without building the record.

        The per-tick call of the flight runner and the envs: the estimate's arrays are read as floats once
        (shapes checked, finiteness by one sum) instead of being copied into a validated record. An estimate
        the record would reject takes the record's path, so the same ``ValueError`` names the field.
        """
        R_a, p_a, v_a, w_a = estimate.R_WB, estimate.p_WB, estimate.v_WB, estimate.omega_B_rad_s
        if (R_a.shape, p_a.shape, v_a.shape, w_a.shape) == _NAV_SHAPES:
            R, p, v, w = R_a.tolist(), p_a.tolist(), v_a.tolist(), w_a.tolist()
            if math.isfinite(sum(R[0]) + sum(R[1]) + sum(R[2]) + sum(p) + sum(v) + sum(w)):
                return self._thrusts_f(t_s, R, p, v, w, setpoint)[0]
        return self.thrusts(t_s, NavState.from_estimate(estimate), setpoint)

    def _thrusts_and_axes(
        self, t_s: float, state: NavState, setpoint: FlatOutput
    ) -> tuple[np.ndarray, tuple]:
        """Steps 1-6 above: motor thrusts (N), shape (4,), and the columns ``(b_1d, b_2d, b_3d)`` of R_d."""
        R, p, v = state.R_WB.tolist(), state.p_WB.tolist(), state.v_WB.tolist()
        return self._thrusts_f(t_s, R, p, v, state.omega_B.tolist(), setpoint)

    def _thrusts_f(
        self, t_s: float, R: list, p: list, v: list, w: list, setpoint: FlatOutput
    ) -> tuple[np.ndarray, tuple]:
        """:meth:`_thrusts_and_axes` on the state as floats: ``R`` (3 rows of 3), ``p``, ``v``, ``w`` (3)."""
        m = self._mass_kg
        p0, p1, p2 = p
        v0, v1, v2 = v
        w0, w1, w2 = w
        pd0, pd1, pd2, vd0, vd1, vd2, ad0, ad1, ad2, jd0, jd1, jd2 = setpoint.vector_floats

        # 1. Desired force in W, with the integral (clamped: anti-windup) and the tilt limit.
        e_p = (p0 - pd0, p1 - pd1, p2 - pd2)
        e_v = (v0 - vd0, v1 - vd1, v2 - vd2)
        self._integrate(t_s, e_p)
        kp, kv, ki, ig, gw = self._kp, self._kv, self._ki, self._integral_m_s, self._gravity_W
        f0 = -kp[0] * e_p[0] - kv[0] * e_v[0] - ki[0] * ig[0] + m * (ad0 - gw[0])
        f1 = -kp[1] * e_p[1] - kv[1] * e_v[1] - ki[1] * ig[1] + m * (ad1 - gw[1])
        f2 = -kp[2] * e_p[2] - kv[2] * e_v[2] - ki[2] * ig[2] + m * (ad2 - gw[2])
        f0, f1, f2 = self._limit_tilt(f0, f1, f2)

        # 2. Collective thrust along the current body z axis (the third column of R).
        collective_N = f0 * R[0][2] + f1 * R[1][2] + f2 * R[2][2]

        # 3. Desired attitude from the force direction and the yaw setpoint.
        b1, b2, b3 = _desired_axes(f0, f1, f2, setpoint.yaw_rad)

        # 4. Desired body rate (flatness feed-forward) and the attitude / rate errors.
        thrust_N = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        wd0, wd1, wd2 = _desired_body_rate(b1, b2, b3, thrust_N, m, (jd0, jd1, jd2), setpoint.yaw_rate_rad_s)
        # omega_d_B = R^T (R_d omega_d).
        u0 = b1[0] * wd0 + b2[0] * wd1 + b3[0] * wd2
        u1 = b1[1] * wd0 + b2[1] * wd1 + b3[1] * wd2
        u2 = b1[2] * wd0 + b2[2] * wd1 + b3[2] * wd2
        r0, r1, r2 = R
        o0 = r0[0] * u0 + r1[0] * u1 + r2[0] * u2
        o1 = r0[1] * u0 + r1[1] * u1 + r2[1] * u2
        o2 = r0[2] * u0 + r1[2] * u1 + r2[2] * u2
        eR0, eR1, eR2 = _attitude_error(R, b1, b2, b3)

        # 5. Moments M = -k_R e_R - k_w e_w + w x J w - J (w x omega_d_B), e_w = w - omega_d_B; the desired
        #    angular acceleration is taken as zero.
        J0, J1, J2 = self._J
        jw0 = J0[0] * w0 + J0[1] * w1 + J0[2] * w2
        jw1 = J1[0] * w0 + J1[1] * w1 + J1[2] * w2
        jw2 = J2[0] * w0 + J2[1] * w1 + J2[2] * w2
        c0, c1, c2 = w1 * o2 - w2 * o1, w2 * o0 - w0 * o2, w0 * o1 - w1 * o0
        kR, kw = self._kR, self._kw
        mx = -kR[0] * eR0 - kw[0] * (w0 - o0) + (w1 * jw2 - w2 * jw1) - (J0[0] * c0 + J0[1] * c1 + J0[2] * c2)
        my = -kR[1] * eR1 - kw[1] * (w1 - o1) + (w2 * jw0 - w0 * jw2) - (J1[0] * c0 + J1[1] * c1 + J1[2] * c2)
        mz = -kR[2] * eR2 - kw[2] * (w2 - o2) + (w0 * jw1 - w1 * jw0) - (J2[0] * c0 + J2[1] * c1 + J2[2] * c2)

        # 6. Mix and saturate.
        return self._mixer.motor_thrusts_f(collective_N, mx, my, mz), (b1, b2, b3)

    def _integrate(self, t_s: float, e_p: tuple[float, float, float]) -> None:
        """Accumulate the position error over the time since the last update (clamped, anti-windup)."""
        ig = self._integral_m_s
        if self._last_t_s is not None:
            dt = t_s - self._last_t_s
            if 0.0 < dt <= _MAX_INTEGRATION_STEP_S:
                ig = (ig[0] + e_p[0] * dt, ig[1] + e_p[1] * dt, ig[2] + e_p[2] * dt)
        self._last_t_s = float(t_s)
        (i0, i1, i2), (b0, b1, b2) = ig, self._integral_limit_m_s
        self._integral_m_s = (min(max(i0, -b0), b0), min(max(i1, -b1), b1), min(max(i2, -b2), b2))

    def _limit_tilt(self, f0: float, f1: float, f2: float) -> tuple[float, float, float]:
        """Keep the vertical force above ``min_thrust_fraction m g`` and the tilt below ``max_tilt_rad``."""
        f2 = max(f2, self._min_thrust_N)
        horizontal = math.sqrt(f0 * f0 + f1 * f1)
        max_horizontal = f2 * self._tan_max_tilt
        if horizontal > max_horizontal:
            scale = max_horizontal / horizontal
            f0, f1 = f0 * scale, f1 * scale
        return f0, f1, f2
