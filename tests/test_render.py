"""Offscreen renderer, GL backend selection and the MuJoCo -> OpenCV camera conversion."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.envs.sim import render as render_mod
from viotb.envs.sim import simulation as sim_mod
from viotb.envs.sim.render import (
    OffscreenRenderer,
    camera_calibration,
    camera_extrinsics,
    camera_intrinsics,
    rgb_to_gray,
    select_gl_backend,
)
from viotb.envs.sim.simulation import Simulation
from viotb.models import _assets
from viotb.models.constants import HOVER_KEYFRAME, ONBOARD_CAMERA, QUAD_BODY, QUADROTOR_XML

CORNER_ARGS = {"maxCorners": 300, "qualityLevel": 0.01, "minDistance": 7}

# Views from inside the textured room: (position (m), yaw (deg), body pitch nose-down (deg)).
# The onboard camera is itself pitched 25 deg down, so pitch 0 looks at the floor at 25 deg.
ROOM_VIEWS = {
    "centre_east": ([0.0, 0.0, 1.0], 0.0, 0.0),
    "centre_north": ([0.0, 0.0, 1.0], 90.0, 0.0),
    "wall_east_1m": ([4.0, 0.0, 1.5], 0.0, -25.0),
    "wall_north_1m": ([0.0, 4.0, 2.0], 90.0, -25.0),
    "wall_west_1m": ([-4.0, 1.0, 2.5], 180.0, -25.0),
    "wall_south_1m": ([1.0, -4.0, 1.2], -90.0, -25.0),
    "room_corner": ([4.0, 4.0, 1.0], 45.0, -10.0),
    "floor_low": ([0.0, 0.0, 0.3], 30.0, 0.0),
    "floor_steep": ([0.0, 0.0, 1.5], -60.0, 30.0),
    "crate_close": ([1.8, 2.5, 0.8], 0.0, 0.0),
    "across_room": ([-4.0, 1.0, 1.5], 0.0, -10.0),
}


def _body_rotation(yaw_deg: float, pitch_down_deg: float) -> np.ndarray:
    return Rotation.from_euler("ZY", [yaw_deg, pitch_down_deg], degrees=True).as_matrix()


@pytest.fixture(scope="module")
def room():
    sim = Simulation("quadrotor", "textured_room")
    with OffscreenRenderer(sim.model) as renderer:
        yield sim, renderer


def test_intrinsics_from_fovy(room):
    sim, renderer = room
    cam = camera_intrinsics(sim.model, ONBOARD_CAMERA, 320, 240)
    # fovy = 90 deg: f = 120 / tan(45 deg) = 120 px (closed form).
    assert cam.fx == pytest.approx(120.0, abs=1e-9) and cam.fy == pytest.approx(120.0, abs=1e-9)
    assert (cam.cx, cam.cy) == (159.5, 119.5)
    assert renderer.camera == cam
    with pytest.raises(ValueError, match="camera 'nope' not in model"):
        camera_intrinsics(sim.model, "nope", 320, 240)


def test_extrinsics_agree_with_cam_xmat(room):
    sim, _ = room
    R_BC, p_BC = camera_extrinsics(sim.model, ONBOARD_CAMERA, QUAD_BODY)
    rng = np.random.default_rng(0)
    for _ in range(5):
        R_WB = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        p_WB = rng.uniform(-2, 2, size=3) + [0, 0, 2]
        sim.set_pose(R_WB, p_WB)
        cam = mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_CAMERA, ONBOARD_CAMERA)
        R_W_Cmj = sim.data.cam_xmat[cam].reshape(3, 3)
        np.testing.assert_allclose(R_WB @ R_BC, R_W_Cmj @ np.diag([1.0, -1.0, -1.0]), atol=1e-12)
        np.testing.assert_allclose(R_WB @ p_BC + p_WB, sim.data.cam_xpos[cam], atol=1e-12)
        R_WC, p_WC = sim.camera_pose()
        np.testing.assert_allclose(R_WC, R_WB @ R_BC, atol=1e-12)
        np.testing.assert_allclose(p_WC, R_WB @ p_BC + p_WB, atol=1e-12)
    # The quadrotor's camera looks 25 deg below the body x axis.
    c, s = np.cos(np.deg2rad(25)), np.sin(np.deg2rad(25))
    np.testing.assert_allclose(R_BC[:, 2], [c, 0, -s], atol=1e-4)
    calib = camera_calibration(sim.model, ONBOARD_CAMERA, QUAD_BODY, 320, 240, time_offset_s=0.01, rate_hz=30)
    np.testing.assert_allclose(calib.R_BC, R_BC, atol=0)
    assert calib.time_offset_s == 0.01 and calib.rate_hz == 30.0
    with pytest.raises(ValueError, match="not attached to body"):
        camera_extrinsics(sim.model, ONBOARD_CAMERA, "world")


def _marker_model() -> tuple[mujoco.MjModel, np.ndarray]:
    markers = [
        (2.5, -1.2, 0.3),
        (2.5, 0.0, 1.0),
        (2.5, 1.2, 0.6),
        (3.5, -0.8, 1.4),
        (3.5, 0.9, -0.2),
        (2.0, 0.5, 0.0),
        (3.0, -1.8, 0.9),
        (4.0, 1.6, 1.8),
        (2.2, -0.3, -0.4),
    ]
    geoms = "".join(
        f'<geom name="marker_{i}" type="sphere" size="0.04" pos="{x} {y} {z}" material="glow"/>'
        for i, (x, y, z) in enumerate(markers)
    )
    xml = (
        '<mujoco model="markers"><visual><global offwidth="752" offheight="480"/>'
        '<headlight ambient="0 0 0" diffuse="0 0 0" specular="0 0 0"/></visual>'
        '<asset><material name="glow" rgba="1 1 1 1" emission="1"/></asset>'
        f"<worldbody>{geoms}</worldbody>"
        f'<include file="{QUADROTOR_XML}"/></mujoco>'
    )
    return mujoco.MjModel.from_xml_string(xml, _assets()), np.array(markers)


@pytest.mark.parametrize("size", [(320, 240), (640, 480)])
def test_rendered_markers_land_on_projection(monkeypatch, size):
    model, markers_W = _marker_model()
    monkeypatch.setattr(sim_mod, "load_model", lambda vehicle, scene: model)
    sim = Simulation("quadrotor", "markers")
    sim.reset(HOVER_KEYFRAME)
    # Tilted and yawed so that every axis of the conversion matters.
    sim.set_pose(Rotation.from_euler("ZYX", [8, -6, 7], degrees=True).as_matrix(), np.array([0.0, 0.1, 0.8]))
    width, height = size
    with OffscreenRenderer(model, width=width, height=height) as renderer:
        gray = renderer.render_gray(sim.data)
        camera = renderer.camera
    R_WC, p_WC = sim.camera_pose()
    p_C = (markers_W - p_WC) @ R_WC
    assert np.all(p_C[:, 2] > 0)
    predicted = camera.project(p_C)
    assert np.all(camera.in_image(predicted, border_px=5))
    # Detect: threshold, connected components, intensity-weighted centroids.
    n_labels, labels = cv2.connectedComponents((gray > 20).astype(np.uint8))
    rows, cols = np.mgrid[0:height, 0:width]
    weights = gray.astype(float)
    centroids = []
    for label in range(1, n_labels):
        w = weights * (labels == label)
        centroids.append([(w * cols).sum() / w.sum(), (w * rows).sum() / w.sum()])
    centroids = np.array(centroids)
    assert len(centroids) == len(markers_W)
    errors = np.array([np.min(np.linalg.norm(centroids - p, axis=1)) for p in predicted])
    print(f"marker error {width}x{height}: max {errors.max():.3f} px, median {np.median(errors):.3f} px")
    assert errors.max() < 0.5, errors


@pytest.mark.parametrize("view", sorted(ROOM_VIEWS))
def test_textured_room_has_corners_everywhere(room, view):
    sim, renderer = room
    position, yaw, pitch = ROOM_VIEWS[view]
    sim.set_pose(_body_rotation(yaw, pitch), np.array(position))
    gray = renderer.render_gray(sim.data)
    corners = cv2.goodFeaturesToTrack(gray, **CORNER_ARGS)
    assert corners is not None and len(corners) >= 100, view


def test_wall_view_is_what_the_test_claims(room):
    """The '1 m from a wall' views do look at the wall: depth at the image centre closed form."""
    sim, renderer = room
    sim.set_pose(_body_rotation(0.0, -25.0), np.array([4.0, 0.0, 1.5]))
    depth = renderer.render_depth(sim.data)
    # Camera 7 cm ahead of the body, optical axis along +x: wall at x = 5 m.
    assert depth[119:121, 159:161].mean() == pytest.approx(5.0 - 4.07, abs=0.01)
    gray = renderer.render_gray(sim.data)  # switching back from depth works
    assert gray.dtype == np.uint8 and gray.shape == (240, 320)


def test_dark_room_is_dark():
    sim = Simulation("quadrotor", "dark_room")
    sim.reset(HOVER_KEYFRAME)
    with OffscreenRenderer(sim.model) as renderer:
        for yaw in (0.0, 90.0, 180.0, 270.0):
            sim.set_pose(_body_rotation(yaw, 0.0), np.array([0.0, 0.0, 1.0]))
            assert renderer.render_gray(sim.data).mean() < 10.0


def test_blank_wall_is_blank():
    sim = Simulation("quadrotor", "blank_wall")
    sim.set_pose(_body_rotation(0.0, -25.0), np.array([4.0, 0.0, 2.0]))
    with OffscreenRenderer(sim.model) as renderer:
        gray = renderer.render_gray(sim.data)
    # Looking level at a uniform wall from 1 m: the upper half of the image is one flat gray.
    assert gray[:100].std() < 2.0


def test_gray_matches_opencv_and_noise_is_seeded(room):
    sim, _ = room
    sim.reset(HOVER_KEYFRAME)
    with OffscreenRenderer(sim.model) as clean:
        rgb = clean.render_rgb(sim.data)
        gray = clean.render_gray(sim.data)
    assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
    reference = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    assert np.abs(gray.astype(int) - reference.astype(int)).max() <= 1
    images = []
    for _ in range(2):
        with OffscreenRenderer(sim.model, pixel_noise_std=3.0, rng=np.random.default_rng(0)) as noisy:
            images.append(noisy.render_gray(sim.data))
    np.testing.assert_array_equal(images[0], images[1])
    diff = images[0].astype(float) - gray
    assert abs(diff.mean()) < 0.1 and diff.std() == pytest.approx(3.0, rel=0.05)


def test_gray_with_reused_buffers_is_the_plain_conversion_and_never_aliased(room):
    sim, renderer = room
    images = []
    for view in ("centre_east", "wall_north_1m", "centre_east"):
        p, yaw, pitch = ROOM_VIEWS[view]
        sim.set_pose(_body_rotation(yaw, pitch), np.array(p))
        gray = renderer.render_gray(sim.data)
        expected = np.clip(np.rint(rgb_to_gray(renderer.render_rgb(sim.data))), 0, 255).astype(np.uint8)
        np.testing.assert_array_equal(gray, expected)
        images.append(gray)
    # Each returned image is its own array: later renders do not overwrite it.
    assert not np.array_equal(images[0], images[1])
    np.testing.assert_array_equal(images[0], images[2])


def test_image_sized_framebuffer_renders_the_same_pixels_as_the_model_sized_one(room):
    """The renderer's framebuffer is allocated at the image size, not the model's offwidth x offheight."""
    sim, renderer = room
    vis = sim.model.vis.global_
    assert (vis.offwidth, vis.offheight) == (752, 480)  # the model keeps its buffer size
    full = mujoco.Renderer(sim.model, height=240, width=320)  # the model-sized buffer, MSAA as configured
    try:
        for view in ("centre_east", "room_corner", "floor_steep", "crate_close"):
            p, yaw, pitch = ROOM_VIEWS[view]
            sim.set_pose(_body_rotation(yaw, pitch), np.array(p))
            full.update_scene(sim.data, camera=ONBOARD_CAMERA)
            np.testing.assert_array_equal(renderer.render_rgb(sim.data), full.render())
            full.enable_depth_rendering()
            full.update_scene(sim.data, camera=ONBOARD_CAMERA)
            np.testing.assert_array_equal(renderer.render_depth(sim.data), full.render().astype(np.float64))
            full.disable_depth_rendering()
    finally:
        full.close()


def test_renderer_rejects_bad_arguments(room):
    sim, _ = room
    with pytest.raises(ValueError, match="exceeds the model's offscreen buffer"):
        OffscreenRenderer(sim.model, width=1024, height=768)
    with pytest.raises(ValueError, match="needs an rng"):
        OffscreenRenderer(sim.model, pixel_noise_std=1.0)
    with pytest.raises(ValueError, match="camera 'nope'"):
        OffscreenRenderer(sim.model, camera="nope")


def test_chase_camera_renders_the_drone(room):
    sim, renderer = room
    sim.reset(HOVER_KEYFRAME)
    rgb = renderer.render_rgb(sim.data, camera="chase")
    assert rgb.shape == (240, 320, 3)
    # The dark hull sits at the image centre.
    assert rgb[110:130, 150:170].mean() < rgb.mean()


def test_bench_render_smoke():
    from viotb.envs.tools.bench_render import bench_render

    result = bench_render(repeats=1, frames=1, physics_steps=10)
    for key in ("render_gray_ms_320x240", "render_gray_ms_640x480", "render_depth_ms_320x240"):
        assert 0.0 < result[key] < 1000.0
    assert result["physics_steps_per_s"] > 1000.0
    with pytest.raises(ValueError, match="counts must be positive"):
        bench_render(repeats=0)


def test_select_gl_backend_honours_explicit_value(monkeypatch):
    bound = []
    monkeypatch.setattr(render_mod, "_bind_mujoco_context", bound.append)
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    assert select_gl_backend(egl_probe=lambda: True) == "osmesa"
    assert bound == ["osmesa"]


def test_select_gl_backend_prefers_egl(monkeypatch):
    monkeypatch.setattr(render_mod, "_bind_mujoco_context", lambda backend: None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    assert select_gl_backend(egl_probe=lambda: True, osmesa_probe=lambda: True) == "egl"
    assert os.environ["MUJOCO_GL"] == "egl"


def test_select_gl_backend_error_names_packages(monkeypatch):
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    with pytest.raises(RuntimeError) as info:
        select_gl_backend(egl_probe=lambda: False, osmesa_probe=lambda: False)
    message = str(info.value)
    for package in render_mod.EGL_PACKAGES.split() + ["libosmesa6", "pyopengl"]:
        assert package in message
    assert "MUJOCO_GL" not in os.environ


def test_exposure_render_is_the_mean_of_the_renders_and_blurs_a_spin(room):
    sim, renderer = room
    position, yaw0, pitch = ROOM_VIEWS["centre_east"]

    def place(offset_s: float, rate_rad_s: float = 3.0) -> None:  # a 3 rad/s yaw spin about the centre time
        sim.set_pose(_body_rotation(yaw0 + np.rad2deg(rate_rad_s * offset_s), pitch), np.array(position))

    offsets = np.linspace(-0.5, 0.5, 9) * 0.045
    # Closed forms: a zero-length exposure is the instant render; otherwise the mean of the renders.
    instant = renderer.render_gray_exposure(sim.data, lambda o: place(0.0), np.zeros(3))
    place(0.0)
    np.testing.assert_array_equal(instant, renderer.render_gray(sim.data))
    manual = []
    for o in offsets:
        place(float(o))
        manual.append(renderer.render_rgb(sim.data).astype(np.float32))
    expected = np.clip(np.rint(rgb_to_gray(np.mean(manual, axis=0))), 0, 255).astype(np.uint8)
    blurred = renderer.render_gray_exposure(sim.data, place, offsets)
    assert np.max(np.abs(blurred.astype(int) - expected.astype(int))) <= 1  # float summation order
    # 3 rad/s x 45 ms smears ~34 px at f ~ 250 px: the Laplacian energy (sharpness) drops well below half.
    sharp = cv2.Laplacian(instant.astype(np.float32), cv2.CV_32F).var()
    smeared = cv2.Laplacian(blurred.astype(np.float32), cv2.CV_32F).var()
    assert smeared < 0.5 * sharp, (sharp, smeared)
    with pytest.raises(ValueError, match="empty"):
        renderer.render_gray_exposure(sim.data, place, np.zeros(0))
