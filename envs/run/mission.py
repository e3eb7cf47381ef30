"""The takeoff-on-the-estimate sequence (used by ``viotb fly`` and the Gymnasium ground start), missions.

:class:`TakeoffSequence` is a small phase machine on the estimate, never on the truth:

1. ``ground``: motors off until the estimator reports its first estimate (it initializes from the IMU at
   rest);
2. ``takeoff``: a smooth climb (:class:`~viotb.controllers.setpoints.Takeoff`) from the estimated start to the
   hover point chosen from that first estimate;
3. ``excite``: a short excitation manoeuvre, only when allowed and the estimator asks for one
   (``estimator.wants_excitation()``), as a real VIO drone must;
4. ``mission``: the mission's setpoints from the hover point; without a mission the takeoff's end is held.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from viotb.controllers.setpoints import (
    ExcitationManeuver,
    FigureEight,
    HoverPoint,
    Sequence,
    StraightLine,
    Takeoff,
    Waypoints,
)
from viotb.controllers.types import FlatOutput
from viotb.vio.lie import rotz, yaw_from_rotmat
from viotb.vio.types import Estimator, StateEstimate

MISSION_KINDS = ("hover", "waypoints", "loops", "line", "figure8", "aggressive")
"""Missions a closed-loop scenario can fly (:func:`mission_setpoints`)."""

Setpoint = Takeoff | HoverPoint | Sequence | FigureEight | ExcitationManeuver | StraightLine | Waypoints
"""Anything with ``sample(t_s) -> FlatOutput`` and ``duration_s``."""


class TakeoffSequence:
    """ground -> takeoff -> (excite) -> mission, on the estimate (see the module docstring).

    Args:
        hover_from_estimate: Maps the first estimate to the hover point (estimator frame, m, shape (3,)).
        takeoff_s: Duration of the climb (s).
        mission: Mission flown from the hover point after the takeoff (a :data:`MISSION_KINDS` name), or None
            to hold the takeoff's end.
        allow_excitation: Fly an excitation manoeuvre after the takeoff when the estimator asks for one (only
            with a mission: without one the takeoff's end is held whatever the estimator asks).

    Attributes:
        phase: ``"ground"``, ``"takeoff"``, ``"excite"`` or ``"mission"``.
        init_t_s: Time of the first estimate (s), None on the ground.
        mission_t0_s: Start of the mission (s), None before.
        excitation_flown: Whether the excitation manoeuvre was started.
        hover_W: The hover point (estimator frame), None on the ground.
    """

    def __init__(
        self,
        hover_from_estimate: Callable[[StateEstimate], np.ndarray],
        takeoff_s: float = 3.0,
        mission: str | None = None,
        allow_excitation: bool = False,
    ) -> None:
        """A sequence on the ground."""
        if mission is not None and mission not in MISSION_KINDS:
            raise ValueError(f"unknown mission {mission!r}; known: {MISSION_KINDS}")
        self._hover_from_estimate = hover_from_estimate
        self._takeoff_s = float(takeoff_s)
        self._mission = mission
        self._allow_excitation = allow_excitation
        self._plan: Setpoint | None = None
        self._plan_t0 = 0.0
        self.phase = "ground"
        self.init_t_s: float | None = None
        self.mission_t0_s: float | None = None
        self.excitation_flown = False
        self.hover_W: np.ndarray | None = None

    @property
    def plan_t0_s(self) -> float:
        """Start time (s) of the current plan."""
        return self._plan_t0

    def update(self, t_s: float, est: StateEstimate | None, estimator: Estimator) -> FlatOutput | None:
        """Advance the phase at time ``t_s`` and return the setpoint (None on the ground).

        Args:
            t_s: Time now (s).
            est: Latest estimate (None before initialization).
            estimator: The estimator (asked ``wants_excitation()`` at the end of the takeoff).
        """
        if self.phase == "ground" and est is not None:
            self.init_t_s = t_s
            yaw0 = yaw_from_rotmat(est.R_WB)
            self.hover_W = self._hover_from_estimate(est)
            self._plan = Takeoff(est.p_WB, float(self.hover_W[2]), duration_s=self._takeoff_s, yaw_rad=yaw0)
            self._plan_t0, self.phase = t_s, "takeoff"
        elif (
            self.phase in ("takeoff", "excite")
            and self._plan is not None
            and self._mission is not None
            and t_s - self._plan_t0 >= self._plan.duration_s
        ):
            yaw0 = self._plan.sample(self._plan.duration_s).yaw_rad
            if self.phase == "takeoff" and self._allow_excitation and estimator.wants_excitation():
                self._plan = ExcitationManeuver(self.hover_W, yaw_center_rad=yaw0)
                self._plan_t0, self.phase, self.excitation_flown = t_s, "excite", True
            else:
                self._plan = mission_setpoints(self._mission, self.hover_W, yaw0)
                self._plan_t0, self.phase, self.mission_t0_s = t_s, "mission", t_s
        return self._plan.sample(t_s - self._plan_t0) if self._plan is not None else None


def mission_setpoints(kind: str, hover_W: np.ndarray, yaw: float) -> Setpoint:
    """Setpoints of mission ``kind`` (one of :data:`MISSION_KINDS`) starting at rest at ``hover_W``.

    Args:
        kind: Mission name.
        hover_W: Start and hold point in the estimator's frame (m), shape (3,).
        yaw: Heading (rad).
    """
    if kind == "hover":
        return HoverPoint(hover_W, yaw)
    if kind in ("waypoints", "loops"):
        R = rotz(yaw)
        lap = [[1.5, 0, 0.5], [1.5, 1.5, 0.5], [0, 1.5, 0.5], [0, 0, 0]]
        corners = [[0, 0, 0]] + lap * (3 if kind == "loops" else 1)
        square = [hover_W + R @ np.array(d) for d in corners]
        yaws = np.full(len(square), yaw)
        return Sequence([Waypoints(np.array(square), yaws_rad=yaws, speed_m_s=0.6), HoverPoint(hover_W, yaw)])
    if kind == "line":
        line = StraightLine(
            hover_W, rotz(yaw) @ np.array([1.0, 0.0, 0.0]), length_m=4.5, speed_m_s=0.8, yaw_rad=yaw
        )
        return Sequence([line, HoverPoint(line.sample(line.duration_s).p_W, yaw)])
    if kind == "figure8":
        return FigureEight(
            center_xy_m=hover_W[:2],
            size_m=np.array([1.5, 0.75]),
            period_s=12.0,
            altitude_m=float(hover_W[2]),
            yaw_rad=yaw,
        )
    if kind == "aggressive":
        return Sequence(
            [
                ExcitationManeuver(
                    hover_W,
                    amplitude_m=np.array([0.6, 0.6, 0.1]),
                    frequency_hz=np.array([1.2, 1.4, 0.5]),
                    yaw_center_rad=yaw,
                    yaw_amplitude_rad=0.0,
                    duration_s=4.0,
                ),
                HoverPoint(hover_W, yaw),
            ]
        )
    raise ValueError(f"unknown mission {kind!r}")
