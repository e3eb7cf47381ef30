"""Stereo geometry: relative pose, triangulation vs closed form and OpenCV, KLT matching on rendered pairs."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.envs.sim.render import OffscreenRenderer, camera_calibration, rgb_to_gray
from viotb.envs.sim.simulation import Simulation
from viotb.models import compose_xml
from viotb.models.constants import (
    HEAD_BODY,
    HEADSET_CAMERA_FOVY_DEG,
    HEADSET_CAMERAS,
    HEADSET_STEREO_BASELINE_M,
    MODELS_DIR,
    ONBOARD_CAMERA,
)
from viotb.vio.camera import CameraCalibration, EquidistantCamera, PinholeCamera
from viotb.vio.lie import exp_so3
from viotb.vio.stereo import (
    StereoMatchParams,
    epipolar_angle_rad,
    match_stereo,
    relative_pose,
    triangulate_dlt,
    triangulate_midpoint,
)

WIDTH, HEIGHT = 640, 480


def _rig(camera):
    """Two cameras 10 cm apart along y_B, slightly toed out, looking along +x_B (headset layout)."""
    R_B_C = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # z_C = x_B, x_C = -y_B
    c0 = CameraCalibration(
        camera, R_B_C @ exp_so3(np.array([0.0, -0.05, 0.01])), np.array([0.085, 0.05, 0.0])
    )
    c1 = CameraCalibration(
        camera, R_B_C @ exp_so3(np.array([0.01, 0.05, 0.0])), np.array([0.085, -0.05, 0.002])
    )
    return c0, c1


def test_relative_pose_composes_the_extrinsics():
    c0, c1 = _rig(PinholeCamera.from_fovy(WIDTH, HEIGHT, 100.0))
    R, t = relative_pose(c0, c1)
    T_BC0, T_BC1 = np.eye(4), np.eye(4)
    T_BC0[:3, :3], T_BC0[:3, 3] = c0.R_BC, c0.p_BC
    T_BC1[:3, :3], T_BC1[:3, 3] = c1.R_BC, c1.p_BC
    T_C1C0 = np.linalg.inv(T_BC1) @ T_BC0
    np.testing.assert_allclose(R, T_C1C0[:3, :3], atol=1e-14)
    np.testing.assert_allclose(t, T_C1C0[:3, 3], atol=1e-14)
    assert np.linalg.norm(t) == pytest.approx(np.hypot(0.1, 0.002))


@pytest.mark.parametrize(
    "camera",
    [
        PinholeCamera.from_fovy(WIDTH, HEIGHT, 100.0),
        EquidistantCamera(WIDTH, HEIGHT, 275.0, 275.0, 319.5, 239.5, (-0.01, 0.004, -0.002, 0.0003)),
    ],
    ids=["pinhole", "equidistant"],
)
def test_triangulated_depth_matches_known_depth(camera):
    c0, c1 = _rig(camera)
    R, t = relative_pose(c0, c1)
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 8.0, 300)
    xy = rng.uniform(-0.8, 0.8, (300, 2))
    p_C0 = np.column_stack([xy * depth[:, None], depth])
    uv0, uv1 = camera.project(p_C0), camera.project(p_C0 @ R.T + t)
    b0, b1 = camera.unproject(uv0), camera.unproject(uv1)
    pts = triangulate_midpoint(b0, b1, R, t)
    assert pts.valid.all()
    np.testing.assert_allclose(pts.depth_m, depth, rtol=1e-9)
    np.testing.assert_allclose(epipolar_angle_rad(b0, b1, R, t), 0.0, atol=1e-12)
    xy0, xy1 = camera.undistort_points(uv0), camera.undistort_points(uv1)
    np.testing.assert_allclose(triangulate_dlt(xy0, xy1, R, t), p_C0, rtol=1e-8)
    # OpenCV as an independent oracle of the linear triangulation.
    X = cv2.triangulatePoints(
        np.hstack([np.eye(3), np.zeros((3, 1))]), np.hstack([R, t[:, None]]), xy0.T, xy1.T
    )
    np.testing.assert_allclose((X[:3] / X[3]).T, p_C0, rtol=1e-6)


def test_triangulation_rejects_parallel_and_diverging_rays():
    R, t = np.eye(3), np.array([-0.1, 0.0, 0.0])  # rectified pair, right camera at x = +0.1 m in C0
    b0 = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    # Parallel (at infinity); diverging (the rays meet 2 m *behind*, negative disparity); converging at 2 m.
    b1 = np.array([[0.0, 0.0, 1.0], [0.05, 0.0, 1.0], [-0.05, 0.0, 1.0]])
    pts = triangulate_midpoint(b0, b1 / np.linalg.norm(b1, axis=1, keepdims=True), R, t)
    np.testing.assert_array_equal(pts.valid, [False, False, True])
    assert pts.depth_m[2] == pytest.approx(2.0, rel=1e-12)


def test_headset_cameras_in_the_model():
    sim = Simulation("headset", "empty")
    c0 = camera_calibration(sim.model, HEADSET_CAMERAS[0], HEAD_BODY, WIDTH, HEIGHT)
    c1 = camera_calibration(sim.model, HEADSET_CAMERAS[1], HEAD_BODY, WIDTH, HEIGHT)
    onboard = camera_calibration(sim.model, ONBOARD_CAMERA, HEAD_BODY, WIDTH, HEIGHT)
    R, t = relative_pose(c0, c1)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)  # parallel, forward
    # C0 (left) sits at -x in the right camera's frame: P1 = [I | -b e_x] as in rectified stereo.
    np.testing.assert_allclose(t, [-HEADSET_STEREO_BASELINE_M, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(c0.R_BC[:, 2], [1.0, 0.0, 0.0], atol=1e-12)  # optical axis = +x_B
    np.testing.assert_allclose(c0.R_BC, onboard.R_BC, atol=1e-12)
    assert c0.camera.fy == pytest.approx(0.5 * HEIGHT / np.tan(np.deg2rad(HEADSET_CAMERA_FOVY_DEG / 2)))


# ---------------------------------------------------------------- rendered stereo pairs


def _gray(renderer, data, camera):
    return np.clip(np.rint(rgb_to_gray(renderer.render_rgb(data, camera=camera))), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def room():
    sim = Simulation("headset", "textured_room")
    calibs = [camera_calibration(sim.model, name, HEAD_BODY, WIDTH, HEIGHT) for name in HEADSET_CAMERAS]
    with OffscreenRenderer(sim.model, WIDTH, HEIGHT, camera=HEADSET_CAMERAS[0]) as renderer:
        yield sim, renderer, calibs


# (position (m), yaw (deg), pitch down (deg)): a crate 1-4 m away on the floor, and a wall ~1.9 m away.
VIEWS = {"crate": ([1.5, 2.0, 1.4], 20.0, 25.0), "north_wall": ([-1.0, 3.0, 1.7], 90.0, 0.0)}


@pytest.mark.parametrize("view", sorted(VIEWS))
def test_rendered_stereo_matches_triangulate_to_the_depth_buffer(room, view):
    sim, renderer, (c0, c1) = room
    pos, yaw, pitch = VIEWS[view]
    sim.set_pose(Rotation.from_euler("ZY", [yaw, pitch], degrees=True).as_matrix(), np.array(pos))
    left, right = renderer.render_gray(sim.data), _gray(renderer, sim.data, HEADSET_CAMERAS[1])
    depth = renderer.render_depth(sim.data)
    uv0 = cv2.goodFeaturesToTrack(left, 300, 0.01, 8, blockSize=5).reshape(-1, 2).astype(float)
    matches = match_stereo(left, right, uv0, c0, c1)
    assert matches.mask.mean() > 0.8
    # Compare where the depth buffer is smooth around the corner (not on an occluding edge).
    ij = np.rint(uv0).astype(int)
    win = np.stack(
        [
            depth[np.clip(ij[:, 1] + dv, 0, HEIGHT - 1), np.clip(ij[:, 0] + du, 0, WIDTH - 1)]
            for du in range(-3, 4)
            for dv in range(-3, 4)
        ]
    )
    truth = depth[ij[:, 1], ij[:, 0]]
    smooth = (win.max(axis=0) - win.min(axis=0)) < 0.05 * truth
    keep = matches.mask & smooth
    assert keep.sum() >= 150
    rel = np.abs(matches.depth_m[keep] - truth[keep]) / truth[keep]
    assert np.median(rel) < 0.01
    assert np.mean(rel < 0.05) > 0.97


def test_tracked_points_match_on_the_finest_level_as_on_the_full_pyramid(room):
    """Points with a prior depth match on pyramid level 0 as on the full pyramid from the same guess.

    The prior is last frame's depth (here the first match's, 5 % off): ``tracked_max_level``.
    """
    sim, renderer, (c0, c1) = room
    pos, yaw, pitch = VIEWS["crate"]
    sim.set_pose(Rotation.from_euler("ZY", [yaw, pitch], degrees=True).as_matrix(), np.array(pos))
    left, right = renderer.render_gray(sim.data), _gray(renderer, sim.data, HEADSET_CAMERAS[1])
    uv0 = cv2.goodFeaturesToTrack(left, 300, 0.01, 8, blockSize=5).reshape(-1, 2).astype(float)
    first = match_stereo(left, right, uv0, c0, c1)  # no prior: the full pyramid
    prior = np.where(first.mask, first.depth_m * 1.05, np.nan)
    fine = match_stereo(left, right, uv0, c0, c1, StereoMatchParams(tracked_max_level=0), prior)
    full = match_stereo(left, right, uv0, c0, c1, StereoMatchParams(tracked_max_level=None), prior)
    assert np.mean(fine.mask == full.mask) > 0.99
    both = fine.mask & full.mask
    assert both.sum() > 0.8 * len(uv0)
    assert np.percentile(np.linalg.norm(fine.uv1_px[both] - full.uv1_px[both], axis=1), 99) < 0.02
    # The points without a prior are matched as before.
    np.testing.assert_array_equal(fine.uv1_px[~first.mask], full.uv1_px[~first.mask])


def test_tracked_points_tracked_back_only_off_their_prediction_match_as_all_tracked_back(room):
    """``tracked_check_beyond_px``: a tracked point whose match lands near its prediction is not tracked back.

    The forward pass is the same, so every match is the same pixel, and skipping a test can only add
    matches. With a good prior (5 % off) it adds none here. With a prior 3x off, the backward pass refuses
    some matches that land within 1 px of the wrong prediction: a few per cent of the points are then
    accepted that the full check refuses (a prior that wrong does not come from the previous frame).
    """
    sim, renderer, (c0, c1) = room
    pos, yaw, pitch = VIEWS["crate"]
    sim.set_pose(Rotation.from_euler("ZY", [yaw, pitch], degrees=True).as_matrix(), np.array(pos))
    left, right = renderer.render_gray(sim.data), _gray(renderer, sim.data, HEADSET_CAMERAS[1])
    uv0 = cv2.goodFeaturesToTrack(left, 300, 0.01, 8, blockSize=5).reshape(-1, 2).astype(float)
    first = match_stereo(left, right, uv0, c0, c1)
    for scale, most_extra in ((1.05, 0), (3.0, 0.05 * len(uv0))):
        prior = np.where(first.mask, first.depth_m * scale, np.nan)
        out = {
            beyond: match_stereo(
                left, right, uv0, c0, c1, StereoMatchParams(tracked_check_beyond_px=beyond), prior
            )
            for beyond in (-1.0, 1.0)
        }
        np.testing.assert_array_equal(out[-1.0].uv1_px, out[1.0].uv1_px)
        assert np.all(out[1.0].mask >= out[-1.0].mask)
        assert (out[1.0].mask & ~out[-1.0].mask).sum() <= most_extra
    assert out[-1.0].mask.sum() > 0.7 * len(uv0)


def _marker_scene():
    """The headset in the textured room plus a small self-lit red sphere (``marker``) in the world."""
    include = {
        str(p.relative_to(MODELS_DIR)): p.read_bytes()
        for p in MODELS_DIR.rglob("*")
        if p.suffix in {".xml", ".png"}
    }
    spec = mujoco.MjSpec.from_string(compose_xml("headset", "textured_room"), include=include)
    spec.add_material(name="marker", rgba=[1.0, 0.0, 0.0, 1.0], emission=1.0)
    body = spec.worldbody.add_body(name="marker", mocap=True)
    body.add_geom(
        type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.03, 0.0, 0.0], contype=0, conaffinity=0, material="marker"
    )
    return spec.compile()


def _red_centroid(rgb):
    rgb = rgb.astype(float)
    # Pure self-lit red; the room's brown crate has G, B well above a quarter of R.
    redness = np.clip(rgb[:, :, 0] - 4.0 * np.maximum(rgb[:, :, 1], rgb[:, :, 2]), 0.0, None)
    v, u = np.nonzero(redness)
    w = redness[v, u]
    return np.array([u @ w, v @ w]) / w.sum(), len(u)


def test_rendered_marker_lands_on_both_projections():
    model = _marker_scene()
    data = mujoco.MjData(model)
    head = model.body_mocapid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, HEAD_BODY)]
    marker = model.body_mocapid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "marker")]
    calibs = [camera_calibration(model, name, HEAD_BODY, WIDTH, HEIGHT) for name in HEADSET_CAMERAS]
    R_WB = Rotation.from_euler("ZY", [30.0, 10.0], degrees=True).as_matrix()
    p_WB = np.array([0.5, -0.5, 1.6])
    data.mocap_pos[head], data.mocap_quat[head] = p_WB, Rotation.from_matrix(R_WB).as_quat(scalar_first=True)
    rng = np.random.default_rng(1)
    with OffscreenRenderer(model, WIDTH, HEIGHT, camera=HEADSET_CAMERAS[0]) as renderer:
        for _ in range(4):
            # A point 1-2.5 m ahead, up to ~27 deg off the axis (a 3 cm sphere: >= 2.4 px radius).
            p_B = np.array([rng.uniform(1.0, 2.5), 0.0, 0.0])
            p_B[1:] = p_B[0] * rng.uniform(-0.5, 0.5, 2)
            p_W = R_WB @ p_B + p_WB
            data.mocap_pos[marker] = p_W
            mujoco.mj_forward(model, data)
            uv_seen = []
            for name, calib in zip(HEADSET_CAMERAS, calibs, strict=True):
                p_C = calib.R_BC.T @ (p_B - calib.p_BC)
                uv_expected = calib.camera.project(p_C)[0]
                uv, n_px = _red_centroid(renderer.render_rgb(data, camera=name))
                assert n_px > 10
                np.testing.assert_allclose(uv, uv_expected, atol=0.3, err_msg=name)
                uv_seen.append(uv)
            # The two rendered centroids triangulate back to the marker.
            R, t = relative_pose(*calibs)
            b0, b1 = (c.camera.unproject(uv[None]) for c, uv in zip(calibs, uv_seen, strict=True))
            p_C0 = calibs[0].R_BC.T @ (p_B - calibs[0].p_BC)
            pts = triangulate_midpoint(b0, b1, R, t)
            # Two centroids each within 0.3 px: the disparity within ~0.4 px of f b / Z (~8-20 px here).
            disparity_px = calibs[0].camera.fx * HEADSET_STEREO_BASELINE_M / p_C0[2]
            assert pts.depth_m[0] == pytest.approx(p_C0[2], rel=0.4 / disparity_px)
