"""Read the quadrotor's controller-facing parameters and its true state from MuJoCo.

:func:`vehicle_params_from_model` is the only place where mass, inertia, rotor geometry, the yaw-moment
coefficient and the thrust limits come from: the MJCF (``models/quadrotor.xml``), through the names in
:mod:`viotb.models.constants`. :func:`nav_state_from_data` turns ``qpos``/``qvel`` into the controller's
:class:`~viotb.controllers.types.NavState` (ground truth).
"""

from __future__ import annotations

import mujoco
import numpy as np
from viotb.controllers.types import NavState
from viotb.controllers.vehicle import VehicleParams
from viotb.models.constants import QUAD_BODY, QUAD_FREEJOINT, QUAD_MOTORS, QUAD_ROTOR_SITES
from viotb.vio.lie import quat_wxyz_to_rotmat

_COM_TOL_M = 1e-9
"""The body origin must be the centre of mass (the controller's B frame = IMU frame)."""


def _id(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str, kind: str) -> int:
    """Index of a named MJCF element, or a ValueError naming it."""
    idx = mujoco.mj_name2id(model, obj, name)
    if idx < 0:
        raise ValueError(f"MJCF has no {kind} named {name!r} (see viotb.models.constants)")
    return idx


def vehicle_params_from_model(model: mujoco.MjModel) -> VehicleParams:
    """Vehicle parameters of the quadrotor in a compiled model.

    Steps: (1) mass and inertia of ``QUAD_BODY`` (principal inertia rotated by ``body_iquat`` into B);
    (2) each motor of ``QUAD_MOTORS`` must drive a site of ``QUAD_ROTOR_SITES`` on that body; its gear gives
    the thrust axis (force part, rotated by the site orientation) and the yaw-moment coefficient (torque part
    along the thrust axis); (3) ``ctrlrange`` gives the thrust limits, since ``ctrl`` is thrust in N
    (unit-norm force gear); (4) gravity from ``model.opt.gravity``.

    Args:
        model: Compiled model holding the quadrotor, e.g. ``viotb.models.load_model("quadrotor", "empty")``.

    Returns:
        The vehicle's :class:`VehicleParams`.

    Raises:
        ValueError: A name is missing, the centre of mass is off the body origin, a motor is not a
            site-driven unit-gear thrust, has no ctrlrange, or gravity is not along -z.
    """
    body = _id(model, mujoco.mjtObj.mjOBJ_BODY, QUAD_BODY, "body")
    ipos = np.array(model.body_ipos[body])
    if np.linalg.norm(ipos) > _COM_TOL_M:
        raise ValueError(
            f"body {QUAD_BODY!r}: inertial pos {ipos.tolist()} must be 0 (B origin = centre of mass)"
        )
    R_B_inertia = quat_wxyz_to_rotmat(model.body_iquat[body])
    inertia = R_B_inertia @ np.diag(model.body_inertia[body]) @ R_B_inertia.T

    positions, axes, coeffs, lows, highs = [], [], [], [], []
    for motor_name, site_name in zip(QUAD_MOTORS, QUAD_ROTOR_SITES, strict=True):
        act = _id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, motor_name, "actuator")
        site = _id(model, mujoco.mjtObj.mjOBJ_SITE, site_name, "site")
        if model.actuator_trntype[act] != mujoco.mjtTrn.mjTRN_SITE or model.actuator_trnid[act, 0] != site:
            raise ValueError(f"actuator {motor_name!r} must act on site {site_name!r}")
        if model.site_bodyid[site] != body:
            raise ValueError(f"site {site_name!r} must belong to body {QUAD_BODY!r}")
        if not model.actuator_ctrllimited[act]:
            raise ValueError(f"actuator {motor_name!r} needs a ctrlrange (thrust limits in N)")
        R_B_site = quat_wxyz_to_rotmat(model.site_quat[site])
        gear = np.array(model.actuator_gear[act])
        force_B = R_B_site @ gear[:3]
        if not np.isclose(np.linalg.norm(force_B), 1.0, atol=1e-9):
            raise ValueError(
                f"actuator {motor_name!r}: force gear {gear[:3].tolist()} must have unit norm "
                "(ctrl = thrust in N)"
            )
        torque_B = R_B_site @ gear[3:]
        positions.append(np.array(model.site_pos[site]) - ipos)
        axes.append(force_B)
        coeffs.append(float(torque_B @ force_B))
        lows.append(float(model.actuator_ctrlrange[act, 0]))
        highs.append(float(model.actuator_ctrlrange[act, 1]))

    gravity = np.array(model.opt.gravity)
    if not np.allclose(gravity[:2], 0.0) or gravity[2] >= 0.0:
        raise ValueError(f"model.opt.gravity must point along -z, got {gravity.tolist()}")
    return VehicleParams(
        mass_kg=float(model.body_mass[body]),
        inertia_kg_m2=inertia,
        rotor_positions_B_m=np.array(positions),
        thrust_axes_B=np.array(axes),
        yaw_moment_coeff_m=np.array(coeffs),
        min_thrust_N=np.array(lows),
        max_thrust_N=np.array(highs),
        gravity_m_s2=float(-gravity[2]),
    )


def nav_state_from_data(model: mujoco.MjModel, data: mujoco.MjData) -> NavState:
    """True navigation state of the quadrotor from its free joint.

    MuJoCo's free joint stores ``qpos = (p_WB, quat_wxyz)`` and ``qvel = (v_WB in W, omega in B)``.

    Args:
        model: Compiled model holding the quadrotor.
        data: Its data after ``mj_step``/``mj_forward``.

    Returns:
        :class:`NavState` with ``R_WB``, ``p_WB`` (m), ``v_WB`` (m/s, in W), ``omega_B`` (rad/s, in B).
    """
    joint = _id(model, mujoco.mjtObj.mjOBJ_JOINT, QUAD_FREEJOINT, "joint")
    qadr = model.jnt_qposadr[joint]
    vadr = model.jnt_dofadr[joint]
    qpos = data.qpos[qadr : qadr + 7]
    qvel = data.qvel[vadr : vadr + 6]
    return NavState(
        R_WB=quat_wxyz_to_rotmat(qpos[3:7]),
        p_WB=np.array(qpos[:3]),
        v_WB=np.array(qvel[:3]),
        omega_B=np.array(qvel[3:6]),
    )
