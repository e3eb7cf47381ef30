"""Rigid-body and rotor parameters of a multirotor, as the controller and the mixer need them.

The values are read from the MJCF by :func:`viotb.envs.sim.vehicle.vehicle_params_from_model`; they are never
typed a second time here (cf. rotorpy ``vehicles/hummingbird_params.py``, but loaded rather than hard-coded).

Rotor model: motor ``i`` at ``rotor_positions_B_m[i]`` (relative to the centre of mass, in B) produces a
thrust ``f_i`` (N) along the unit axis ``thrust_axes_B[i]`` and a reaction moment
``yaw_moment_coeff_m[i] * f_i`` (N m) about the same axis; the sign of the coefficient is the spin direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.controllers.types import checked_array
from viotb.vio.types import GRAVITY_M_S2

_N_ROTORS = 4


@dataclass(frozen=True)
class VehicleParams:
    """Physical parameters of a four-rotor vehicle.

    Attributes:
        mass_kg: Total mass (kg).
        inertia_kg_m2: Inertia about the centre of mass, expressed in B (kg m^2), shape (3, 3), symmetric PD.
        rotor_positions_B_m: Rotor force application points relative to the centre of mass, in B (m),
            shape (4, 3).
        thrust_axes_B: Unit thrust direction of each rotor in B, shape (4, 3) (``+z_B`` for a flat frame).
        yaw_moment_coeff_m: Reaction moment per unit thrust about the thrust axis (m = N m / N), shape (4,),
            signed by spin direction.
        min_thrust_N: Lower thrust limit per motor (N), shape (4,).
        max_thrust_N: Upper thrust limit per motor (N), shape (4,).
        gravity_m_s2: Magnitude of gravity (m/s^2); world gravity is ``(0, 0, -gravity_m_s2)``.
    """

    mass_kg: float
    inertia_kg_m2: np.ndarray
    rotor_positions_B_m: np.ndarray
    thrust_axes_B: np.ndarray
    yaw_moment_coeff_m: np.ndarray
    min_thrust_N: np.ndarray
    max_thrust_N: np.ndarray
    gravity_m_s2: float = GRAVITY_M_S2

    def __post_init__(self) -> None:
        """Validate shapes and physical sense; store read-only float arrays."""
        if not (np.isfinite(self.mass_kg) and self.mass_kg > 0.0):
            raise ValueError(f"VehicleParams.mass_kg must be positive and finite, got {self.mass_kg!r}")
        if not (np.isfinite(self.gravity_m_s2) and self.gravity_m_s2 > 0.0):
            raise ValueError(f"VehicleParams.gravity_m_s2 must be positive, got {self.gravity_m_s2!r}")
        arrays = {
            "inertia_kg_m2": (3, 3),
            "rotor_positions_B_m": (_N_ROTORS, 3),
            "thrust_axes_B": (_N_ROTORS, 3),
            "yaw_moment_coeff_m": (_N_ROTORS,),
            "min_thrust_N": (_N_ROTORS,),
            "max_thrust_N": (_N_ROTORS,),
        }
        for name, shape in arrays.items():
            object.__setattr__(self, name, checked_array("VehicleParams", name, getattr(self, name), shape))
        inertia = self.inertia_kg_m2
        if not np.allclose(inertia, inertia.T, atol=1e-12) or np.linalg.eigvalsh(inertia).min() <= 0.0:
            raise ValueError(
                f"VehicleParams.inertia_kg_m2 must be symmetric positive definite, got {inertia}"
            )
        norms = np.linalg.norm(self.thrust_axes_B, axis=1)
        if not np.allclose(norms, 1.0, atol=1e-9):
            raise ValueError(f"VehicleParams.thrust_axes_B rows must be unit vectors, norms {norms.tolist()}")
        if np.any(self.min_thrust_N < 0.0) or np.any(self.max_thrust_N <= self.min_thrust_N):
            raise ValueError(
                "VehicleParams thrust limits need 0 <= min_thrust_N < max_thrust_N, got "
                f"min {self.min_thrust_N.tolist()} max {self.max_thrust_N.tolist()}"
            )
        object.__setattr__(self, "mass_kg", float(self.mass_kg))
        object.__setattr__(self, "gravity_m_s2", float(self.gravity_m_s2))

    @property
    def hover_thrust_N(self) -> float:
        """Collective thrust that balances gravity, ``m g`` (N)."""
        return self.mass_kg * self.gravity_m_s2

    @property
    def gravity_W_m_s2(self) -> np.ndarray:
        """World gravity vector (m/s^2), shape (3,)."""
        return np.array([0.0, 0.0, -self.gravity_m_s2])
