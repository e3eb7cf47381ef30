"""The motion library: named scripted motions of the quadrotor and the headset (ground truth for recordings).

Each motion is a :class:`~viotb.envs.scenarios.curves.ScriptedTrajectory` built from sums of sinusoids in a
smoothly warped phase (see :mod:`~viotb.envs.scenarios.curves`); :data:`TRAJECTORY_FACTORIES` names them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from dataclasses import replace as dataclass_replace

from viotb.envs.scenarios.curves import (
    ScriptedTrajectory,
    Sinusoids,
    SmoothWarp,
    StillStart,
    TimeShifted,
    Trajectory,
    TruthSample,
    TruthSeries,
)

__all__ = [
    "TRAJECTORY_FACTORIES",
    "MotionParams",
    "ScriptedTrajectory",
    "Sinusoids",
    "SmoothWarp",
    "StillStart",
    "TimeShifted",
    "Trajectory",
    "TruthSample",
    "TruthSeries",
]


@dataclass(frozen=True)
class MotionParams:
    """Shared knobs of the named motions.

    Attributes:
        duration_s: Length (s).
        ramp_s: Start/stop ramp (s).
        speed_scale: Multiplies the phase rate (1 = nominal speed).
    """

    duration_s: float = 30.0
    ramp_s: float = 2.0
    speed_scale: float = 1.0


def _warp(params: MotionParams, rate: float) -> SmoothWarp:
    ramp = min(params.ramp_s, 0.5 * params.duration_s)
    return SmoothWarp(params.duration_s, rate * params.speed_scale, ramp)


def _constant_yaw(yaw_rad: float) -> Sinusoids:
    return Sinusoids((yaw_rad,))


def hover(params: MotionParams = MotionParams()) -> ScriptedTrajectory:
    """Hover at (0, 0, 1.5) m with a small 3-axis Lissajous excitation (~5-10 cm, ~0.5 m/s^2) and yaw sway."""
    position = Sinusoids(
        (0.0, 0.0, 1.5),
        terms=(
            ((0.10, 0.0, 0.0), 2.0, (0.0, 0.0, 0.0)),
            ((0.0, 0.08, 0.0), 2.6, (0.0, 0.0, 0.0)),
            ((0.0, 0.0, 0.05), 3.3, (0.0, 0.0, 0.0)),
        ),
    )
    yaw = Sinusoids((0.0,), terms=(((0.15,), 0.7, (0.0,)),))
    return ScriptedTrajectory(position, yaw, "flat", _warp(params, 1.0))


def circle(
    params: MotionParams = MotionParams(), radius_m: float = 2.0, speed_m_s: float = 1.5
) -> ScriptedTrajectory:
    """Horizontal circle of ``radius_m`` at 1.5 m height, nose pointing along the velocity."""
    position = Sinusoids(
        (0.0, 0.0, 1.5), terms=(((radius_m, radius_m, 0.0), 1.0, (math.pi / 2.0, 0.0, 0.0)),)
    )
    yaw = Sinusoids((math.pi / 2.0,), linear=(1.0,))
    return ScriptedTrajectory(position, yaw, "flat", _warp(params, speed_m_s / radius_m))


def figure8(
    params: MotionParams = MotionParams(duration_s=60.0), half_width_m: float = 2.5, rate: float = 0.5
) -> ScriptedTrajectory:
    """Lemniscate of Gerono ``x = a sin th, y = (a/2) sin 2th`` with a gentle height wave, facing +x."""
    a = half_width_m
    position = Sinusoids(
        (0.0, 0.0, 1.5),
        terms=(((a, 0.0, 0.0), 1.0, (0.0, 0.0, 0.0)), ((0.0, 0.5 * a, 0.3), 2.0, (0.0, 0.0, 0.0))),
    )
    yaw = Sinusoids((0.0,), terms=(((0.3,), 1.0, (0.0,)),))
    return ScriptedTrajectory(position, yaw, "flat", _warp(params, rate))


def line(params: MotionParams = MotionParams(duration_s=8.0), speed_m_s: float = 0.8) -> ScriptedTrajectory:
    """Straight line along +x at constant velocity between the ramps, from x = -3 m, facing +x.

    The speed is lowered when needed so that the line stays within 6 m (inside the room).
    """
    position = Sinusoids((-3.0, 0.5, 1.5), linear=(1.0, 0.0, 0.0))
    cruise_s = params.duration_s - min(params.ramp_s, 0.5 * params.duration_s)
    speed = min(speed_m_s * params.speed_scale, 6.0 / cruise_s)
    warp = _warp(dataclass_replace(params, speed_scale=1.0), speed)
    return ScriptedTrajectory(position, _constant_yaw(0.0), "flat", warp)


def fast_rotation(params: MotionParams = MotionParams(), yaw_rate_rad_s: float = 3.0) -> ScriptedTrajectory:
    """Yaw spin at ``yaw_rate_rad_s`` in place at (0, 0, 1.5) m with a small translational excitation."""
    position = Sinusoids(
        (0.0, 0.0, 1.5), terms=(((0.1, 0.1, 0.05), 1.0 / yaw_rate_rad_s, (0.0, math.pi / 2.0, 0.0)),)
    )
    yaw = Sinusoids((0.0,), linear=(1.0,))
    return ScriptedTrajectory(position, yaw, "flat", _warp(params, yaw_rate_rad_s))


def aggressive(params: MotionParams = MotionParams(duration_s=20.0)) -> ScriptedTrajectory:
    """Fast 3-D figure-8 (peak ~9 m/s^2, ~5 m/s, tilt ~40 deg, ~5 rad/s) with yaw oscillation."""
    position = Sinusoids(
        (0.0, 0.0, 1.6),
        terms=(((2.8, 0.0, 0.0), 1.0, (0.0, 0.0, 0.0)), ((0.0, 1.4, 0.6), 2.0, (0.0, 0.0, math.pi / 2.0))),
    )
    yaw = Sinusoids((0.0,), terms=(((0.8,), 1.0, (math.pi / 2.0,)),))
    return ScriptedTrajectory(position, yaw, "flat", _warp(params, 1.2))


def long_loop(params: MotionParams = MotionParams(duration_s=120.0), laps: int = 3) -> ScriptedTrajectory:
    """``laps`` laps of a 3 x 2.5 m ellipse with a height wave, ending exactly at its start pose."""
    position = Sinusoids(
        (0.0, 0.0, 1.6),
        terms=(((3.0, 2.5, 0.0), 1.0, (0.0, -math.pi / 2.0, 0.0)), ((0.0, 0.0, 0.5), 2.0, (0.0, 0.0, 0.0))),
    )
    yaw = Sinusoids((0.0,), terms=(((0.5,), 1.0, (0.0,)),))
    ramp = min(params.ramp_s, 0.5 * params.duration_s)
    return ScriptedTrajectory(
        position,
        yaw,
        "flat",
        SmoothWarp(params.duration_s, 2.0 * math.pi * laps / (params.duration_s - ramp), ramp),
    )


def head_walk(
    params: MotionParams = MotionParams(), radius_m: float = 2.2, speed_m_s: float = 1.2
) -> ScriptedTrajectory:
    """Walk a circle of ``radius_m`` at head height 1.65 m with step bob (~2 Hz) and heading-aligned gaze."""
    rate = speed_m_s / radius_m
    step_freq = 2.0 * 2.0 * math.pi / rate  # two steps per second, in units of theta
    position = Sinusoids(
        (0.0, 0.0, 1.65),
        terms=(
            ((radius_m, radius_m, 0.0), 1.0, (math.pi / 2.0, 0.0, 0.0)),
            ((0.0, 0.0, 0.02), step_freq, (0.0,) * 3),
        ),
    )
    angles = Sinusoids(
        (math.pi / 2.0, 0.05, 0.0),
        linear=(1.0, 0.0, 0.0),
        terms=(
            ((0.25, 0.0, 0.0), 0.6 / rate, (0.0,) * 3),
            ((0.0, 0.02, 0.03), step_freq / 2.0, (0.0, 0.0, 0.5)),
        ),
    )
    return ScriptedTrajectory(position, angles, "euler", _warp(params, rate))


def head_look_around(params: MotionParams = MotionParams()) -> ScriptedTrajectory:
    """Standing at (0, 0, 1.65) m looking around: yaw +-60 deg, pitch +-25 deg, small sway (~0.5 rad/s)."""
    position = Sinusoids((0.0, 0.0, 1.65), terms=(((0.05, 0.04, 0.02), 0.5, (0.0, 1.0, 2.0)),))
    angles = Sinusoids(
        (0.0, 0.0, 0.0),
        terms=(((1.05, 0.0, 0.0), 0.45, (0.0,) * 3), ((0.0, 0.45, 0.08), 0.7, (0.0, 0.3, 1.0))),
    )
    return ScriptedTrajectory(position, angles, "euler", _warp(params, 1.0))


def head_fast_turns(params: MotionParams = MotionParams(duration_s=20.0)) -> ScriptedTrajectory:
    """Fast head turns: yaw +-70 deg at 0.8 Hz (peak ~6 rad/s = ~350 deg/s), pitch nods, standing still."""
    position = Sinusoids((0.0, 0.0, 1.65), terms=(((0.03, 0.03, 0.01), 1.0, (0.0, 1.0, 2.0)),))
    two_pi = 2.0 * math.pi
    angles = Sinusoids(
        (0.0, 0.0, 0.0),
        terms=(
            ((1.2, 0.0, 0.0), two_pi * 0.8, (0.0,) * 3),
            ((0.0, 0.3, 0.05), two_pi * 0.5, (0.0, 0.0, 1.0)),
        ),
    )
    return ScriptedTrajectory(position, angles, "euler", _warp(params, 1.0))


TRAJECTORY_FACTORIES = {
    "hover": hover,
    "circle": circle,
    "figure8": figure8,
    "line": line,
    "fast-rotation": fast_rotation,
    "aggressive": aggressive,
    "long-loop": long_loop,
    "head-walk": head_walk,
    "head-look-around": head_look_around,
    "head-fast-turns": head_fast_turns,
}
"""Motion name -> factory ``(MotionParams) -> ScriptedTrajectory``."""
