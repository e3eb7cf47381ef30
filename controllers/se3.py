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

from dataclasses import dataclass, field

import numpy as np
from viotb.controllers.mixer import Mixer
from viotb.controllers.types import ControlCommand, FlatOutput, NavState
from viotb.controllers.vehicle import VehicleParams
from viotb.vio.lie import cross, skew, vee

_E3 = np.array([0.0, 0.0, 1.0])
_MAX_INTEGRATION_STEP_S = 0.1
"""Longer gaps between updates (e.g. after a pause) are not integrated."""


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


def desired_attitude(force_W: np.ndarray, yaw_rad: float) -> np.ndarray:
    """Desired attitude ``R_WB_d`` (3, 3) with z axis along ``force_W`` (3,) and heading ``yaw_rad``.

    Lee et al. 2010, sec. III-A: ``b_2d = b_3d x b_1c`` normalised, ``b_1d = b_2d x b_3d``.
    """
    b3 = force_W / np.linalg.norm(force_W)
    b1c = np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0])
    b2 = cross(b3, b1c)
    b2 /= np.linalg.norm(b2)  # nonzero: the tilt limit keeps b3 away from the horizontal plane
    return np.column_stack([cross(b2, b3), b2, b3])


def attitude_error(R_WB: np.ndarray, R_WB_desired: np.ndarray) -> np.ndarray:
    """Attitude error ``e_R = 1/2 vee(R_d^T R - R^T R_d)`` in B (3,) (Lee et al. 2010, eq. 10)."""
    return 0.5 * vee(R_WB_desired.T @ R_WB - R_WB.T @ R_WB_desired)


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
    b1, b2, b3 = R_d[:, 0], R_d[:, 1], R_d[:, 2]
    j = setpoint.j_W
    h = (mass_kg / thrust_N) * (j - (b3 @ j) * b3)
    return np.array([-h @ b2, h @ b1, setpoint.yaw_rate_rad_s * b3[2]])


class SE3Controller:
    """Geometric SE(3) position and attitude controller (see the module docstring for the equations).

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
        self._integral_m_s = np.zeros(3)
        self._last_t_s: float | None = None
        # Constants of the gains, built once instead of at every update (the gains are frozen).
        ki = self._gains.ki_N_m_s
        limit = np.full(3, np.inf)
        np.divide(self._gains.integral_limit_N, ki, out=limit, where=ki > 0.0)
        self._integral_limit_m_s = limit
        self._neg_integral_limit_m_s = -limit
        self._tan_max_tilt = np.tan(self._gains.max_tilt_rad)
        self._min_thrust_N = self._gains.min_thrust_fraction * self._vehicle.hover_thrust_N

    @property
    def gains(self) -> SE3Gains:
        """The controller's gains."""
        return self._gains

    def reset(self) -> None:
        """Clear the integral state and the time of the last update."""
        self._integral_m_s = np.zeros(3)
        self._last_t_s = None

    def update(self, t_s: float, state: NavState, setpoint: FlatOutput) -> ControlCommand:
        """Motor command for ``state`` tracking ``setpoint`` at time ``t_s`` (s)."""
        thrusts, R_d = self._thrusts_and_attitude(t_s, state, setpoint)
        # Report the wrench the motors actually produce.
        produced_collective, produced_moments = self._mixer.wrench(thrusts)
        return ControlCommand(
            thrusts_N=thrusts,
            collective_N=produced_collective,
            moments_B_Nm=produced_moments,
            R_WB_desired=R_d,
        )

    def thrusts(self, t_s: float, state: NavState, setpoint: FlatOutput) -> np.ndarray:
        """Motor thrusts (N), shape (4,): ``update(...).thrusts_N`` without building the full command.

        For loops that use only the thrusts (the Gymnasium envs, every low-level tick); the integral state
        advances exactly as in :meth:`update`.
        """
        return self._thrusts_and_attitude(t_s, state, setpoint)[0]

    def _thrusts_and_attitude(
        self, t_s: float, state: NavState, setpoint: FlatOutput
    ) -> tuple[np.ndarray, np.ndarray]:
        """Steps 1-6 above: motor thrusts (N), shape (4,), and desired attitude ``R_WB_d``, shape (3, 3)."""
        g, m = self._gains, self._vehicle.mass_kg
        R = state.R_WB

        # 1. Desired force in W, with the integral (clamped: anti-windup) and the tilt limit.
        e_p = state.p_WB - setpoint.p_W
        e_v = state.v_WB - setpoint.v_W
        self._integrate(t_s, e_p)
        force_W = (
            -g.kp_N_m * e_p
            - g.kv_N_s_m * e_v
            - self._integral_force_N()
            + m * (setpoint.a_W - self._vehicle.gravity_W_m_s2)
        )
        force_W = self._limit_tilt(force_W)

        # 2. Collective thrust along the current body z axis.
        collective_N = float(force_W @ (R @ _E3))

        # 3. Desired attitude from the force direction and the yaw setpoint.
        R_d = desired_attitude(force_W, setpoint.yaw_rad)

        # 4. Desired body rate (flatness feed-forward) and the attitude / rate errors.
        omega_d = desired_body_rate(R_d, float(np.linalg.norm(force_W)), m, setpoint)
        omega_d_B = R.T @ R_d @ omega_d
        e_R = attitude_error(R, R_d)
        e_w = state.omega_B - omega_d_B

        # 5. Moments, with the gyroscopic term; the desired angular acceleration is taken as zero.
        J = self._vehicle.inertia_kg_m2
        w = state.omega_B
        moments_B = -g.kR_Nm_rad * e_R - g.kw_Nm_s_rad * e_w + cross(w, J @ w) - J @ (skew(w) @ omega_d_B)

        # 6. Mix and saturate.
        return self._mixer.motor_thrusts(collective_N, moments_B), R_d

    def _integrate(self, t_s: float, e_p: np.ndarray) -> None:
        """Accumulate the position error over the time since the last update (clamped, anti-windup)."""
        if self._last_t_s is not None:
            dt = t_s - self._last_t_s
            if 0.0 < dt <= _MAX_INTEGRATION_STEP_S:
                self._integral_m_s = self._integral_m_s + e_p * dt
        self._last_t_s = float(t_s)
        self._integral_m_s = np.clip(
            self._integral_m_s, self._neg_integral_limit_m_s, self._integral_limit_m_s
        )

    def _integral_force_N(self) -> np.ndarray:
        """Integral force ``k_i int(e_p)`` (N), shape (3,)."""
        return self._gains.ki_N_m_s * self._integral_m_s

    def _limit_tilt(self, force_W: np.ndarray) -> np.ndarray:
        """Keep the vertical force above ``min_thrust_fraction m g`` and the tilt below ``max_tilt_rad``."""
        out = force_W.copy()
        out[2] = max(out[2], self._min_thrust_N)
        horizontal = float(np.linalg.norm(out[:2]))
        max_horizontal = out[2] * self._tan_max_tilt
        if horizontal > max_horizontal:
            out[:2] *= max_horizontal / horizontal
        return out
