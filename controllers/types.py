"""What crosses the controller boundary: setpoints in, navigation state in, motor command out.

Frames: ``W`` world (z up), ``B`` body (x forward, y left, z up). Cf. rotorpy
``controllers/controller_template.py``, with frozen dataclasses in place of string-keyed dicts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from viotb.vio.types import StateEstimate


def checked_array(owner: str, name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    """Read-only float copy of ``value`` with the given shape, or a ValueError naming the field."""
    arr = np.array(value, dtype=float)
    if arr.shape != shape:
        raise ValueError(f"{owner}.{name}: expected shape {shape}, got {arr.shape}")
    if not np.isfinite(arr).all():  # the method: np.all() costs microseconds per tick
        raise ValueError(f"{owner}.{name}: non-finite value {arr.tolist()}")
    arr.setflags(write=False)
    return arr


def checked_arrays(owner: str, fields: tuple[tuple[str, object, tuple[int, ...]], ...]) -> list[np.ndarray]:
    """:func:`checked_array` for several fields at once: read-only float views of one checked buffer.

    The records built every control tick (setpoints, navigation states) validate four small arrays each;
    one copy and one finiteness check over all of them cost less than half of four separate ones (5 us
    against 12 us for a navigation state, on the loaded 2-core machine).

    Args:
        owner: Record name for the error message.
        fields: ``(name, value, shape)`` per field.

    Raises:
        ValueError: A value of the wrong shape or with a non-finite entry, naming the field.
    """
    parts = [value if type(value) is np.ndarray else np.asarray(value) for _, value, _ in fields]
    for (name, _, shape), part in zip(fields, parts, strict=True):
        if part.shape != shape:
            raise ValueError(f"{owner}.{name}: expected shape {shape}, got {part.shape}")
    buf = np.concatenate(parts, axis=None, dtype=float)  # a new, flat float buffer
    buf.setflags(write=False)  # before the views: a view of a writable buffer would stay writable
    out, start = [], 0
    for _, _, shape in fields:
        stop = start + math.prod(shape)
        out.append(buf[start:stop] if len(shape) == 1 else buf[start:stop].reshape(shape))
        start = stop
    if not np.isfinite(buf).all():
        for (name, _, _), arr in zip(fields, out, strict=True):
            if not np.isfinite(arr).all():
                raise ValueError(f"{owner}.{name}: non-finite value {arr.tolist()}")
    return out


def _zeros3() -> np.ndarray:
    return np.zeros(3)


@dataclass(frozen=True)
class FlatOutput:
    """A point on a differentially flat quadrotor trajectory (Mellinger & Kumar, ICRA 2011).

    Attributes:
        p_W: Position (m), shape (3,).
        v_W: Velocity (m/s), shape (3,).
        a_W: Acceleration (m/s^2), shape (3,).
        j_W: Jerk (m/s^3), shape (3,).
        yaw_rad: Heading of the body x axis about world z (rad).
        yaw_rate_rad_s: Its time derivative (rad/s).
    """

    p_W: np.ndarray
    v_W: np.ndarray = field(default_factory=_zeros3)
    a_W: np.ndarray = field(default_factory=_zeros3)
    j_W: np.ndarray = field(default_factory=_zeros3)
    yaw_rad: float = 0.0
    yaw_rate_rad_s: float = 0.0

    def __post_init__(self) -> None:
        """Validate shapes; store read-only float arrays."""
        names = ("p_W", "v_W", "a_W", "j_W")
        arrays = checked_arrays("FlatOutput", tuple((n, getattr(self, n), (3,)) for n in names))
        for name, arr in zip(names, arrays, strict=True):
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "_floats", tuple(x for arr in arrays for x in arr.tolist()))
        for name in ("yaw_rad", "yaw_rate_rad_s"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise ValueError(f"FlatOutput.{name}: non-finite value {value}")
            object.__setattr__(self, name, value)

    @classmethod
    def from_floats(
        cls, p_W: list, v_W: list, a_W: list, j_W: list, yaw_rad: float, yaw_rate_rad_s: float
    ) -> FlatOutput:
        """The record ``FlatOutput(p_W, v_W, a_W, j_W, yaw_rad, yaw_rate_rad_s)`` from plain floats.

        The setpoint generators' per-tick constructor: one float buffer of the 12 vector entries (read-only
        views, as the validating constructor stores them) and one finiteness test on a sum, about a fifth of
        the validating path's cost. A sum that is not finite (a non-finite entry, or finite ones whose sum
        overflows) takes the validating constructor, which raises its own error or builds the same record.

        Args:
            p_W: Position (m) in W, 3 floats.
            v_W: Velocity (m/s), 3 floats.
            a_W: Acceleration (m/s^2), 3 floats.
            j_W: Jerk (m/s^3), 3 floats.
            yaw_rad: Heading (rad).
            yaw_rate_rad_s: Its time derivative (rad/s).
        """
        values = [*p_W, *v_W, *a_W, *j_W]
        yaw, rate = float(yaw_rad), float(yaw_rate_rad_s)
        sizes_ok = len(p_W) == len(v_W) == len(a_W) == len(j_W) == 3
        if not (sizes_ok and math.isfinite(sum(values) + yaw + rate)):
            return cls(p_W=p_W, v_W=v_W, a_W=a_W, j_W=j_W, yaw_rad=yaw_rad, yaw_rate_rad_s=yaw_rate_rad_s)
        buf = np.array(values, dtype=float)
        buf.setflags(write=False)
        out = object.__new__(cls)  # the fields below are what __post_init__ would store
        for name, start in (("p_W", 0), ("v_W", 3), ("a_W", 6), ("j_W", 9)):
            object.__setattr__(out, name, buf[start : start + 3])
        object.__setattr__(out, "yaw_rad", yaw)
        object.__setattr__(out, "yaw_rate_rad_s", rate)
        object.__setattr__(out, "_floats", tuple(buf.tolist()))
        return out

    @property
    def vector_floats(self) -> tuple[float, ...]:
        """``(*p_W, *v_W, *a_W, *j_W)``: the 12 vector entries as plain floats, kept from the construction.

        The controllers' per-tick read (one attribute instead of four ``tolist`` calls); the arrays' values.
        """
        return self._floats


@dataclass(frozen=True)
class NavState:
    """The vehicle state a position controller consumes (from an estimate or from ground truth).

    Attributes:
        R_WB: Orientation, maps B coordinates to W, shape (3, 3).
        p_WB: Position of B's origin in W (m), shape (3,).
        v_WB: Velocity of B's origin in W (m/s), shape (3,).
        omega_B: Angular velocity of B relative to W, expressed in B (rad/s), shape (3,).
    """

    R_WB: np.ndarray
    p_WB: np.ndarray
    v_WB: np.ndarray = field(default_factory=_zeros3)
    omega_B: np.ndarray = field(default_factory=_zeros3)

    def __post_init__(self) -> None:
        """Validate shapes; store read-only float arrays."""
        fields = (("R_WB", self.R_WB, (3, 3)),) + tuple(
            (n, getattr(self, n), (3,)) for n in ("p_WB", "v_WB", "omega_B")
        )
        for (name, _, _), arr in zip(fields, checked_arrays("NavState", fields), strict=True):
            object.__setattr__(self, name, arr)

    @classmethod
    def from_estimate(cls, estimate: StateEstimate) -> NavState:
        """Build from the estimator's output.

        Uses ``R_WB``, ``p_WB``, ``v_WB`` and ``omega_B_rad_s`` (bias-corrected rate). ``vio.types`` is one of
        the two ``vio`` modules this room may import (DESIGN.md: the estimate it consumes; ``vio.lie`` for
        rotation math).
        """
        return cls(
            R_WB=estimate.R_WB,
            p_WB=estimate.p_WB,
            v_WB=estimate.v_WB,
            omega_B=estimate.omega_B_rad_s,
        )


@dataclass(frozen=True)
class ControlCommand:
    """One controller output.

    Attributes:
        thrusts_N: Per-motor thrusts after mixing and saturation (N), shape (4,); MuJoCo ``ctrl``.
        collective_N: Collective thrust actually produced by ``thrusts_N`` (N).
        moments_B_Nm: Body moments actually produced by ``thrusts_N`` (N m), shape (3,).
        R_WB_desired: Desired attitude from the position loop, shape (3, 3).
    """

    thrusts_N: np.ndarray
    collective_N: float
    moments_B_Nm: np.ndarray
    R_WB_desired: np.ndarray

    def __post_init__(self) -> None:
        """Validate shapes; store read-only float arrays."""
        fields = (
            ("thrusts_N", self.thrusts_N, (4,)),
            ("moments_B_Nm", self.moments_B_Nm, (3,)),
            ("R_WB_desired", self.R_WB_desired, (3, 3)),
        )
        for (name, _, _), arr in zip(fields, checked_arrays("ControlCommand", fields), strict=True):
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "collective_N", float(self.collective_N))


@runtime_checkable
class PositionController(Protocol):
    """A controller that turns a navigation state and a flat-output setpoint into motor thrusts."""

    def update(self, t_s: float, state: NavState, setpoint: FlatOutput) -> ControlCommand:
        """Compute the command at time ``t_s`` (s).

        Args:
            t_s: Current time (s); used for integral terms.
            state: Current (estimated or true) navigation state.
            setpoint: Desired flat output at ``t_s``.

        Returns:
            The motor command.
        """
        ...
