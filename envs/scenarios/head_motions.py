"""Head motions of the headset rig: sitting still, looking around, fast turns, crouching, facing a wall.

Each is a :class:`~viotb.envs.scenarios.curves.ScriptedTrajectory` in ``"euler"`` attitude mode
(``R_WB = Rz(yaw) Ry(pitch) Rx(roll)``, B = x forward, y left, z up) with the phase running at one unit per
second (``theta = t`` between the start/stop ramps), so every frequency below is in rad/s of time. Walking the
room is :func:`viotb.envs.scenarios.motions.head_walk`. Eye height: 1.65 m standing, 1.20 m seated; the room
is ~10 x 10 m centred at the origin.

Peak yaw rate of ``A sin(w t)`` is ``A w``: looking around (``A = 60 deg``, ``w = 3.33 rad/s``) peaks at
200 deg/s; the fast turns (``A = 70 deg``, ``w = 2 pi 0.8 rad/s``) at ~350 deg/s.
"""

from __future__ import annotations

import math

from viotb.envs.scenarios.curves import ScriptedTrajectory, Sinusoids, SmoothWarp
from viotb.envs.scenarios.motions import MotionParams

_DEG = math.pi / 180.0
_TWO_PI = 2.0 * math.pi
STANDING_EYE_HEIGHT_M = 1.65
SEATED_EYE_HEIGHT_M = 1.20
_DEFAULT = MotionParams()


def _warp(params: MotionParams) -> SmoothWarp:
    """Phase = time (rate 1) with the motion's start/stop ramps."""
    ramp = min(params.ramp_s, 0.5 * params.duration_s)
    return SmoothWarp(params.duration_s, params.speed_scale, ramp)


def head_still(params: MotionParams = _DEFAULT) -> ScriptedTrajectory:
    """Seated still: breathing sway (0.25 Hz, 0.4 mm fore-aft, 0.3 mm vertical) and 0.03 deg head sway."""
    w_breath = _TWO_PI * 0.25
    position = Sinusoids(
        (0.0, 0.0, SEATED_EYE_HEIGHT_M),
        terms=(((4e-4, 1e-4, 3e-4), w_breath, (0.0, 1.0, 0.5)),),
    )
    angles = Sinusoids(
        (0.0, 0.0, 0.0),
        terms=(((0.03 * _DEG, 0.02 * _DEG, 0.01 * _DEG), _TWO_PI * 0.1, (0.0, 1.0, 2.0)),),
    )
    return ScriptedTrajectory(position, angles, "euler", _warp(params))


def head_look_around_fast(
    params: MotionParams = _DEFAULT, yaw_deg: float = 60.0, peak_rate_deg_s: float = 200.0
) -> ScriptedTrajectory:
    """Standing, looking around: yaw +-``yaw_deg`` peaking at ``peak_rate_deg_s``, pitch +-15 deg, neck sway.

    The eyes sit ~10 cm in front of the neck's yaw axis, so they sweep an arc of a few cm as the head turns.
    """
    w_yaw = peak_rate_deg_s / yaw_deg
    neck_m = 0.10
    position = Sinusoids(
        (0.0, 0.0, STANDING_EYE_HEIGHT_M),
        terms=(
            ((0.0, neck_m * math.sin(yaw_deg * _DEG), 0.0), w_yaw, (0.0, 0.0, 0.0)),
            ((0.01, 0.0, 0.005), 0.5, (0.0, 0.0, 1.0)),
        ),
    )
    angles = Sinusoids(
        (0.0, 0.0, 0.0),
        terms=(
            ((yaw_deg * _DEG, 0.0, 0.0), w_yaw, (0.0,) * 3),
            ((0.0, 15 * _DEG, 3 * _DEG), 1.1, (0.0, 0.4, 1.0)),
        ),
    )
    return ScriptedTrajectory(position, angles, "euler", _warp(params))


def head_crouch(params: MotionParams = _DEFAULT, period_s: float = 4.0) -> ScriptedTrajectory:
    """Crouching and standing: eye height 1.65 <-> 1.05 m every ``period_s``, leaning forward 10 deg down."""
    w = _TWO_PI / period_s
    position = Sinusoids(
        (0.0, 0.0, STANDING_EYE_HEIGHT_M - 0.30),
        terms=(((0.08, 0.0, 0.30), w, (-math.pi / 2.0, 0.0, math.pi / 2.0)),),
    )
    angles = Sinusoids(
        (0.3, 5 * _DEG, 0.0),
        terms=(((0.3, 5 * _DEG, 0.0), w * 0.5, (0.0, -math.pi / 2.0, 0.0)),),
    )
    return ScriptedTrajectory(position, angles, "euler", _warp(params))


def head_face_wall(params: MotionParams = _DEFAULT, distance_m: float = 1.0) -> ScriptedTrajectory:
    """Standing ``distance_m`` from the +x wall (at 5 m), facing it, glancing +-15 deg and nodding slowly."""
    position = Sinusoids(
        (5.0 - distance_m, 0.0, STANDING_EYE_HEIGHT_M),
        terms=(((0.02, 0.02, 0.01), 0.6, (0.0, 1.0, 2.0)),),
    )
    angles = Sinusoids(
        (0.0, 0.0, 0.0),
        terms=(((15 * _DEG, 0.0, 0.0), 0.8, (0.0,) * 3), ((0.0, 8 * _DEG, 0.0), 0.5, (0.0, 0.3, 0.0))),
    )
    return ScriptedTrajectory(position, angles, "euler", _warp(params))


HEAD_TRAJECTORY_FACTORIES = {
    "head-still": head_still,
    "head-look-around-fast": head_look_around_fast,
    "head-crouch": head_crouch,
    "head-face-wall": head_face_wall,
}
"""Motion name -> factory ``(MotionParams) -> ScriptedTrajectory`` (the other head motions are in
:data:`viotb.envs.scenarios.motions.TRAJECTORY_FACTORIES`)."""
