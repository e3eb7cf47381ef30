"""Simulation wrapper: named truth readers against MuJoCo internals and closed forms."""

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.envs.sim.simulation import Simulation, sensor_data, sensor_slice
from viotb.models.constants import ACCEL_SENSOR, GYRO_SENSOR, HOME_KEYFRAME, HOVER_KEYFRAME
from viotb.vio.types import GRAVITY_M_S2, gravity_W


@pytest.fixture(scope="module")
def quad():
    return Simulation("quadrotor", "textured_room")


@pytest.fixture(scope="module")
def head():
    return Simulation("headset", "textured_room")


def test_sensor_helpers(quad):
    quad.reset(HOVER_KEYFRAME)
    sl = sensor_slice(quad.model, ACCEL_SENSOR)
    assert sl.stop - sl.start == 3
    np.testing.assert_array_equal(sensor_data(quad.model, quad.data, ACCEL_SENSOR), quad.data.sensordata[sl])
    with pytest.raises(ValueError, match="sensor 'nope' not in model.*gyro"):
        sensor_slice(quad.model, "nope")


def test_level_and_still_reads_plus_g(quad):
    quad.reset(HOVER_KEYFRAME)
    np.testing.assert_allclose(quad.specific_force_B(), [0, 0, GRAVITY_M_S2], atol=1e-9)
    np.testing.assert_allclose(quad.angular_velocity_B(), 0.0, atol=1e-12)
    np.testing.assert_allclose(quad.motor_thrusts_N(), 1.2 * GRAVITY_M_S2 / 4, rtol=1e-12)
    R_WB, p_WB = quad.pose()
    np.testing.assert_allclose(R_WB, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(p_WB, [0, 0, 1], atol=1e-12)


def test_hover_holds_one_second(quad):
    quad.reset(HOVER_KEYFRAME)
    p0 = quad.pose()[1]
    quad.step(n_steps=round(1.0 / quad.timestep_s))
    assert quad.time_s == pytest.approx(1.0, abs=1e-9)
    assert np.linalg.norm(quad.pose()[1] - p0) < 1e-3
    assert not quad.in_collision()


def test_free_fall_closed_form(quad):
    quad.reset(HOVER_KEYFRAME)
    quad.set_pose(np.eye(3), np.array([0.0, 0.0, 3.0]))
    quad.step(ctrl=np.zeros(4), n_steps=100)
    t = quad.time_s
    # Semi-implicit Euler: v_n = -g n h exactly; z_n = z0 - g h^2 n (n + 1) / 2.
    h, n = quad.timestep_s, 100
    np.testing.assert_allclose(quad.velocity_W(), [0, 0, -GRAVITY_M_S2 * t], atol=1e-9)
    z_expected = 3.0 - GRAVITY_M_S2 * h * h * n * (n + 1) / 2
    np.testing.assert_allclose(quad.pose()[1], [0, 0, z_expected], atol=1e-9)
    # Free fall: the accelerometer reads zero specific force.
    np.testing.assert_allclose(quad.specific_force_B(), 0.0, atol=1e-9)


def test_set_pose_and_readers_tilted_and_spinning(quad):
    rng = np.random.default_rng(0)
    rot = Rotation.from_rotvec(rng.normal(size=3) * 0.5)
    R_WB = rot.as_matrix()
    p_WB = np.array([0.5, -0.3, 1.7])
    v_WB = np.array([0.2, 0.1, -0.3])
    omega_B = np.array([0.3, -0.2, 0.5])
    quad.reset(HOVER_KEYFRAME)
    quad.set_pose(R_WB, p_WB, v_WB, omega_B)
    R, p = quad.pose()
    np.testing.assert_allclose(R, R_WB, atol=1e-12)
    np.testing.assert_allclose(p, p_WB, atol=1e-12)
    np.testing.assert_allclose(quad.velocity_W(), v_WB, atol=1e-12)
    np.testing.assert_allclose(quad.angular_velocity_B(), omega_B, atol=1e-12)
    np.testing.assert_allclose(sensor_data(quad.model, quad.data, GYRO_SENSOR), omega_B, atol=1e-12)
    # Specific force at the COM = R^T (a - g); total thrust along z_B gives a = R e3 T / m + g.
    thrust = quad.motor_thrusts_N().sum()
    a_W = R_WB[:, 2] * thrust / 1.2 + gravity_W()
    np.testing.assert_allclose(quad.specific_force_B(), R_WB.T @ (a_W - gravity_W()), atol=1e-9)
    # Body position and orientation also agree with MuJoCo's own kinematics.
    np.testing.assert_allclose(quad.data.xmat[1].reshape(3, 3), R_WB, atol=1e-12)


def test_camera_pose_is_opencv(quad):
    quad.reset(HOVER_KEYFRAME)
    R_WC, p_WC = quad.camera_pose()
    # Level quadrotor, camera pitched 25 deg down, 7 cm ahead: optical axis z_C = (cos 25, 0, -sin 25),
    # image x = -y_W (right when looking along +x), image y = z_C x x_C (down-ish).
    c, s = np.cos(np.deg2rad(25)), np.sin(np.deg2rad(25))
    np.testing.assert_allclose(R_WC[:, 2], [c, 0, -s], atol=1e-4)
    np.testing.assert_allclose(R_WC[:, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(R_WC[:, 1], np.cross(R_WC[:, 2], R_WC[:, 0]), atol=1e-12)
    np.testing.assert_allclose(p_WC, [0.07, 0, 1.0], atol=1e-12)


def test_collision_with_wall_and_floor(quad):
    quad.reset(HOVER_KEYFRAME)
    assert not quad.in_collision()
    quad.set_pose(np.eye(3), np.array([4.95, 0.0, 1.5]))
    assert quad.in_collision()
    quad.set_pose(np.eye(3), np.array([0.0, 0.0, 0.02]))
    assert quad.in_collision()


def test_headset_kinematic_readers(head):
    head.reset(HOME_KEYFRAME)
    R_WB, p_WB = head.pose()
    np.testing.assert_allclose(p_WB, [0, 0, 1.6], atol=1e-12)
    np.testing.assert_allclose(head.specific_force_B(), [0, 0, GRAVITY_M_S2], atol=1e-12)
    rot = Rotation.from_euler("zyx", [40, -10, 5], degrees=True).as_matrix()
    v, w, a = np.array([0.5, 0, 0]), np.array([0, 0, 1.0]), np.array([0.1, 0.2, 0.3])
    head.set_pose(rot, np.array([1.0, 2.0, 1.5]), v, w, a_W=a)
    R, p = head.pose()
    np.testing.assert_allclose(R, rot, atol=1e-12)
    np.testing.assert_allclose(p, [1.0, 2.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(head.velocity_W(), v, atol=0)
    np.testing.assert_allclose(head.angular_velocity_B(), w, atol=0)
    np.testing.assert_allclose(head.specific_force_B(), rot.T @ (a - gravity_W()), atol=1e-12)
    # Forward camera: optical axis along x_B.
    np.testing.assert_allclose(head.camera_pose()[0][:, 2], rot[:, 0], atol=1e-12)
    assert head.motor_thrusts_N().shape == (0,)
    head.step(n_steps=3)  # stepping a mocap rig keeps its pose
    np.testing.assert_allclose(head.pose()[1], [1.0, 2.0, 1.5], atol=1e-12)


def test_bad_inputs_raise_clear_errors(quad):
    with pytest.raises(ValueError, match="unknown scene"):
        Simulation("quadrotor", "moon")
    with pytest.raises(ValueError, match="keyframe 'nope'.*hover"):
        quad.reset("nope")
    with pytest.raises(ValueError, match="ctrl must be"):
        quad.step(ctrl=np.zeros(3))
    with pytest.raises(ValueError, match="n_steps"):
        quad.step(n_steps=0)
    with pytest.raises(ValueError, match="R_WB is not a rotation"):
        quad.set_pose(2 * np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="p_WB must be"):
        quad.set_pose(np.eye(3), np.zeros(2))
    with pytest.raises(ValueError, match="a_W is only for the headset"):
        quad.set_pose(np.eye(3), np.zeros(3), a_W=np.zeros(3))


def test_reset_none_restores_model_defaults(quad):
    quad.set_pose(np.eye(3), np.array([1.0, 1.0, 1.0]))
    quad.reset()
    np.testing.assert_allclose(quad.data.qpos, quad.model.qpos0, atol=0)
    assert quad.time_s == 0.0
    assert mujoco.mj_name2id(quad.model, mujoco.mjtObj.mjOBJ_KEY, HOVER_KEYFRAME) == 0
