"""Smooth scripted trajectories with analytic derivatives: the curve machinery of the motion library.

Every trajectory is a path ``p(theta)`` and an attitude law, both sums of sinusoids (plus a linear term) in a
phase ``theta``, composed with a smooth time warp ``theta(t)``. The warp's rate ``theta'`` ramps 0 -> rate
-> 0 with a 7th-order smoothstep (zero 1st-3rd derivatives at both ends), so each trajectory starts and ends
at rest with continuous snap, body rate and angular acceleration. Time derivatives of ``f(theta(t))`` come
from Faa di Bruno's formula up to order 4.

Attitude laws:

* ``flat`` (quadrotor): differential flatness (Mellinger & Kumar, "Minimum snap trajectory generation and
  control for quadrotors", ICRA 2011, sec. III): ``z_B = (a_W - g_W) / |a_W - g_W|``,
  ``y_B = z_B x x_C / |.|`` with ``x_C = (cos psi, sin psi, 0)``, ``x_B = y_B x z_B``. Instead of the paper's
  closed forms for the body rates, the first two derivatives of ``R_WB`` follow exactly from the chain rule
  on these normalisations and cross products (jerk and snap enter through ``a_W'`` and ``a_W''``).
* ``euler`` (headset): ``R_WB = Rz(yaw) Ry(pitch) Rx(roll)`` with analytic Euler-angle rates.

From ``R, R', R''``: ``Omega = R^T R'`` gives ``omega_B = vee(Omega)`` and
``alpha_B = vee(R^T R'' - Omega^2)`` (since ``R'' = R (Omega^2 + Omega')``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import numpy as np
from viotb.vio.lie import cross, skew, vee
from viotb.vio.types import gravity_W


@dataclass(frozen=True)
class TruthSample:
    """True kinematic state of B at one instant.

    Attributes:
        t_s: Time (s).
        p_WB: Position (m) in W, shape (3,).
        v_WB: Velocity (m/s) in W, shape (3,).
        a_WB: Acceleration (m/s^2) in W, shape (3,).
        R_WB: Orientation, shape (3, 3).
        omega_B: Angular velocity of B w.r.t. W, in B (rad/s), shape (3,).
        alpha_B: Angular acceleration in B (rad/s^2), shape (3,).
    """

    t_s: float
    p_WB: np.ndarray
    v_WB: np.ndarray
    a_WB: np.ndarray
    R_WB: np.ndarray
    omega_B: np.ndarray
    alpha_B: np.ndarray

    @property
    def specific_force_B(self) -> np.ndarray:
        """What an ideal accelerometer at B reads: ``R_WB^T (a_W - g_W)`` (m/s^2), shape (3,)."""
        return self.R_WB.T @ (self.a_WB - gravity_W())


@dataclass(frozen=True)
class TruthSeries:
    """Array form of N :class:`TruthSample` (same fields with a leading N axis)."""

    t_s: np.ndarray
    p_WB: np.ndarray
    v_WB: np.ndarray
    a_WB: np.ndarray
    R_WB: np.ndarray
    omega_B: np.ndarray
    alpha_B: np.ndarray

    def __len__(self) -> int:
        """Number of samples."""
        return int(self.t_s.shape[0])

    @property
    def specific_force_B(self) -> np.ndarray:
        """Ideal accelerometer readings ``R_WB^T (a_W - g_W)`` (m/s^2), shape (N, 3)."""
        return np.einsum("nji,nj->ni", self.R_WB, self.a_WB - gravity_W())


@runtime_checkable
class Trajectory(Protocol):
    """A scripted motion of B in W over ``[0, duration_s]``."""

    @property
    def duration_s(self) -> float:
        """Length of the trajectory (s)."""

    def sample(self, t_s: float) -> TruthSample:
        """State at ``t_s`` (clamped to ``[0, duration_s]``)."""

    def sample_many(self, t_s: np.ndarray) -> TruthSeries:
        """States at times ``t_s`` (s), shape (N,)."""


# ----------------------------------------------------------------------------------------------------------
# Building blocks: sinusoid signals in theta, the smooth warp, Faa di Bruno composition.


@dataclass(frozen=True)
class Sinusoids:
    """``f(theta) = offset + linear * theta + sum_i amp_i * sin(freq_i * theta + phase_i)``, per dimension.

    Attributes:
        offset: shape (D,).
        linear: Slope per unit theta, shape (D,).
        terms: Tuple of ``(amp (D,), freq (scalar, per unit theta), phase (D,))``.
    """

    offset: tuple[float, ...]
    linear: tuple[float, ...] | None = None
    terms: tuple[tuple[tuple[float, ...], float, tuple[float, ...]], ...] = ()

    def derivatives(self, theta: float, order: int) -> np.ndarray:
        """``d^k f / d theta^k`` for k = 0..order, shape (order + 1, D)."""
        dim = len(self.offset)
        out = np.zeros((order + 1, dim))
        out[0] = self.offset
        if self.linear is not None:
            out[0] += np.asarray(self.linear) * theta
            if order >= 1:
                out[1] += self.linear
        for amp, freq, phase in self.terms:
            arg = freq * theta + np.asarray(phase, dtype=float)
            for k in range(order + 1):
                # d^k/dtheta^k sin(w theta + phi) = w^k sin(w theta + phi + k pi / 2).
                out[k] += np.asarray(amp) * freq**k * np.sin(arg + k * math.pi / 2.0)
        return out


def _smoothstep7(x: float) -> np.ndarray:
    """``S(x) = 35x^4 - 84x^5 + 70x^6 - 20x^7`` and its integral and first 3 derivatives on [0, 1].

    Returns:
        ``[int_0^x S, S, S', S'', S''']``, shape (5,).
    """
    x = min(max(x, 0.0), 1.0)
    integral = 7 * x**5 - 14 * x**6 + 10 * x**7 - 2.5 * x**8
    s0 = 35 * x**4 - 84 * x**5 + 70 * x**6 - 20 * x**7
    s1 = 140 * x**3 - 420 * x**4 + 420 * x**5 - 140 * x**6
    s2 = 420 * x**2 - 1680 * x**3 + 2100 * x**4 - 840 * x**5
    s3 = 840 * x - 5040 * x**2 + 8400 * x**3 - 4200 * x**4
    return np.array([integral, s0, s1, s2, s3])


@dataclass(frozen=True)
class SmoothWarp:
    """Phase ``theta(t)`` whose rate ramps ``0 -> rate -> 0`` (smoothstep ramps of ``ramp_s`` each).

    ``theta(duration) = rate * (duration - ramp_s)``.

    Attributes:
        duration_s: Total time (s).
        rate: Plateau rate of theta (units of theta per second).
        ramp_s: Length of each ramp (s); ``2 * ramp_s <= duration_s``.
    """

    duration_s: float
    rate: float
    ramp_s: float

    def __post_init__(self) -> None:
        """Validate the timing."""
        if not (self.duration_s > 0.0 and 0.0 < self.ramp_s <= 0.5 * self.duration_s):
            raise ValueError(
                f"SmoothWarp needs duration_s > 0 and 0 < ramp_s <= duration_s / 2, got "
                f"duration_s={self.duration_s}, ramp_s={self.ramp_s}"
            )

    def derivatives(self, t_s: float) -> np.ndarray:
        """``[theta, theta', theta'', theta''', theta'''']`` at ``t_s`` (clamped), shape (5,)."""
        T, r, c = self.duration_s, self.ramp_s, self.rate
        t = min(max(t_s, 0.0), T)
        if t < r:
            s = _smoothstep7(t / r)
            return c * np.array([r * s[0], s[1], s[2] / r, s[3] / r**2, s[4] / r**3])
        if t <= T - r:
            return c * np.array([0.5 * r + (t - r), 1.0, 0.0, 0.0, 0.0])
        # Mirror of the ramp-up: theta(t) = theta(T) - theta_up(T - t).
        s = _smoothstep7((T - t) / r)
        total = T - r
        return c * np.array([total - r * s[0], s[1], -s[2] / r, s[3] / r**2, -s[4] / r**3])


def _compose(f: np.ndarray, w: np.ndarray, order: int) -> np.ndarray:
    """Time derivatives of ``f(theta(t))`` by Faa di Bruno's formula.

    Args:
        f: ``d^k f / d theta^k``, k = 0..order, shape (order + 1, D).
        w: ``d^k theta / dt^k``, k = 0..4, shape (5,).
        order: Highest derivative wanted (<= 4).

    Returns:
        ``d^k f / dt^k``, k = 0..order, shape (order + 1, D).
    """
    _, t1, t2, t3, t4 = w
    out = np.zeros_like(f)
    out[0] = f[0]
    if order >= 1:
        out[1] = f[1] * t1
    if order >= 2:
        out[2] = f[2] * t1**2 + f[1] * t2
    if order >= 3:
        out[3] = f[3] * t1**3 + 3.0 * f[2] * t1 * t2 + f[1] * t3
    if order >= 4:
        out[4] = f[4] * t1**4 + 6.0 * f[3] * t1**2 * t2 + f[2] * (3.0 * t2**2 + 4.0 * t1 * t3) + f[1] * t4
    return out


def _normalize_d2(w: np.ndarray) -> np.ndarray:
    """Unit vector ``u = w / |w|`` and its first two time derivatives.

    Args:
        w: ``[w, w', w'']``, shape (3, 3).

    Returns:
        ``[u, u', u'']``, shape (3, 3).
    """
    n = float(np.linalg.norm(w[0]))
    if n < 1e-9:
        raise ValueError("trajectory: cannot normalise a zero vector (free fall or body axis along yaw axis)")
    u = w[0] / n
    P = np.eye(3) - np.outer(u, u)
    n1 = float(u @ w[1])
    u1 = P @ w[1] / n
    P1 = -(np.outer(u1, u) + np.outer(u, u1))
    u2 = (P1 @ w[1] + P @ w[2]) / n - P @ w[1] * n1 / n**2
    return np.stack([u, u1, u2])


def _cross_d2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` and its first two time derivatives from ``[a, a', a'']`` and ``[b, b', b'']``."""
    c = cross(a[[0, 1, 0, 2, 1, 0]], b[[0, 0, 1, 0, 1, 2]])
    return np.stack([c[0], c[1] + c[2], c[3] + 2.0 * c[4] + c[5]])


def _flat_attitude(acc_W: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """``[R, R', R'']`` of the differential-flatness attitude, shape (3, 3, 3).

    Args:
        acc_W: ``[a, a', a'']`` (acceleration, jerk, snap) in W, shape (3, 3).
        yaw: ``[psi, psi', psi'']``, shape (3,).
    """
    z = _normalize_d2(acc_W - np.stack([gravity_W(), np.zeros(3), np.zeros(3)]))
    psi, psi1, psi2 = yaw
    c, s = math.cos(psi), math.sin(psi)
    x_c = np.array(
        [[c, s, 0.0], [-s * psi1, c * psi1, 0.0], [-s * psi2 - c * psi1**2, c * psi2 - s * psi1**2, 0.0]]
    )
    y = _normalize_d2(_cross_d2(z, x_c))
    x = _cross_d2(y, z)
    return np.stack([np.stack([x[k], y[k], z[k]], axis=1) for k in range(3)])


def _euler_attitude(angles: np.ndarray) -> np.ndarray:
    """``[R, R', R'']`` of ``Rz(yaw) Ry(pitch) Rx(roll)``, shape (3, 3, 3).

    Args:
        angles: ``[[yaw, pitch, roll], first derivatives, second derivatives]`` (rad), shape (3, 3).
    """
    axes = (np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    factors = []
    for i, axis in enumerate(axes):
        q, q1, q2 = angles[:, i]
        K = skew(axis)
        F = np.eye(3) + math.sin(q) * K + (1.0 - math.cos(q)) * K @ K
        # d/dt exp(q K) = exp(q K) K q';  d2/dt2 = exp(q K) (K^2 q'^2 + K q'').
        factors.append((F, F @ K * q1, F @ (K @ K * q1**2 + K * q2)))
    (A, A1, A2), (B, B1, B2), (C, C1, C2) = factors
    R = A @ B @ C
    R1 = A1 @ B @ C + A @ B1 @ C + A @ B @ C1
    R2 = A2 @ B @ C + A @ B2 @ C + A @ B @ C2 + 2.0 * (A1 @ B1 @ C + A1 @ B @ C1 + A @ B1 @ C1)
    return np.stack([R, R1, R2])


def _body_rates(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``omega_B, alpha_B`` from ``[R, R', R'']``: ``Omega = R^T R'``, ``Omega' = R^T R'' - Omega^2``."""
    Omega = R[0].T @ R[1]
    return vee(Omega), vee(R[0].T @ R[2] - Omega @ Omega)


# ----------------------------------------------------------------------------------------------------------
# The trajectory class.


@dataclass(frozen=True)
class ScriptedTrajectory:
    """Position and attitude laws in a warped phase (see module docstring).

    Attributes:
        position: ``p_WB(theta)`` (m), a 3-D :class:`Sinusoids`.
        attitude: 1-D yaw law (rad) for ``"flat"``, or 3-D ``(yaw, pitch, roll)`` law (rad) for ``"euler"``.
        attitude_mode: ``"flat"`` (quadrotor, differential flatness) or ``"euler"`` (headset).
        warp: The phase ``theta(t)``.
    """

    position: Sinusoids
    attitude: Sinusoids
    attitude_mode: str
    warp: SmoothWarp

    def __post_init__(self) -> None:
        """Check that the laws have the right dimensions."""
        expected = {"flat": 1, "euler": 3}
        if self.attitude_mode not in expected:
            raise ValueError(f"attitude_mode must be 'flat' or 'euler', got {self.attitude_mode!r}")
        if len(self.position.offset) != 3 or len(self.attitude.offset) != expected[self.attitude_mode]:
            raise ValueError(
                "ScriptedTrajectory: position must be 3-D and attitude 1-D (flat) or 3-D (euler)"
            )

    @property
    def duration_s(self) -> float:
        """Length (s)."""
        return self.warp.duration_s

    def sample(self, t_s: float) -> TruthSample:
        """State at ``t_s`` (s), clamped to ``[0, duration_s]``."""
        w = self.warp.derivatives(float(t_s))
        pos = _compose(self.position.derivatives(w[0], 4), w, 4)
        att = _compose(self.attitude.derivatives(w[0], 2), w, 2)
        if self.attitude_mode == "flat":
            R = _flat_attitude(pos[2:5], att[:, 0])
        else:
            R = _euler_attitude(att)
        omega_B, alpha_B = _body_rates(R)
        return TruthSample(float(t_s), pos[0], pos[1], pos[2], R[0], omega_B, alpha_B)

    def sample_many(self, t_s: np.ndarray) -> TruthSeries:
        """States at times ``t_s`` (s), shape (N,)."""
        samples = [self.sample(t) for t in np.asarray(t_s, dtype=float)]
        return TruthSeries(
            np.asarray(t_s, dtype=float).copy(),
            *(
                np.array([getattr(s, name) for s in samples])
                for name in TruthSample.__dataclass_fields__
                if name != "t_s"
            ),
        )


@dataclass(frozen=True)
class StillStart:
    """Hold ``inner``'s first pose for ``still_s`` seconds, then run ``inner`` shifted by ``still_s``.

    Real sequences (EuRoC's among them) begin at rest, which is what a static initializer needs. Every
    scripted motion starts at rest with vanishing derivatives (7th-order time warp), so the joint is exact.

    Attributes:
        inner: The motion.
        still_s: Rest before it (s), >= 0.
    """

    inner: ScriptedTrajectory
    still_s: float

    @property
    def duration_s(self) -> float:
        """Rest plus motion (s)."""
        return self.still_s + self.inner.duration_s

    def sample(self, t_s: float) -> TruthSample:
        """State at ``t_s`` (s)."""
        inner = self.inner.sample(max(float(t_s) - self.still_s, 0.0))
        return replace(inner, t_s=float(t_s))

    def sample_many(self, t_s: np.ndarray) -> TruthSeries:
        """States at times ``t_s`` (s), shape (N,)."""
        t = np.asarray(t_s, dtype=float)
        series = self.inner.sample_many(np.maximum(t - self.still_s, 0.0))
        return replace(series, t_s=t.copy())


@dataclass(frozen=True)
class TimeShifted:
    """``inner`` from its time ``start_s`` on, relabelled to start at 0: a recording begun mid-motion.

    ``sample(t) = inner.sample(t + start_s)`` with ``t_s = t``; the duration shrinks by ``start_s``.

    Attributes:
        inner: Any trajectory (``StillStart`` included).
        start_s: Time of ``inner`` (s) that becomes time 0, ``0 <= start_s < inner.duration_s``.
    """

    inner: Trajectory
    start_s: float

    def __post_init__(self) -> None:
        """Check that the start lies inside ``inner``."""
        if not (np.isfinite(self.start_s) and 0.0 <= self.start_s < self.inner.duration_s):
            raise ValueError(
                f"TimeShifted.start_s must lie in [0, {self.inner.duration_s:.3f}) s, got {self.start_s}"
            )

    @property
    def duration_s(self) -> float:
        """What is left of ``inner`` after ``start_s`` (s)."""
        return self.inner.duration_s - self.start_s

    def sample(self, t_s: float) -> TruthSample:
        """State at ``t_s`` (s)."""
        return replace(self.inner.sample(float(t_s) + self.start_s), t_s=float(t_s))

    def sample_many(self, t_s: np.ndarray) -> TruthSeries:
        """States at times ``t_s`` (s), shape (N,)."""
        t = np.asarray(t_s, dtype=float)
        return replace(self.inner.sample_many(t + self.start_s), t_s=t.copy())


# ----------------------------------------------------------------------------------------------------------
# The library of motions. Room: ~10 x 10 x 4 m centred at the origin; stay in |x|,|y| < 3.5, 0.5 < z < 3.
