"""Display pose: the estimator's pose with its corrections smoothed, the pose a headset renders with.

A filter's pose at IMU rate is smooth between camera frames (IMU propagation) and jumps at every update (30
Hz): on a seated head the stereo MSCKF's pose steps by up to ~1 mm per update and its velocity error makes a
saw-tooth in between; the user sees that as the world trembling. Headsets therefore render with a *display
pose*: the IMU-propagated motion at high frequency and the estimator's pose at low frequency (a
complementary filter, as in [1] Sec. III and the attitude filters of [2]).

Per IMU sample ``k`` (``dt = t_k - t_{k-1}``), with the estimator's bias-corrected body rate ``omega_B`` and
gravity-removed acceleration ``a_W``, and its pose ``(R_f, p_f)``:

1. Propagate the display state with the same IMU the estimator uses::

       R_d <- R_d Exp(omega_B dt),   p_d <- p_d + v_d dt + a_W dt^2 / 2,   v_d <- v_d + a_W dt

2. Crossover frequency ``f_c`` from the motion: ``m = clip(max(|omega_B| / omega_full, |a_W| / a_full), 0,
   1)`` blends ``f_still`` (heavy smoothing, nothing moves so nothing can lag) into ``f_moving`` (the
   estimator is followed closely while the head turns, where gyro scale errors would otherwise accumulate).
   ``w_c = 2 pi f_c``.
3. Orientation, first order: ``R_d <- R_d Exp(min(1, w_c dt) Log(R_d^T R_f))``.
4. Position, second order, critically damped (``zeta = 1``; the classical alpha-beta pull with the IMU
   acceleration as feed-forward)::

       e = p_f - p_d,   p_d <- p_d + 2 w_c dt e,   v_d <- v_d + w_c^2 dt e

   From the estimator's position to the display's this is the low-pass ``(2 w_c s + w_c^2) / (s + w_c)^2``;
   what the IMU adds is the complementary high-pass, so a motion the IMU measures passes without lag and only
   the estimator's corrections are smoothed.
5. A jump larger than ``snap_m`` / ``snap_rad`` (a relocalization, a loop closure, a re-initialization) is
   taken at once: smoothing it would show the world sliding for seconds.

The estimator's own state is never changed; the display pose is an output only.

[1] R. Mahony, T. Hamel, J.-M. Pflimlin, "Nonlinear complementary filters on the special orthogonal group",
IEEE TAC 53(5), 2008. [2] S. LaValle, A. Yershova, M. Katsev, M. Antonov, "Head tracking for the Oculus
Rift", ICRA 2014.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.vio.lie import exp_so3, log_so3, normalize_rotmat


@dataclass(frozen=True)
class DisplayPoseParams:
    """Settings of the display pose filter.

    Attributes:
        f_still_hz: Crossover frequency when the head is still (Hz): lower is smoother.
        f_moving_hz: Crossover frequency while the head moves fast (Hz).
        omega_full_rad_s: Body rate at and above which ``f_moving_hz`` applies (rad/s).
        accel_full_m_s2: Gravity-removed acceleration at and above which ``f_moving_hz`` applies (m/s^2).
        snap_m: Position jumps of the estimator larger than this are taken at once (m).
        snap_rad: Orientation jumps larger than this are taken at once (rad).
        damping: Damping ratio ``zeta`` of the position pull (1: critically damped); lower rolls the
            estimator's corrections off sooner above the crossover (``2 zeta w_c / w``) at some overshoot.
    """

    f_still_hz: float = 0.1
    f_moving_hz: float = 3.0
    omega_full_rad_s: float = 1.0
    accel_full_m_s2: float = 2.0
    snap_m: float = 0.03
    snap_rad: float = 0.02
    damping: float = 0.7
    velocity_pull_hz: float = 0.0

    def __post_init__(self) -> None:
        """Validate the settings."""
        for name in (
            "f_still_hz",
            "f_moving_hz",
            "omega_full_rad_s",
            "accel_full_m_s2",
            "snap_m",
            "snap_rad",
            "damping",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f"DisplayPoseParams.{name} must be finite and > 0, got {value}")
        if self.f_moving_hz < self.f_still_hz:
            raise ValueError(
                f"DisplayPoseParams.f_moving_hz ({self.f_moving_hz}) must be >= "
                f"f_still_hz ({self.f_still_hz})"
            )


class DisplayPoseFilter:
    """The complementary filter of the module docstring; feed it every IMU-rate estimate in time order.

    Args:
        params: Settings.
    """

    def __init__(self, params: DisplayPoseParams | None = None) -> None:
        """Create a filter that starts at the first estimate it is given."""
        self.params = params if params is not None else DisplayPoseParams()
        self.t_s: float | None = None
        self.R_WB = np.eye(3)
        self.p_WB_m = np.zeros(3)
        self.v_WB_m_s = np.zeros(3)
        self.snaps = 0

    def crossover_hz(self, omega_B_rad_s: np.ndarray, a_W_m_s2: np.ndarray) -> float:
        """Crossover frequency (Hz) for the current motion (step 2)."""
        p = self.params
        m = max(
            float(np.linalg.norm(omega_B_rad_s)) / p.omega_full_rad_s,
            float(np.linalg.norm(a_W_m_s2)) / p.accel_full_m_s2,
        )
        m = min(max(m, 0.0), 1.0)
        return p.f_still_hz + m * (p.f_moving_hz - p.f_still_hz)

    def _reset(self, t_s: float, R_WB: np.ndarray, p_WB_m: np.ndarray, v_WB_m_s: np.ndarray) -> None:
        self.t_s = t_s
        self.R_WB = np.array(R_WB, dtype=float)
        self.p_WB_m = np.array(p_WB_m, dtype=float)
        self.v_WB_m_s = np.array(v_WB_m_s, dtype=float)

    def update(
        self,
        t_s: float,
        R_WB: np.ndarray,
        p_WB_m: np.ndarray,
        v_WB_m_s: np.ndarray,
        omega_B_rad_s: np.ndarray,
        a_W_m_s2: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance to ``t_s`` with the estimator's pose and motion there; return the display pose.

        Args:
            t_s: Time of the estimate (s), after the previous one.
            R_WB: Estimator orientation, shape (3, 3).
            p_WB_m: Estimator position in W (m), shape (3,).
            v_WB_m_s: Estimator velocity in W (m/s), shape (3,): used only to start.
            omega_B_rad_s: Bias-corrected body rate (rad/s), shape (3,).
            a_W_m_s2: Bias-corrected, gravity-removed acceleration in W (m/s^2), shape (3,).

        Returns:
            ``(R_WB, p_WB_m, v_WB_m_s)`` of the display state, shapes (3, 3), (3,), (3,) (copies).

        Raises:
            ValueError: ``t_s`` not after the previous time.
        """
        if self.t_s is None:
            self._reset(t_s, R_WB, p_WB_m, v_WB_m_s)
            return self.R_WB.copy(), self.p_WB_m.copy(), self.v_WB_m_s.copy()
        dt = float(t_s) - self.t_s
        if not dt > 0.0:
            raise ValueError(f"DisplayPoseFilter: time {t_s} s is not after the previous {self.t_s} s")
        omega = np.asarray(omega_B_rad_s, dtype=float)
        a_W = np.asarray(a_W_m_s2, dtype=float)
        # 1. IMU propagation of the display state.
        self.R_WB = normalize_rotmat(self.R_WB @ exp_so3(omega * dt))
        self.p_WB_m = self.p_WB_m + self.v_WB_m_s * dt + 0.5 * a_W * dt * dt
        self.v_WB_m_s = self.v_WB_m_s + a_W * dt
        self.t_s = float(t_s)
        # 5. Large jumps are taken at once.
        e_p = np.asarray(p_WB_m, dtype=float) - self.p_WB_m
        e_R = log_so3(self.R_WB.T @ np.asarray(R_WB, dtype=float))
        p = self.params
        if np.linalg.norm(e_p) > p.snap_m or np.linalg.norm(e_R) > p.snap_rad:
            self.snaps += 1
            self._reset(t_s, R_WB, p_WB_m, v_WB_m_s)
            return self.R_WB.copy(), self.p_WB_m.copy(), self.v_WB_m_s.copy()
        # 2. Crossover from the motion.
        w_c = 2.0 * np.pi * self.crossover_hz(omega, a_W)
        # 3. Orientation pull (first order).
        self.R_WB = normalize_rotmat(self.R_WB @ exp_so3(min(1.0, w_c * dt) * e_R))
        # 4. Position pull (second order, critically damped).
        self.p_WB_m = self.p_WB_m + min(1.0, 2.0 * p.damping * w_c * dt) * e_p
        self.v_WB_m_s = self.v_WB_m_s + (w_c * w_c * dt) * e_p
        if p.velocity_pull_hz > 0.0:
            e_v = np.asarray(v_WB_m_s, dtype=float) - self.v_WB_m_s
            self.v_WB_m_s = self.v_WB_m_s + min(1.0, 2.0 * np.pi * p.velocity_pull_hz * dt) * e_v
        return self.R_WB.copy(), self.p_WB_m.copy(), self.v_WB_m_s.copy()
