"""Scene landmarks and their projection (simulated-feature mode)."""

import cv2
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.envs.sim.landmarks import project_landmarks, scene_landmarks
from viotb.envs.sim.simulation import Simulation
from viotb.models import load_model
from viotb.models.constants import ROOM_WALL_GEOMS
from viotb.vio.camera import PinholeCamera

EUROC_CAM0 = PinholeCamera(
    752, 480, 458.654, 457.296, 367.215, 248.375, (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
)


@pytest.fixture(scope="module")
def room():
    return Simulation("quadrotor", "textured_room")


def _distance_to_box_surface(model, data, geom_id, points):
    """Distance of points to the surface of a box geom (m)."""
    R = data.geom_xmat[geom_id].reshape(3, 3)
    local = np.abs((points - data.geom_xpos[geom_id]) @ R) - model.geom_size[geom_id]
    outside = np.linalg.norm(np.maximum(local, 0.0), axis=1)
    inside = np.minimum(local.max(axis=1), 0.0)
    return outside - inside


def test_landmarks_lie_on_room_surfaces(room):
    points = scene_landmarks(room.model, np.random.default_rng(0), count=2000)
    assert points.shape == (2000, 3)
    data = room.data
    on_surface = np.zeros(len(points), dtype=bool)
    for g in range(room.model.ngeom):
        if room.model.geom_bodyid[g] != 0:
            continue
        if room.model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            local = (points - data.geom_xpos[g]) @ data.geom_xmat[g].reshape(3, 3)
            on_surface |= np.abs(local[:, 2]) < 1e-9
        else:
            on_surface |= np.abs(_distance_to_box_surface(room.model, data, g, points)) < 1e-9
    assert on_surface.all()
    # Inside the room (closed bounds of the 10 x 10 x 4 m interior).
    assert np.all(np.abs(points[:, :2]) <= 5.0 + 1e-9)
    assert np.all((points[:, 2] >= -1e-9) & (points[:, 2] <= 4.0 + 1e-9))
    # Area-proportional: floor 100 m^2 of about 300 m^2 visible area -> about a third on the floor.
    floor_share = np.mean(np.abs(points[:, 2]) < 1e-9)
    assert 0.25 < floor_share < 0.40


def test_no_landmarks_hidden_inside_solids(room):
    points = scene_landmarks(room.model, np.random.default_rng(1), count=3000)
    # Nothing under crates (bottom faces) and nothing on the wall behind a poster.
    crate = mujoco.mj_name2id(room.model, mujoco.mjtObj.mjOBJ_GEOM, "crate_1")
    pos, size = room.data.geom_xpos[crate], room.model.geom_size[crate]
    under = (np.abs(points[:, 0] - pos[0]) < size[0]) & (np.abs(points[:, 1] - pos[1]) < size[1])
    assert not np.any(under & (points[:, 2] < 1e-6))
    poster = mujoco.mj_name2id(room.model, mujoco.mjtObj.mjOBJ_GEOM, "poster_north")
    pos, size = room.data.geom_xpos[poster], room.model.geom_size[poster]
    behind = (np.abs(points[:, 0] - pos[0]) < size[0]) & (np.abs(points[:, 2] - pos[2]) < size[2])
    assert not np.any(behind & (points[:, 1] > 5.0 - 1e-9))


def test_blank_wall_walls_have_no_landmarks():
    model = load_model("quadrotor", "blank_wall")
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    points = scene_landmarks(model, np.random.default_rng(0), count=1000)
    for name in ROOM_WALL_GEOMS:
        g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
        local = (points - data.geom_xpos[g]) @ data.geom_xmat[g].reshape(3, 3)
        assert not np.any(np.abs(local[:, 2]) < 1e-6), name
    assert np.all(points[:, 2] < 4.0 - 1e-6)  # no ceiling either


def test_landmarks_are_seeded_and_empty_scene_raises():
    model = load_model("quadrotor", "pillars")
    a = scene_landmarks(model, np.random.default_rng(3), count=500)
    b = scene_landmarks(model, np.random.default_rng(3), count=500)
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="no textured"):
        scene_landmarks(load_model("quadrotor", "empty"), np.random.default_rng(0))
    with pytest.raises(ValueError, match="count must be positive"):
        scene_landmarks(model, np.random.default_rng(0), count=0)


def test_projection_matches_opencv_project_points():
    rng = np.random.default_rng(0)
    R_WC = Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix()
    p_WC = np.array([0.2, -0.1, 1.0])
    n = 400
    points_C = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-1, 8, n)])
    points_W = points_C @ R_WC.T + p_WC
    obs = project_landmarks(points_W, R_WC, p_WC, EUROC_CAM0, rng, pixel_sigma_px=0.0)
    assert len(obs.ids) > 50 and obs.ids.dtype == np.int64
    assert np.all(points_C[obs.ids, 2] > 0)
    rvec, _ = cv2.Rodrigues(R_WC.T)
    tvec = -R_WC.T @ p_WC
    dist = np.array([*EUROC_CAM0.distortion, 0.0])
    expected, _ = cv2.projectPoints(points_W[obs.ids], rvec, tvec, EUROC_CAM0.K, dist)
    np.testing.assert_allclose(obs.uv_px, expected[:, 0, :], atol=1e-6)
    # Every point in front whose projection is well inside the image is reported.
    front = points_C[:, 2] > 0
    uv_all, _ = cv2.projectPoints(points_W[front], rvec, tvec, EUROC_CAM0.K, dist)
    xy = points_C[front, :2] / points_C[front, 2:]
    sane = np.all(np.abs(xy) < 0.8, axis=1)
    inside = EUROC_CAM0.in_image(uv_all[:, 0, :], border_px=1.0) & sane
    assert set(np.flatnonzero(front)[inside]) <= set(obs.ids)


def test_projection_noise_is_gaussian_and_seeded():
    rng = np.random.default_rng(0)
    camera = PinholeCamera.from_fovy(640, 480, 90.0)
    points_W = np.column_stack([rng.uniform(-2, 2, 4000), rng.uniform(-1.5, 1.5, 4000), np.full(4000, 3.0)])
    clean = project_landmarks(points_W, np.eye(3), np.zeros(3), camera, rng, pixel_sigma_px=0.0)
    noisy = project_landmarks(points_W, np.eye(3), np.zeros(3), camera, np.random.default_rng(5), 0.5)
    again = project_landmarks(points_W, np.eye(3), np.zeros(3), camera, np.random.default_rng(5), 0.5)
    np.testing.assert_array_equal(noisy.uv_px, again.uv_px)
    common, i_clean, i_noisy = np.intersect1d(clean.ids, noisy.ids, return_indices=True)
    residual = noisy.uv_px[i_noisy] - clean.uv_px[i_clean]
    assert len(common) > 2000
    assert residual.std(axis=0) == pytest.approx([0.5, 0.5], rel=0.05)
    assert np.all(camera.in_image(noisy.uv_px))


def test_depth_limit_and_points_behind():
    camera = PinholeCamera.from_fovy(320, 240, 90.0)
    points_W = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 25.0], [0.0, 0.0, -5.0], [0.1, 0.1, 0.0]])
    obs = project_landmarks(points_W, np.eye(3), np.zeros(3), camera, np.random.default_rng(0), 0.0)
    np.testing.assert_array_equal(obs.ids, [0])
    np.testing.assert_allclose(obs.uv_px, [[159.5, 119.5]], atol=1e-12)
    with pytest.raises(ValueError, match="landmarks_W must have shape"):
        project_landmarks(points_W[:, :2], np.eye(3), np.zeros(3), camera, np.random.default_rng(0))
    with pytest.raises(ValueError, match="both model and data"):
        project_landmarks(points_W, np.eye(3), np.zeros(3), camera, np.random.default_rng(0), model=object())


def test_occlusion_by_crate(room):
    # Camera 1.5 m in front of crate_0 (centre (3, 2.5, 0.4), half size 0.4) looking +x at it.
    R_WB = Rotation.from_euler("ZY", [0.0, -25.0], degrees=True).as_matrix()
    room.set_pose(R_WB, np.array([1.0, 2.5, 0.4]))
    R_WC, p_WC = room.camera_pose()
    behind = np.array([[5.0, 2.5, 0.4], [5.0, 2.6, 0.5]])  # east wall, hidden by the crate
    front = np.array([[2.6, 2.5, 0.4], [2.6, 2.4, 0.3]])  # crate's west face, visible
    points = np.vstack([behind, front])
    camera = PinholeCamera.from_fovy(320, 240, 90.0)
    free = project_landmarks(points, R_WC, p_WC, camera, np.random.default_rng(0), 0.0)
    np.testing.assert_array_equal(free.ids, [0, 1, 2, 3])
    occluded = project_landmarks(
        points, R_WC, p_WC, camera, np.random.default_rng(0), 0.0, model=room.model, data=room.data
    )
    np.testing.assert_array_equal(occluded.ids, [2, 3])


def test_sampled_landmarks_are_seen_from_the_centre(room):
    room.reset("hover")
    points = scene_landmarks(room.model, np.random.default_rng(0), count=3000)
    camera = PinholeCamera.from_fovy(320, 240, 90.0)
    R_WC, p_WC = room.camera_pose()
    rng = np.random.default_rng(0)
    obs = project_landmarks(points, R_WC, p_WC, camera, rng, model=room.model, data=room.data)
    assert len(obs.ids) >= 100
