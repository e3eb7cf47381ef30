"""Control allocation: collective thrust and body moments <-> four motor thrusts.

The allocation matrix ``A`` (4 x 4) maps motor thrusts ``f`` (N) to the wrench ``w = (T, M_x, M_y, M_z)``:
row 0 is the thrust component along ``z_B`` and rows 1-3 the moment ``r_i x a_i f_i + k_i a_i f_i`` (lever arm
plus rotor reaction moment), cf. rotorpy ``SE3Control.f_to_TM``. It is built and inverted once.

Saturation policy of :meth:`Mixer.motor_thrusts`: a request that fits within the per-motor limits is inverted
exactly. Otherwise, in priority order:

1. Collective thrust is clipped to what the motors can give in total.
2. Roll/pitch moments come first: if their spread cannot fit between the limits at any collective thrust, they
   are scaled down (direction kept) until they just fit.
3. Collective thrust is kept if possible, otherwise moved by the least amount that fits the roll/pitch
   thrusts within the limits (attitude authority beats altitude for a moment).
4. Yaw is sacrificed: the yaw moment is scaled by the largest factor in [0, 1] that keeps every motor
   within limits.
"""

from __future__ import annotations

import math

import numpy as np
from viotb.controllers.vehicle import VehicleParams

_AXIS_TOL = 1e-6
"""Thrust axes must be +z_B to this tolerance: the collective thrust acts along b3."""


class Mixer:
    """Motor mixer for a four-rotor vehicle with thrust axes along ``+z_B``.

    Args:
        vehicle: Rotor geometry, yaw-moment coefficients and thrust limits.

    Raises:
        ValueError: A thrust axis is not ``+z_B``, or the allocation matrix is singular.
    """

    def __init__(self, vehicle: VehicleParams) -> None:
        """Build the allocation matrix and its inverse once."""
        axes = vehicle.thrust_axes_B
        if not np.allclose(axes, [0.0, 0.0, 1.0], atol=_AXIS_TOL):
            raise ValueError(f"Mixer needs every thrust axis along +z_B, got {axes.tolist()}")
        moments = np.cross(vehicle.rotor_positions_B_m, axes) + vehicle.yaw_moment_coeff_m[:, None] * axes
        allocation = np.vstack([axes[:, 2], moments.T])
        if abs(np.linalg.det(allocation)) < 1e-12:
            raise ValueError(f"Mixer: singular allocation matrix for rotor geometry {allocation.tolist()}")
        self._allocation = allocation
        self._allocation_inv = np.linalg.inv(allocation)
        self._min_N = vehicle.min_thrust_N.copy()
        self._max_N = vehicle.max_thrust_N.copy()
        # Plain-float copies for the per-tick exact inversion (:meth:`motor_thrusts_f`): four 4-term sums
        # in Python floats cost less than one small numpy product.
        self._inv_rows = tuple(tuple(row) for row in self._allocation_inv.tolist())
        self._lo_hi = tuple(zip(self._min_N.tolist(), self._max_N.tolist(), strict=True))

    @property
    def allocation(self) -> np.ndarray:
        """Allocation matrix, wrench ``(T, M_x, M_y, M_z) = A @ f``, shape (4, 4)."""
        return self._allocation.copy()

    def wrench(self, thrusts_N: np.ndarray) -> tuple[float, np.ndarray]:
        """Collective thrust (N) and body moments (N m, shape (3,)) from motor thrusts (N, shape (4,))."""
        f = np.asarray(thrusts_N, dtype=float)
        if f.shape != (4,) or not np.isfinite(f).all():
            raise ValueError(
                f"Mixer.wrench: thrusts_N must be 4 finite values, got {np.asarray(thrusts_N)!r}"
            )
        w = self._allocation @ f
        return float(w[0]), w[1:]

    def motor_thrusts(self, collective_N: float, moments_B_Nm: np.ndarray) -> np.ndarray:
        """Motor thrusts (N, shape (4,)) for a wrench, saturated by the policy in the module docstring.

        Args:
            collective_N: Desired collective thrust along ``z_B`` (N).
            moments_B_Nm: Desired body moments (N m), shape (3,).
        """
        moments = np.asarray(moments_B_Nm, dtype=float)
        if moments.shape != (3,) or not np.isfinite(moments).all() or not np.isfinite(collective_N):
            raise ValueError(
                f"Mixer.motor_thrusts: need a finite collective and 3 finite moments, got "
                f"{collective_N!r}, {np.asarray(moments_B_Nm)!r}"
            )
        mx, my, mz = moments.tolist()
        return self.motor_thrusts_f(float(collective_N), mx, my, mz)

    def motor_thrusts_f(self, collective_N: float, mx_Nm: float, my_Nm: float, mz_Nm: float) -> np.ndarray:
        """:meth:`motor_thrusts` for finite plain floats (the controllers' per-tick path), shape (4,).

        The exact inversion runs in Python floats (the same products as ``A^-1 @ w``, summed left to right
        rather than by BLAS, so a result may differ from the matrix product in the last bit); a request
        beyond the limits goes through the saturation policy.
        """
        exact = [
            r0 * collective_N + r1 * mx_Nm + r2 * my_Nm + r3 * mz_Nm for r0, r1, r2, r3 in self._inv_rows
        ]
        for f, (lo_i, hi_i) in zip(exact, self._lo_hi, strict=True):
            if not lo_i <= f <= hi_i:
                return self._saturate(collective_N, np.array([mx_Nm, my_Nm, mz_Nm]))
        return np.array(exact)

    def _saturate(self, collective_N: float, moments: np.ndarray) -> np.ndarray:
        """Steps 1-4 of the saturation policy (module docstring) for a request beyond the motor limits."""
        if not math.isfinite(collective_N) or not np.isfinite(moments).all():
            raise ValueError(
                f"Mixer.motor_thrusts: need a finite collective and 3 finite moments, got "
                f"{collective_N!r}, {moments!r}"
            )
        lo, hi = self._min_N, self._max_N
        col_T, col_rp, col_yaw = (
            self._allocation_inv[:, 0],
            self._allocation_inv[:, 1:3],
            self._allocation_inv[:, 3],
        )

        # 1. Collective within what the motors can give in total (col_T > 0 for a sane geometry).
        collective = float(np.clip(collective_N, np.max(lo / col_T), np.min(hi / col_T)))

        # 2. Roll/pitch thrust differences; scale them until some collective fits them all.
        d_rp = col_rp @ moments[:2]
        d_rp *= self._fit_scale(d_rp, col_T, lo, hi)

        # 3. Collective: nearest feasible value given the roll/pitch differences.
        t_lo = np.max((lo - d_rp) / col_T)
        t_hi = np.min((hi - d_rp) / col_T)
        collective = float(np.clip(collective, t_lo, max(t_lo, t_hi)))
        f_rp = col_T * collective + d_rp

        # 4. Yaw: the largest scale in [0, 1] that keeps every motor within limits.
        d_yaw = col_yaw * moments[2]
        scale = 1.0
        for i in range(4):
            if d_yaw[i] > 0.0:
                scale = min(scale, (hi[i] - f_rp[i]) / d_yaw[i])
            elif d_yaw[i] < 0.0:
                scale = min(scale, (lo[i] - f_rp[i]) / d_yaw[i])
        scale = max(scale, 0.0)
        return np.clip(f_rp + scale * d_yaw, lo, hi)

    @staticmethod
    def _fit_scale(d: np.ndarray, col_T: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
        """Largest ``s`` in [0, 1] such that some ``T`` gives ``lo <= col_T T + s d <= hi`` for every motor.

        Feasible iff for all pairs (i, j): ``(lo_i - s d_i) / c_i <= (hi_j - s d_j) / c_j``, which is linear
        in ``s``: ``s (d_j / c_j - d_i / c_i) <= hi_j / c_j - lo_i / c_i``.
        """
        slope = (d / col_T)[None, :] - (d / col_T)[:, None]
        room = (hi / col_T)[None, :] - (lo / col_T)[:, None]
        binding = slope > 0.0
        if not np.any(binding):
            return 1.0
        return float(np.clip(np.min(room[binding] / slope[binding]), 0.0, 1.0))
