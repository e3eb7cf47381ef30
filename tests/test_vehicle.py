"""Tests of viotb.controllers.vehicle and viotb.envs.sim.vehicle (parameters and truth from the MJCF)."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.controllers.vehicle import VehicleParams
from viotb.envs.sim.vehicle import nav_state_from_data, vehicle_params_from_model
from viotb.models import load_model
from viotb.models.constants import (
    GYRO_SENSOR,
    MODELS_DIR,
    QUAD_BODY,
    QUAD_MOTORS,
    QUAD_ROTOR_SITES,
    QUADROTOR_XML,
)


def _floats(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split()])


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return load_model("quadrotor", "empty")


@pytest.fixture(scope="module")
def xml_root() -> ET.Element:
    """The quadrotor MJCF parsed as plain XML: an oracle independent of MuJoCo's compiler."""
    return ET.parse(MODELS_DIR / QUADROTOR_XML).getroot()


def test_reads_mass_and_inertia_from_xml(model: mujoco.MjModel, xml_root: ET.Element) -> None:
    params = vehicle_params_from_model(model)
    inertial = xml_root.find(f".//body[@name='{QUAD_BODY}']/inertial")
    assert inertial is not None
    assert params.mass_kg == pytest.approx(1.2, abs=1e-12)
    assert params.mass_kg == pytest.approx(float(inertial.get("mass")), abs=1e-12)
    np.testing.assert_allclose(
        params.inertia_kg_m2, np.diag(_floats(inertial.get("diaginertia"))), atol=1e-12
    )
    assert params.gravity_m_s2 == pytest.approx(9.81, abs=1e-12)
    assert params.hover_thrust_N == pytest.approx(1.2 * 9.81, abs=1e-12)


def test_reads_rotors_gear_and_limits_from_xml(model: mujoco.MjModel, xml_root: ET.Element) -> None:
    params = vehicle_params_from_model(model)
    rotor_class = xml_root.find(".//default[@class='rotor']/motor")
    assert rotor_class is not None
    ctrlrange = _floats(rotor_class.get("ctrlrange"))
    for i, (motor, site) in enumerate(zip(QUAD_MOTORS, QUAD_ROTOR_SITES, strict=True)):
        site_el = xml_root.find(f".//site[@name='{site}']")
        motor_el = xml_root.find(f".//motor[@name='{motor}']")
        assert site_el is not None and motor_el is not None
        gear = _floats(motor_el.get("gear"))
        np.testing.assert_allclose(params.rotor_positions_B_m[i], _floats(site_el.get("pos")), atol=1e-12)
        np.testing.assert_allclose(params.thrust_axes_B[i], gear[:3], atol=1e-12)
        assert params.yaw_moment_coeff_m[i] == pytest.approx(gear[5], abs=1e-12)
        assert params.min_thrust_N[i] == pytest.approx(ctrlrange[0], abs=1e-12)
        assert params.max_thrust_N[i] == pytest.approx(ctrlrange[1], abs=1e-12)
    # Spin directions alternate so that yaw moments cancel at equal thrusts.
    assert np.sum(params.yaw_moment_coeff_m) == pytest.approx(0.0, abs=1e-15)


def test_hover_keyframe_ctrl_is_mg_over_4(model: mujoco.MjModel) -> None:
    params = vehicle_params_from_model(model)
    np.testing.assert_allclose(model.key_ctrl[0], params.hover_thrust_N / 4, atol=1e-3)


def test_nav_state_matches_mujoco_readers(model: mujoco.MjModel) -> None:
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    rot = Rotation.random(random_state=1)
    quat_xyzw = rot.as_quat()
    data.qpos[:3] = rng.normal(size=3)
    data.qpos[3:7] = np.roll(quat_xyzw, 1)
    data.qvel[:] = rng.normal(size=6)
    mujoco.mj_forward(model, data)
    state = nav_state_from_data(model, data)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, QUAD_BODY)
    np.testing.assert_allclose(state.R_WB, rot.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(state.R_WB, data.xmat[body].reshape(3, 3), atol=1e-12)
    np.testing.assert_allclose(state.p_WB, data.xpos[body], atol=1e-12)
    vel = np.zeros(6)  # (angular, linear), world-oriented, at the body origin
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, body, vel, 0)
    np.testing.assert_allclose(state.v_WB, vel[3:], atol=1e-12)
    np.testing.assert_allclose(state.R_WB @ state.omega_B, vel[:3], atol=1e-12)
    gyro = data.sensor(GYRO_SENSOR).data
    np.testing.assert_allclose(state.omega_B, gyro, atol=1e-12)


def test_vehicle_params_rejects_bad_values(model: mujoco.MjModel) -> None:
    good = vehicle_params_from_model(model)
    fields = {
        "mass_kg": good.mass_kg,
        "inertia_kg_m2": good.inertia_kg_m2,
        "rotor_positions_B_m": good.rotor_positions_B_m,
        "thrust_axes_B": good.thrust_axes_B,
        "yaw_moment_coeff_m": good.yaw_moment_coeff_m,
        "min_thrust_N": good.min_thrust_N,
        "max_thrust_N": good.max_thrust_N,
    }
    with pytest.raises(ValueError, match="mass_kg"):
        VehicleParams(**{**fields, "mass_kg": -1.0})
    with pytest.raises(ValueError, match="rotor_positions_B_m"):
        VehicleParams(**{**fields, "rotor_positions_B_m": np.zeros((3, 3))})
    with pytest.raises(ValueError, match="inertia_kg_m2"):
        VehicleParams(**{**fields, "inertia_kg_m2": -np.eye(3)})
    with pytest.raises(ValueError, match="thrust limits"):
        VehicleParams(**{**fields, "max_thrust_N": np.zeros(4)})
    with pytest.raises(ValueError, match="unit vectors"):
        VehicleParams(**{**fields, "thrust_axes_B": 2.0 * good.thrust_axes_B})


def test_arrays_are_read_only(model: mujoco.MjModel) -> None:
    params = vehicle_params_from_model(model)
    with pytest.raises(ValueError):
        params.inertia_kg_m2[0, 0] = 1.0


def test_missing_name_gives_clear_error() -> None:
    bare = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body name='x'><freejoint/><geom size='0.1'/></body></worldbody></mujoco>"
    )
    with pytest.raises(ValueError, match="quadrotor"):
        vehicle_params_from_model(bare)
