"""controllers room: SE(3) controller, motor mixer, setpoints (numpy; of vio only vio.lie and vio.types)."""

from viotb.controllers.mixer import Mixer
from viotb.controllers.se3 import SE3Controller, SE3Gains
from viotb.controllers.setpoints import (
    ExcitationManeuver,
    FigureEight,
    HoverPoint,
    Sequence,
    Setpoint,
    Takeoff,
    Waypoints,
)
from viotb.controllers.types import ControlCommand, FlatOutput, NavState, PositionController
from viotb.controllers.vehicle import VehicleParams

__all__ = [
    "ControlCommand",
    "ExcitationManeuver",
    "FigureEight",
    "FlatOutput",
    "HoverPoint",
    "Mixer",
    "NavState",
    "PositionController",
    "SE3Controller",
    "SE3Gains",
    "Sequence",
    "Setpoint",
    "Takeoff",
    "VehicleParams",
    "Waypoints",
]
