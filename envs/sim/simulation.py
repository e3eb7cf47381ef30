"""MuJoCo simulation of one vehicle (quadrotor or headset rig) in one scene, with named truth readers.

The wrapper owns one ``MjModel``/``MjData`` pair (dm_control's ``Physics`` idea): all names come from
:mod:`viotb.models.constants`, ids are resolved once in ``__init__``, and every reader returns a numpy
array with its frame and unit in its name. Frames: ``W`` world (z up), ``B`` body = IMU frame, ``C`` the
OpenCV camera frame (x right, y down, z forward).

Two ways to move the vehicle:

* dynamics: :meth:`Simulation.step` with motor thrusts (quadrotor);
* kinematics: :meth:`Simulation.set_pose` writes the pose and twist (free-joint ``qpos``/``qvel`` for the
  quadrotor, the mocap pose for the headset) and runs ``mj_forward``.

The headset is a mocap body: it has no degrees of freedom, so MuJoCo's gyro and accelerometer on it read
zero rate and plain gravity. Its truth readers therefore return the kinematic twist and acceleration
last given to :meth:`Simulation.set_pose`.
"""

from __future__ import annotations

import mujoco
import numpy as np
from viotb.envs.sim.checks import all_finite
from viotb.envs.sim.render import camera_world_pose
from viotb.models import load_model
from viotb.models.constants import (
    ACCEL_SENSOR,
    GYRO_SENSOR,
    HEAD_BODY,
    IMU_POS_SENSOR,
    IMU_QUAT_SENSOR,
    ONBOARD_CAMERA,
    QUAD_FREEJOINT,
    QUAD_MOTORS,
    VEHICLE_BODIES,
)
from viotb.vio.lie import quat_wxyz_to_rotmat, quat_wxyz_to_rotmat_rows, rotmat_to_quat_wxyz
from viotb.vio.types import gravity_W

_ROTATION_ATOL = 1e-6
"""Tolerance on ``R^T R = I`` and ``det R = 1`` for rotations given to :meth:`Simulation.set_pose`."""


def _name_id(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str) -> int:
    """Id of a named model element, with a clear error naming the missing element."""
    obj_id = mujoco.mj_name2id(model, obj, name)
    if obj_id < 0:
        raise ValueError(f"{obj.name[6:].lower()} {name!r} not found in the model")
    return obj_id


def sensor_slice(model: mujoco.MjModel, name: str) -> slice:
    """Slice of ``data.sensordata`` holding the named sensor.

    Raises:
        ValueError: No sensor of that name.
    """
    sensor_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
    if sensor_id < 0:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SENSOR, i) for i in range(model.nsensor)]
        raise ValueError(f"sensor {name!r} not in model; sensors: {names}")
    adr = int(model.sensor_adr[sensor_id])
    return slice(adr, adr + int(model.sensor_dim[sensor_id]))


def sensor_data(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> np.ndarray:
    """Copy of the named sensor's reading (mujoco_playground's ``get_sensor_data``), shape (dim,)."""
    return data.sensordata[sensor_slice(model, name)].copy()


def _check_vector(value, name: str, size: int = 3) -> np.ndarray:
    """``value`` as a finite float array of shape (size,), or a ValueError naming the argument."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite array of shape ({size},), got {value!r}")
    return arr


def _check_rotation(R: np.ndarray, name: str) -> np.ndarray:
    """``R`` as a (3, 3) rotation matrix, or a ValueError naming the argument."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"{name} must be a finite (3, 3) rotation matrix, got shape {R.shape}")
    if not np.allclose(R.T @ R, np.eye(3), atol=_ROTATION_ATOL) or abs(np.linalg.det(R) - 1) > _ROTATION_ATOL:
        raise ValueError(f"{name} is not a rotation matrix (R^T R != I or det != 1): {R.tolist()}")
    return R


class Simulation:
    """One vehicle in one scene.

    Args:
        vehicle: ``"quadrotor"`` or ``"headset"``.
        scene: Scene name from ``viotb.models.constants.SCENE_XMLS``.

    Attributes:
        model: The compiled ``mujoco.MjModel``.
        data: Its ``mujoco.MjData``.
        vehicle: The vehicle name.
        scene: The scene name.

    Raises:
        ValueError: Unknown vehicle or scene.
    """

    def __init__(self, vehicle: str = "quadrotor", scene: str = "textured_room") -> None:
        """Compile the model and resolve every id the readers use."""
        self.model = load_model(vehicle, scene)
        self.data = mujoco.MjData(self.model)
        self.vehicle = vehicle
        self.scene = scene
        m = self.model
        self._body_id = _name_id(m, mujoco.mjtObj.mjOBJ_BODY, VEHICLE_BODIES[vehicle])
        self._cam_id = _name_id(m, mujoco.mjtObj.mjOBJ_CAMERA, ONBOARD_CAMERA)
        self._gyro = sensor_slice(m, GYRO_SENSOR)
        self._accel = sensor_slice(m, ACCEL_SENSOR)
        self._imu_pos = sensor_slice(m, IMU_POS_SENSOR)
        self._imu_quat = sensor_slice(m, IMU_QUAT_SENSOR)
        self._is_mocap = vehicle == "headset"
        if self._is_mocap:
            self._mocap_id = int(m.body_mocapid[_name_id(m, mujoco.mjtObj.mjOBJ_BODY, HEAD_BODY)])
            self._motor_ids = np.zeros(0, dtype=int)
        else:
            joint_id = _name_id(m, mujoco.mjtObj.mjOBJ_JOINT, QUAD_FREEJOINT)
            self._qpos_adr = int(m.jnt_qposadr[joint_id])
            self._qvel_adr = int(m.jnt_dofadr[joint_id])
            self._motor_ids = np.array([_name_id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in QUAD_MOTORS])
        # Geoms of the vehicle's subtree (for in_collision).
        root_of_body = m.body_rootid
        self._vehicle_geoms = frozenset(
            int(g) for g in range(m.ngeom) if root_of_body[m.geom_bodyid[g]] == self._body_id
        )
        # Kinematic twist and acceleration of the mocap headset (W / B frames; m/s, rad/s, m/s^2).
        self._kin_v_W = np.zeros(3)
        self._kin_omega_B = np.zeros(3)
        self._kin_a_W = np.zeros(3)
        self._forward_key: tuple | None = None  # the state of the last step's closing mj_forward
        self._has_mocap = m.nmocap > 0
        # Views into ``data``'s arrays, built once (each attribute read of MjData builds a new view): the
        # per-tick readers and the state key read these; ``data`` is this object's for its whole life.
        d = self.data
        self._qpos, self._qvel = d.qpos, d.qvel
        self._quat_view = d.sensordata[self._imu_quat]
        self._pos_view = d.sensordata[self._imu_pos]
        self._gyro_view = d.sensordata[self._gyro]
        self._accel_view = d.sensordata[self._accel]
        self._xfrc_body = d.xfrc_applied[self._body_id]
        mujoco.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------ time and stepping

    @property
    def model_name(self) -> str:
        """``"<vehicle>_<scene>"``, the composed model's name."""
        return f"{self.vehicle}_{self.scene}"

    @property
    def time_s(self) -> float:
        """Simulation time (s)."""
        return float(self.data.time)

    @property
    def timestep_s(self) -> float:
        """Physics timestep (s)."""
        return float(self.model.opt.timestep)

    def keyframe_names(self) -> list[str]:
        """Names of the model's keyframes."""
        return [mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_KEY, i) for i in range(self.model.nkey)]

    def reset(self, keyframe: str | None = None) -> None:
        """Reset to the model defaults (``keyframe=None``) or to a named keyframe, then ``mj_forward``.

        Raises:
            ValueError: Unknown keyframe (the message lists the model's keyframes).
        """
        if keyframe is None:
            mujoco.mj_resetData(self.model, self.data)
        else:
            key_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_KEY, keyframe)
            if key_id < 0:
                known = self.keyframe_names()
                raise ValueError(f"keyframe {keyframe!r} not in model {self.model_name}; keyframes: {known}")
            mujoco.mj_resetDataKeyframe(self.model, self.data, key_id)
        self._kin_v_W[:] = 0.0
        self._kin_omega_B[:] = 0.0
        self._kin_a_W[:] = 0.0
        self._forward_key = None
        mujoco.mj_forward(self.model, self.data)

    def step(self, ctrl: np.ndarray | None = None, n_steps: int = 1) -> None:
        """Advance the physics ``n_steps`` timesteps holding ``ctrl``, then ``mj_forward``.

        The final ``mj_forward`` makes every reader (poses, sensors, camera) consistent with the state at
        :attr:`time_s` (``mj_step`` alone leaves them at the state before its last integration).

        Args:
            ctrl: Actuator commands, shape (nu,) (quadrotor: motor thrusts (N), clipped to ctrlrange by
                MuJoCo); None keeps the current ``data.ctrl``.
            n_steps: Number of physics steps (>= 1).

        Raises:
            ValueError: Wrong ``ctrl`` shape, non-finite ``ctrl`` or ``n_steps < 1``.
        """
        self.step_checked(None if ctrl is None else self.checked_ctrl(ctrl), n_steps)

    def checked_ctrl(self, ctrl: np.ndarray) -> np.ndarray:
        """``ctrl`` as a float array of shape (nu,), checked once for loops that step it in several chunks.

        Raises:
            ValueError: Wrong shape or non-finite values.
        """
        ctrl = np.asarray(ctrl, dtype=float)
        if ctrl.shape != (self.model.nu,) or not all_finite(ctrl.tolist()):
            raise ValueError(f"ctrl must be a finite array of shape ({self.model.nu},), got {ctrl!r}")
        return ctrl

    def step_checked(self, ctrl: np.ndarray | None, n_steps: int = 1) -> None:
        """:meth:`step` for a ``ctrl`` already passed through :meth:`checked_ctrl` (or None)."""
        if n_steps < 1:
            raise ValueError(f"n_steps must be >= 1, got {n_steps}")
        m, d = self.model, self.data
        if ctrl is not None:
            d.ctrl[:] = ctrl
        key = self._forward_key
        if key is not None and key == self.state_key():
            # The last step's closing mj_forward computed this state's position and velocity stages (the
            # collision test is most of them): finish the first step with MuJoCo's split step, mj_step2
            # (mj_step = mj_step1 + mj_step2; mj_step1 is those stages and the position/velocity checks).
            mujoco.mj_checkPos(m, d)
            mujoco.mj_checkVel(m, d)
            mujoco.mj_step2(m, d)
            if n_steps > 1:
                mujoco.mj_step(m, d, n_steps - 1)
        else:
            mujoco.mj_step(m, d, n_steps)  # the same as n_steps calls, without their overhead
        mujoco.mj_forward(m, d)
        self._forward_key = self.state_key()

    def state_key(self) -> tuple:
        """What the position and velocity stages read from ``data``: time, ``qpos``, ``qvel`` (and mocap).

        Equal keys mean the same physics state (the readers memoize on it, e.g. the closed loop's truth).
        """
        d = self.data
        if self._has_mocap:
            return (d.time, d.qpos.tobytes(), d.qvel.tobytes(), d.mocap_pos.tobytes(), d.mocap_quat.tobytes())
        return (d.time, self._qpos.tobytes(), self._qvel.tobytes())

    def model_changed(self) -> None:
        """Call after editing the model's parameters (masses, inertias...): the next step starts afresh.

        :meth:`step_checked` reuses the previous step's ``mj_forward`` for the position stage when the state
        (time, ``qpos``, ``qvel``, mocap poses) is unchanged; an edited model invalidates it, which the state
        cannot show.
        """
        self._forward_key = None

    # ------------------------------------------------------------------ kinematic driving

    def set_pose(
        self,
        R_WB: np.ndarray,
        p_WB: np.ndarray,
        v_WB: np.ndarray | None = None,
        omega_B: np.ndarray | None = None,
        a_W: np.ndarray | None = None,
    ) -> None:
        """Place the vehicle kinematically, then ``mj_forward``.

        Args:
            R_WB: Orientation, shape (3, 3).
            p_WB: Position of B in W (m), shape (3,).
            v_WB: Velocity of B in W (m/s), shape (3,); zero when None.
            omega_B: Angular rate of B w.r.t. W, in B (rad/s), shape (3,); zero when None.
            a_W: Headset only: acceleration of B in W (m/s^2), shape (3,), reported by
                :meth:`specific_force_B`; zero when None. The quadrotor's acceleration comes from its
                dynamics, so passing it there is an error.

        Raises:
            ValueError: Bad shapes, non-finite values, ``R_WB`` not a rotation, or ``a_W`` for the quadrotor.
        """
        R_WB = _check_rotation(R_WB, "R_WB")
        p_WB = _check_vector(p_WB, "p_WB")
        v_WB = np.zeros(3) if v_WB is None else _check_vector(v_WB, "v_WB")
        omega_B = np.zeros(3) if omega_B is None else _check_vector(omega_B, "omega_B")
        quat_wxyz = rotmat_to_quat_wxyz(R_WB)
        if self._is_mocap:
            self.data.mocap_pos[self._mocap_id] = p_WB
            self.data.mocap_quat[self._mocap_id] = quat_wxyz
            self._kin_v_W[:] = v_WB
            self._kin_omega_B[:] = omega_B
            self._kin_a_W[:] = np.zeros(3) if a_W is None else _check_vector(a_W, "a_W")
        else:
            if a_W is not None:
                raise ValueError("a_W is only for the headset; the quadrotor's acceleration comes from ctrl")
            # MuJoCo free joint: qpos = (p_W, quat_wxyz), qvel = (v_W, omega_B).
            self.data.qpos[self._qpos_adr : self._qpos_adr + 3] = p_WB
            self.data.qpos[self._qpos_adr + 3 : self._qpos_adr + 7] = quat_wxyz
            self.data.qvel[self._qvel_adr : self._qvel_adr + 3] = v_WB
            self.data.qvel[self._qvel_adr + 3 : self._qvel_adr + 6] = omega_B
        mujoco.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------ truth readers

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Pose of B (= IMU frame) in W from the ``imu_quat``/``imu_pos`` sensors.

        Returns:
            ``(R_WB (3, 3), p_WB (3,) m)``.
        """
        return quat_wxyz_to_rotmat(self._quat_view), self._pos_view.copy()

    def body_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(*pose(), velocity_W(), angular_velocity_B())`` as read-only views of one buffer.

        The same values as the four readers (the truth of a control tick), packed by one array call.

        Returns:
            ``(R_WB (3, 3), p_WB (3,) m, v_WB (3,) m/s, omega_B (3,) rad/s)``, read-only.
        """
        if self._is_mocap:
            R_WB, p_WB = self.pose()
            out = (R_WB, p_WB, self.velocity_W(), self.angular_velocity_B())
            for arr in out:
                arr.setflags(write=False)
            return out
        a = self._qvel_adr
        buf = np.array(
            quat_wxyz_to_rotmat_rows(self._quat_view)
            + self._pos_view.tolist()
            + self._qvel[a : a + 3].tolist()
            + self._gyro_view.tolist()
        )
        buf.setflags(write=False)  # before the views: a view of a writable buffer would stay writable
        return buf[:9].reshape(3, 3), buf[9:12], buf[12:15], buf[15:18]

    def velocity_W(self) -> np.ndarray:
        """Velocity of B's origin in W (m/s), shape (3,)."""
        if self._is_mocap:
            return self._kin_v_W.copy()
        return self._qvel[self._qvel_adr : self._qvel_adr + 3].copy()

    def angular_velocity_B(self) -> np.ndarray:
        """Angular rate of B w.r.t. W, in B (rad/s), shape (3,) (the noiseless gyro)."""
        if self._is_mocap:
            return self._kin_omega_B.copy()
        return self._gyro_view.copy()

    def specific_force_B(self) -> np.ndarray:
        """Specific force ``R_WB^T (a_W - g_W)`` at the IMU, in B (m/s^2), shape (3,) (noiseless accel).

        Quadrotor: MuJoCo's accelerometer at the ``imu`` site (accelerations from the dynamics under the
        current ``ctrl``). Headset: computed from the ``a_W`` given to :meth:`set_pose`.
        """
        if self._is_mocap:
            R_WB, _ = self.pose()
            return R_WB.T @ (self._kin_a_W - gravity_W())
        return self._accel_view.copy()

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Pose of the onboard camera in W, OpenCV convention (x right, y down, z forward).

        Returns:
            ``(R_WC (3, 3), p_WC (3,) m)``.
        """
        return camera_world_pose(self.data, self._cam_id)

    def set_body_force_W(self, fx_N: float, fy_N: float, fz_N: float) -> None:
        """Hold an external force (N, world frame, at the body's centre of mass) on the vehicle's root body.

        MuJoCo's ``xfrc_applied[body, :3]`` (the torque part is left as it is), written entry by entry.
        """
        f = self._xfrc_body
        f[0], f[1], f[2] = fx_N, fy_N, fz_N

    def in_collision(self) -> bool:
        """True when any active contact involves a geom of the vehicle.

        MuJoCo does not collide mocap bodies with the static world, so the headset never reports contact.
        """
        d = self.data
        if d.ncon == 0:
            return False  # in flight: no contact list to read
        contacts = d.contact
        mine = self._vehicle_geoms
        return any(g in mine for g in contacts.geom1.tolist()) or any(
            g in mine for g in contacts.geom2.tolist()
        )

    def motor_thrusts_N(self) -> np.ndarray:
        """Thrust of each motor (N), shape (4,) for the quadrotor (after ctrlrange clipping); (0,) headset."""
        return self.data.actuator_force[self._motor_ids].copy()
