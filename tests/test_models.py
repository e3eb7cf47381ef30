"""Models: every scene x vehicle compiles, names, dimensions, keyframes, hover, visual settings."""

import itertools
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
from viotb.models import compose_xml, load_model
from viotb.models.constants import (
    ACCEL_SENSOR,
    CAMERA_SITE,
    CHASE_CAMERA,
    COMMON_XMLS,
    DEFAULT_KEYFRAMES,
    GYRO_SENSOR,
    HOVER_KEYFRAME,
    IMU_POS_SENSOR,
    IMU_QUAT_SENSOR,
    IMU_SITE,
    MODELS_DIR,
    ONBOARD_CAMERA,
    QUAD_BODY,
    QUAD_FREEJOINT,
    QUAD_MASS_KG,
    QUAD_MOTORS,
    QUAD_ROTOR_SITES,
    SCENE_XMLS,
    VEHICLE_BODIES,
    VEHICLE_XMLS,
)
from viotb.vio.types import GRAVITY_M_S2

COMBOS = list(itertools.product(sorted(VEHICLE_XMLS), sorted(SCENE_XMLS)))

_NAMED = [
    (mujoco.mjtObj.mjOBJ_BODY, "nbody"),
    (mujoco.mjtObj.mjOBJ_GEOM, "ngeom"),
    (mujoco.mjtObj.mjOBJ_SITE, "nsite"),
    (mujoco.mjtObj.mjOBJ_CAMERA, "ncam"),
    (mujoco.mjtObj.mjOBJ_SENSOR, "nsensor"),
    (mujoco.mjtObj.mjOBJ_ACTUATOR, "nu"),
    (mujoco.mjtObj.mjOBJ_JOINT, "njnt"),
    (mujoco.mjtObj.mjOBJ_LIGHT, "nlight"),
    (mujoco.mjtObj.mjOBJ_MATERIAL, "nmat"),
    (mujoco.mjtObj.mjOBJ_TEXTURE, "ntex"),
    (mujoco.mjtObj.mjOBJ_KEY, "nkey"),
]


@pytest.fixture(scope="module", params=COMBOS, ids=[f"{v}-{s}" for v, s in COMBOS])
def model(request):
    return load_model(*request.param)


def test_every_file_is_listed_and_exists():
    listed = set(SCENE_XMLS.values()) | set(VEHICLE_XMLS.values()) | set(COMMON_XMLS)
    on_disk = {str(p.relative_to(MODELS_DIR)) for p in MODELS_DIR.rglob("*.xml")}
    assert listed == on_disk


def test_unknown_names_raise_clear_errors():
    with pytest.raises(ValueError, match="unknown scene 'nope'.*textured_room"):
        compose_xml("quadrotor", "nope")
    with pytest.raises(ValueError, match="unknown vehicle 'car'.*headset"):
        load_model("car", "empty")


def test_components_have_names(model):
    # dm_control suite_test.test_components_have_names; the world body (id 0) is named "world".
    for obj, count_attr in _NAMED:
        for i in range(getattr(model, count_attr)):
            assert mujoco.mj_id2name(model, obj, i), f"unnamed {obj.name} #{i} in {model.names[:40]!r}"


def test_names_used_by_code_exist(model):
    vehicle = "headset" if model.nmocap else "quadrotor"
    for obj, name in [
        (mujoco.mjtObj.mjOBJ_BODY, VEHICLE_BODIES[vehicle]),
        (mujoco.mjtObj.mjOBJ_SITE, IMU_SITE),
        (mujoco.mjtObj.mjOBJ_SITE, CAMERA_SITE),
        (mujoco.mjtObj.mjOBJ_CAMERA, ONBOARD_CAMERA),
        (mujoco.mjtObj.mjOBJ_CAMERA, CHASE_CAMERA),
        (mujoco.mjtObj.mjOBJ_KEY, DEFAULT_KEYFRAMES[vehicle]),
    ]:
        assert mujoco.mj_name2id(model, obj, name) >= 0, f"{name} missing"
    if vehicle == "quadrotor":
        for name in QUAD_MOTORS:
            assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, name) >= 0
        for name in QUAD_ROTOR_SITES:
            assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name) >= 0
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, QUAD_FREEJOINT) >= 0


def test_object_counts_and_sensor_dims(model):
    vehicle = "headset" if model.nmocap else "quadrotor"
    expected = {"quadrotor": (7, 6, 4, 0), "headset": (0, 0, 0, 1)}[vehicle]
    assert (model.nq, model.nv, model.nu, model.nmocap) == expected
    assert model.nbody == 2  # world + vehicle: scenes add geometry to the world body only
    dims = {GYRO_SENSOR: 3, ACCEL_SENSOR: 3, IMU_POS_SENSOR: 3, IMU_QUAT_SENSOR: 4}
    for name, dim in dims.items():
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
        assert model.sensor_dim[sid] == dim
        assert model.sensor_objtype[sid] == mujoco.mjtObj.mjOBJ_SITE
        assert mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE, model.sensor_objid[sid]) == IMU_SITE


def test_imu_site_is_body_frame(model):
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, IMU_SITE)
    np.testing.assert_allclose(model.site_pos[site], 0.0, atol=0)
    np.testing.assert_allclose(model.site_quat[site], [1, 0, 0, 0], atol=0)


def test_camera_site_matches_camera(model):
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, CAMERA_SITE)
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, ONBOARD_CAMERA)
    np.testing.assert_allclose(model.site_pos[site], model.cam_pos[cam], atol=1e-12)
    np.testing.assert_allclose(model.site_quat[site], model.cam_quat[cam], atol=1e-12)


def test_visual_settings(model):
    assert (model.vis.global_.offwidth, model.vis.global_.offheight) == (752, 480)
    assert model.vis.quality.shadowsize <= 1024
    assert not np.any(model.light_castshadow), "shadows must be off by default"


def test_quadrotor_mass_matches_constant():
    model = load_model("quadrotor", "empty")
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, QUAD_BODY)
    assert model.body_mass[body] == pytest.approx(QUAD_MASS_KG, abs=1e-12)
    np.testing.assert_allclose(model.body_inertia[body], [0.0123, 0.0123, 0.0224], atol=1e-12)


def test_chase_camera_tracks_com_and_looks_at_drone():
    model = load_model("quadrotor", "empty")
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, CHASE_CAMERA)
    assert model.cam_mode[cam] == mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    # MuJoCo cameras look along -z: the optical axis must point at the body within 1 deg.
    axis = -data.cam_xmat[cam].reshape(3, 3)[:, 2]
    to_body = data.xpos[1] - data.cam_xpos[cam]
    cos = axis @ to_body / np.linalg.norm(to_body)
    assert cos > np.cos(np.deg2rad(1.0))
    assert data.cam_xpos[cam, 2] > data.xpos[1, 2] and data.cam_xpos[cam, 0] < data.xpos[1, 0]


@pytest.mark.parametrize("scene", sorted(SCENE_XMLS))
def test_hover_keyframe_holds(scene):
    model = load_model("quadrotor", scene)
    data = mujoco.MjData(model)
    key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, HOVER_KEYFRAME)
    mujoco.mj_resetDataKeyframe(model, data, key)
    # The keyframe thrust is m g / 4 per motor (closed form, from the MJCF mass).
    np.testing.assert_allclose(data.ctrl, QUAD_MASS_KG * GRAVITY_M_S2 / 4, rtol=1e-12)
    p0 = data.qpos[:3].copy()
    n_steps = round(1.0 / model.opt.timestep)
    for _ in range(n_steps):
        mujoco.mj_step(model, data)
    assert np.linalg.norm(data.qpos[:3] - p0) < 1e-3
    assert data.ncon == 0


def test_scene_files_have_no_joints_or_bodies():
    for file in SCENE_XMLS.values():
        root = ET.parse(MODELS_DIR / file).getroot()
        assert not root.findall(".//joint") and not root.findall(".//freejoint"), file
        assert not root.findall(".//body"), file
