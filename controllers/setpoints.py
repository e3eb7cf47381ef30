"""Setpoint generators: smooth flat-output trajectories sampled by time.

Every generator has ``sample(t_s) -> FlatOutput`` (time relative to its own start, seconds) and ``duration_s``
(``inf`` when it never ends). Derivatives (velocity, acceleration, jerk, yaw rate) are analytic.

- :class:`HoverPoint`: hold a position and heading.
- :class:`Waypoints`: rest-to-rest minimum-jerk segments (Flash and Hogan, J. Neurosci. 1985: the quintic
  ``10 s^3 - 15 s^4 + 6 s^5``) between points, timed by an average speed or by given segment times.
- :class:`Takeoff`: a minimum-jerk climb from the ground to an altitude.
- :class:`StraightLine`: a constant-speed line between smooth ramps (no acceleration while cruising).
- :class:`FigureEight`: a lemniscate of Gerono, ``x = a sin(theta)``, ``y = b sin(2 theta)``, whose phase rate
  ramps up (and, for a finite number of laps, down) smoothly so it starts and ends at rest.
- :class:`ExcitationManeuver`: small sinusoids in x, y, z and yaw under a ``sin^2`` window, to make the
  estimator's states observable (the lesson's excitation requirement), starting and ending at rest.
- :class:`Sequence`: chain the above, each one after the previous ends.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from viotb.controllers.profiles import min_jerk_segment, phase_ramp, phase_ramp_up_down
from viotb.controllers.types import FlatOutput

_CONTINUITY_TOL_M = 1e-3
"""Sequence items must join within this distance (m)."""


@runtime_checkable
class Setpoint(Protocol):
    """A time-parametrised flat-output trajectory."""

    @property
    def duration_s(self) -> float:
        """Length (s); ``inf`` for setpoints that never end."""
        ...

    def sample(self, t_s: float) -> FlatOutput:
        """Flat output at ``t_s`` seconds after the start (clamped to ``[0, duration_s]``)."""
        ...


def _vector(owner: str, name: str, value: object, size: int = 3) -> np.ndarray:
    """Read-only float vector of the given size, or a ValueError naming the field."""
    arr = np.array(value, dtype=float)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{owner}.{name}: expected {size} finite values, got {np.asarray(value)!r}")
    arr.setflags(write=False)
    return arr


def _positive(owner: str, name: str, value: float) -> float:
    """``value`` as a float if positive and finite, else a ValueError naming the field."""
    if not (np.isfinite(value) and value > 0.0):
        raise ValueError(f"{owner}.{name} must be positive and finite, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class HoverPoint:
    """Hold position ``p_W`` (m, shape (3,)) and heading ``yaw_rad`` (rad) forever."""

    p_W: np.ndarray
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        """Validate the position."""
        object.__setattr__(self, "p_W", _vector("HoverPoint", "p_W", self.p_W))
        # The same immutable record at every time: built once, not at every control tick.
        object.__setattr__(self, "_setpoint", FlatOutput(p_W=self.p_W, yaw_rad=self.yaw_rad))

    @property
    def duration_s(self) -> float:
        """Never ends: ``inf``."""
        return math.inf

    def sample(self, t_s: float) -> FlatOutput:
        """The hover point, at rest."""
        return self._setpoint


class Waypoints:
    """Rest-to-rest minimum-jerk segments through waypoints; holds the last point after the end.

    Args:
        points_W_m: Waypoints (m), shape (N, 3), N >= 2.
        yaws_rad: Heading at each waypoint (rad), shape (N,); default 0. Blended with the same profile
            (no wrapping: give unwrapped angles).
        speed_m_s: Average speed (m/s) that sets each segment's time as ``length / speed`` (peak speed is
            1.875 times that); used when ``segment_times_s`` is not given.
        segment_times_s: Duration of each segment (s), shape (N - 1,).
        min_segment_s: Floor on a segment's duration when timed by speed (s), e.g. for a pure yaw turn.

    Raises:
        ValueError: Bad shapes, non-positive speed or durations, or neither timing given.
    """

    def __init__(
        self,
        points_W_m: np.ndarray,
        yaws_rad: np.ndarray | None = None,
        speed_m_s: float | None = None,
        segment_times_s: np.ndarray | None = None,
        min_segment_s: float = 1.0,
    ) -> None:
        """Validate and store the waypoints and the segment start times."""
        points = np.array(points_W_m, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 2 or not np.all(np.isfinite(points)):
            raise ValueError(f"Waypoints.points_W_m: expected shape (N >= 2, 3) finite, got {points.shape}")
        n_seg = points.shape[0] - 1
        yaws = np.zeros(n_seg + 1) if yaws_rad is None else np.array(yaws_rad, dtype=float)
        if yaws.shape != (n_seg + 1,) or not np.all(np.isfinite(yaws)):
            raise ValueError(f"Waypoints.yaws_rad: expected shape ({n_seg + 1},), got {yaws.shape}")
        if segment_times_s is not None:
            times = np.array(segment_times_s, dtype=float)
            if times.shape != (n_seg,) or not np.all(np.isfinite(times)) or np.any(times <= 0.0):
                raise ValueError(
                    f"Waypoints.segment_times_s: expected {n_seg} positive values, "
                    f"got {np.asarray(segment_times_s)!r}"
                )
        elif speed_m_s is not None:
            speed = _positive("Waypoints", "speed_m_s", speed_m_s)
            lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
            times = np.maximum(lengths / speed, _positive("Waypoints", "min_segment_s", min_segment_s))
        else:
            raise ValueError("Waypoints: give speed_m_s or segment_times_s")
        self._points = points
        self._yaws = yaws
        self._times = times
        self._starts = np.concatenate([[0.0], np.cumsum(times)])
        # The same values as plain floats for the per-tick sample (a bisection on a list, no numpy calls).
        self._points_f = points.tolist()
        self._yaws_f = yaws.tolist()
        self._times_f = times.tolist()
        self._starts_f = self._starts.tolist()

    @property
    def duration_s(self) -> float:
        """Total time of all segments (s)."""
        return self._starts_f[-1]

    @property
    def segment_times_s(self) -> np.ndarray:
        """Duration of each segment (s), shape (N - 1,)."""
        return self._times.copy()

    def sample(self, t_s: float) -> FlatOutput:
        """Flat output at ``t_s`` (s); before 0 the first point, after the end the last point, at rest."""
        starts = self._starts_f
        t = min(max(float(t_s), 0.0), starts[-1])
        # np.searchsorted(starts, t, side="right") - 1, clipped to a segment.
        k = min(max(bisect.bisect_right(starts, t) - 1, 0), len(self._times_f) - 1)
        return min_jerk_segment(
            self._points_f[k],
            self._points_f[k + 1],
            self._yaws_f[k],
            self._yaws_f[k + 1],
            self._times_f[k],
            t - starts[k],
        )


class Takeoff(Waypoints):
    """Climb straight up from ``start_W_m`` (m, shape (3,)) to ``altitude_m`` (m) in ``duration_s`` (s).

    A single minimum-jerk segment at constant heading ``yaw_rad``; it starts and ends at rest.
    """

    def __init__(
        self, start_W_m: np.ndarray, altitude_m: float, duration_s: float = 3.0, yaw_rad: float = 0.0
    ):
        """Build the climb segment."""
        start = _vector("Takeoff", "start_W_m", start_W_m)
        if not np.isfinite(altitude_m):
            raise ValueError(f"Takeoff.altitude_m must be finite, got {altitude_m!r}")
        end = np.array([start[0], start[1], float(altitude_m)])
        super().__init__(
            np.vstack([start, end]),
            yaws_rad=np.array([yaw_rad, yaw_rad]),
            segment_times_s=np.array([_positive("Takeoff", "duration_s", duration_s)]),
        )


@dataclass(frozen=True)
class StraightLine:
    """A straight line flown at a constant speed between a smooth start and a smooth stop.

    No acceleration while cruising: the lesson's "constant velocity", under which scale is unobservable.

    ``p(t) = start + u * speed * w(t)`` with the warped time ``w`` of
    :func:`~viotb.controllers.profiles.phase_ramp_up_down`: its rate ramps from 0 to 1 over ``ramp_s``, stays
    1, and ramps back to 0, ending at rest ``length_m`` along ``u``.

    Attributes:
        start_W_m: Start (m), shape (3,).
        direction_W: Direction (any length), shape (3,).
        length_m: Distance to fly (m).
        speed_m_s: Cruise speed (m/s).
        ramp_s: Duration of each speed ramp (s).
        yaw_rad: Constant heading (rad).
    """

    start_W_m: np.ndarray
    direction_W: np.ndarray
    length_m: float
    speed_m_s: float = 0.8
    ramp_s: float = 2.0
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        """Validate and normalise the direction."""
        object.__setattr__(self, "start_W_m", _vector("StraightLine", "start_W_m", self.start_W_m))
        d = _vector("StraightLine", "direction_W", self.direction_W)
        if float(np.linalg.norm(d)) < 1e-9:
            raise ValueError(f"StraightLine.direction_W must be non-zero, got {d.tolist()}")
        object.__setattr__(self, "direction_W", d / np.linalg.norm(d))
        _positive("StraightLine", "length_m", self.length_m)
        _positive("StraightLine", "speed_m_s", self.speed_m_s)
        _positive("StraightLine", "ramp_s", self.ramp_s)

    @property
    def duration_s(self) -> float:
        """``length / speed + ramp_s`` (s)."""
        return self.length_m / self.speed_m_s + self.ramp_s

    def sample(self, t_s: float) -> FlatOutput:
        """Flat output at ``t_s`` (s)."""
        t = min(max(float(t_s), 0.0), self.duration_s)
        w, dw, d2w, d3w = phase_ramp_up_down(t, self.duration_s, self.ramp_s)
        u = self.direction_W * self.speed_m_s
        return FlatOutput(
            p_W=self.start_W_m + u * w, v_W=u * dw, a_W=u * d2w, j_W=u * d3w, yaw_rad=self.yaw_rad
        )


@dataclass(frozen=True)
class FigureEight:
    """Lemniscate of Gerono in a horizontal plane, flown from and back to its centre.

    ``p(t) = (cx + a sin(theta), cy + b sin(2 theta), altitude)`` with ``theta = 2 pi w(t) / period``, where
    the warped time ``w`` ramps its rate smoothly from 0 to 1 over ``ramp_s`` (and back down at the end when
    ``laps`` is finite), so the vehicle starts (and stops) at the centre at rest. Heading is constant.

    Attributes:
        center_xy_m: Centre (m), shape (2,).
        size_m: Half-widths ``(a, b)`` (m) along x and y, shape (2,).
        period_s: Time of one lap at full rate (s).
        altitude_m: Height (m).
        ramp_s: Duration of the rate ramp (s).
        laps: Number of laps, or ``None`` to fly forever; the total phase is exactly ``laps`` turns.
        yaw_rad: Constant heading (rad).
    """

    center_xy_m: np.ndarray
    size_m: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.5]))
    period_s: float = 8.0
    altitude_m: float = 1.0
    ramp_s: float = 2.0
    laps: int | None = None
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        """Validate; a finite number of laps must be long enough for both ramps."""
        object.__setattr__(self, "center_xy_m", _vector("FigureEight", "center_xy_m", self.center_xy_m, 2))
        object.__setattr__(self, "size_m", _vector("FigureEight", "size_m", self.size_m, 2))
        _positive("FigureEight", "period_s", self.period_s)
        _positive("FigureEight", "ramp_s", self.ramp_s)
        if self.laps is not None and (int(self.laps) != self.laps or self.laps * self.period_s < self.ramp_s):
            raise ValueError(
                f"FigureEight.laps must be a whole number with laps * period_s >= ramp_s, got {self.laps!r}"
            )

    @property
    def duration_s(self) -> float:
        """``laps * period_s + ramp_s`` (s), or ``inf``."""
        return math.inf if self.laps is None else self.laps * self.period_s + self.ramp_s

    def _warp(self, t_s: float) -> tuple[float, float, float, float]:
        """Warped time and its three derivatives, with the ramp-down mirrored at the end."""
        if self.laps is None:
            return phase_ramp(t_s, self.ramp_s)
        return phase_ramp_up_down(t_s, self.duration_s, self.ramp_s)

    def sample(self, t_s: float) -> FlatOutput:
        """Flat output at ``t_s`` (s), by the chain rule through the warped phase."""
        t = min(max(float(t_s), 0.0), self.duration_s)
        w, dw, d2w, d3w = self._warp(t)
        omega = 2.0 * math.pi / self.period_s
        th, th1, th2, th3 = omega * w, omega * dw, omega * d2w, omega * d3w
        # f(theta) = (a sin theta, b sin 2 theta) and its theta-derivatives f', f'', f'''.
        a, b = self.size_m
        f = np.array([a * math.sin(th), b * math.sin(2 * th)])
        f1 = np.array([a * math.cos(th), 2 * b * math.cos(2 * th)])
        f2 = np.array([-a * math.sin(th), -4 * b * math.sin(2 * th)])
        f3 = np.array([-a * math.cos(th), -8 * b * math.cos(2 * th)])
        # d/dt: v = f' th1; a = f'' th1^2 + f' th2; j = f''' th1^3 + 3 f'' th1 th2 + f' th3.
        vel = f1 * th1
        acc = f2 * th1**2 + f1 * th2
        jerk = f3 * th1**3 + 3.0 * f2 * th1 * th2 + f1 * th3
        return FlatOutput(
            p_W=np.array([self.center_xy_m[0] + f[0], self.center_xy_m[1] + f[1], self.altitude_m]),
            v_W=np.append(vel, 0.0),
            a_W=np.append(acc, 0.0),
            j_W=np.append(jerk, 0.0),
            yaw_rad=self.yaw_rad,
        )


@dataclass(frozen=True)
class ExcitationManeuver:
    """Small smooth oscillations in x, y, z and yaw around a point, starting and ending at rest.

    Each channel is ``A_k h(t) sin(2 pi f_k t)`` with the window ``h(t) = sin^2(pi t / duration_s)``, whose
    value and slope vanish at both ends. The defaults give peak accelerations of about 1.2-1.4 m/s^2 per axis
    (``A (2 pi f)^2``) and yaw rates near 1 rad/s: enough to excite the accelerometer and gyro axes for bias
    and scale observability.

    Attributes:
        center_W_m: Point to oscillate about (m), shape (3,).
        amplitude_m: Peak displacement per axis (m), shape (3,).
        frequency_hz: Oscillation frequency per axis (Hz), shape (3,); distinct values decorrelate the axes.
        yaw_center_rad: Mean heading (rad).
        yaw_amplitude_rad: Peak heading swing (rad).
        yaw_frequency_hz: Heading oscillation frequency (Hz).
        duration_s: Length of the manoeuvre (s).
    """

    center_W_m: np.ndarray
    amplitude_m: np.ndarray = field(default_factory=lambda: np.array([0.12, 0.07, 0.04]))
    frequency_hz: np.ndarray = field(default_factory=lambda: np.array([0.5, 0.7, 0.9]))
    yaw_center_rad: float = 0.0
    yaw_amplitude_rad: float = 0.4
    yaw_frequency_hz: float = 0.4
    duration_s: float = 6.0

    def __post_init__(self) -> None:
        """Validate fields."""
        for name in ("center_W_m", "amplitude_m", "frequency_hz"):
            object.__setattr__(self, name, _vector("ExcitationManeuver", name, getattr(self, name)))
        if np.any(self.frequency_hz <= 0.0):
            raise ValueError(
                f"ExcitationManeuver.frequency_hz must be positive, got {self.frequency_hz.tolist()}"
            )
        _positive("ExcitationManeuver", "yaw_frequency_hz", self.yaw_frequency_hz)
        _positive("ExcitationManeuver", "duration_s", self.duration_s)
        # The four channels (x, y, z, yaw), stacked once rather than at every sample.
        object.__setattr__(self, "_amplitudes", np.append(self.amplitude_m, self.yaw_amplitude_rad))
        object.__setattr__(self, "_frequencies", np.append(self.frequency_hz, self.yaw_frequency_hz))
        # What _sine computes from the frequencies alone, once: w = 2 pi f (the array np.sin/np.cos take),
        # and w, -(w^2), -(w^3) and the amplitudes as floats (the same numpy operations, then .tolist()).
        w = 2.0 * math.pi * self._frequencies
        object.__setattr__(self, "_omega_rad_s", w)
        object.__setattr__(
            self,
            "_sine_factors",
            (w.tolist(), (-(w**2)).tolist(), (-(w**3)).tolist(), self._amplitudes.tolist()),
        )

    def _window(self, t: float) -> tuple[float, float, float, float]:
        """``h = sin^2(pi t / T) = (1 - cos(2 pi t / T)) / 2`` and its 3 derivatives."""
        c = 2.0 * math.pi / self.duration_s
        return (
            0.5 * (1.0 - math.cos(c * t)),
            0.5 * c * math.sin(c * t),
            0.5 * c**2 * math.cos(c * t),
            -0.5 * c**3 * math.sin(c * t),
        )

    @staticmethod
    def _sine(amplitude: np.ndarray, frequency_hz: np.ndarray, t: float) -> np.ndarray:
        """``A sin(2 pi f t)`` and its 3 derivatives, shape (4, K)."""
        w = 2.0 * math.pi * frequency_hz
        s, c = np.sin(w * t), np.cos(w * t)
        return amplitude * np.array([s, w * c, -(w**2) * s, -(w**3) * c])

    def sample(self, t_s: float) -> FlatOutput:
        """Flat output at ``t_s`` (s); Leibniz rule for the windowed sines."""
        t = min(max(float(t_s), 0.0), self.duration_s)
        h0, h1, h2, h3 = self._window(t)
        # _sine(amplitudes, frequencies, t) with its frequency terms precomputed: np.sin / np.cos of the same
        # array w t, then per channel A s, A (w c), A ((-w^2) s), A ((-w^3) c) in floats (the same products).
        wt = self._omega_rad_s * t
        sin, cos = np.sin(wt).tolist(), np.cos(wt).tolist()
        w1, w2, w3, amp = self._sine_factors
        g0 = [a * s for a, s in zip(amp, sin, strict=True)]
        g1 = [a * (w * c) for a, w, c in zip(amp, w1, cos, strict=True)]
        g2 = [a * (w * s) for a, w, s in zip(amp, w2, sin, strict=True)]
        g3 = [a * (w * c) for a, w, c in zip(amp, w3, cos, strict=True)]
        # d^n/dt^n (h g) = sum_k C(n, k) h^(k) g^(n-k) per channel, in plain floats: the same products and
        # left-to-right sums, from 0, as the former array expression (binomial rows 1; 1 1; 1 2 1; 1 3 3 1).
        d = [
            [0 + 1 * h0 * a for a in g0],
            [0 + 1 * h0 * a + 1 * h1 * b for a, b in zip(g1, g0, strict=True)],
            [0 + 1 * h0 * a + 2 * h1 * b + 1 * h2 * c for a, b, c in zip(g2, g1, g0, strict=True)],
            [
                0 + 1 * h0 * a + 3 * h1 * b + 3 * h2 * c + 1 * h3 * e
                for a, b, c, e in zip(g3, g2, g1, g0, strict=True)
            ],
        ]
        cx, cy, cz = self.center_W_m.tolist()
        return FlatOutput.from_floats(
            [cx + d[0][0], cy + d[0][1], cz + d[0][2]],
            d[1][:3],
            d[2][:3],
            d[3][:3],
            self.yaw_center_rad + d[0][3],
            d[1][3],
        )


class Sequence:
    """Setpoints flown one after another; each item's time starts when the previous one ends.

    Args:
        items: Setpoints; every item but the last needs a finite ``duration_s``. Consecutive items must join
            in position (end of one = start of the next within 1 mm).

    Raises:
        ValueError: Empty list, an infinite item before the end, or a position jump between items.
    """

    def __init__(self, items: Iterable[Setpoint]) -> None:
        """Validate the chain and precompute start times."""
        self._items = list(items)
        if not self._items:
            raise ValueError("Sequence needs at least one setpoint")
        starts = [0.0]
        for k, item in enumerate(self._items[:-1]):
            if not math.isfinite(item.duration_s):
                raise ValueError(f"Sequence item {k} ({type(item).__name__}) never ends but is not last")
            end = item.sample(item.duration_s).p_W
            start_next = self._items[k + 1].sample(0.0).p_W
            jump = float(np.linalg.norm(end - start_next))
            if jump > _CONTINUITY_TOL_M:
                raise ValueError(
                    f"Sequence items {k} ({type(item).__name__}) and {k + 1} "
                    f"({type(self._items[k + 1]).__name__}) are {jump:.3f} m apart: end {end.tolist()}, "
                    f"start {start_next.tolist()}"
                )
            starts.append(starts[-1] + item.duration_s)
        self._starts = starts

    @property
    def duration_s(self) -> float:
        """Sum of the item durations (s); ``inf`` if the last item never ends."""
        return self._starts[-1] + self._items[-1].duration_s

    @property
    def start_times_s(self) -> list[float]:
        """Start time of each item (s)."""
        return list(self._starts)

    def sample(self, t_s: float) -> FlatOutput:
        """Flat output of the item active at ``t_s`` (s), in that item's local time."""
        k = max(0, bisect.bisect_right(self._starts, float(t_s)) - 1)  # np.searchsorted(side="right")
        return self._items[k].sample(float(t_s) - self._starts[k])
