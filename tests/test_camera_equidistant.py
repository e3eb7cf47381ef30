"""Equidistant (Kannala-Brandt) camera model vs OpenCV's fisheye module, Jacobians and the Kalibr factory."""

import cv2
import numpy as np
import pytest
from viotb.vio.camera import (
    CameraCalibration,
    EquidistantCamera,
    PinholeCamera,
    camera_from_kalibr,
    camera_to_kalibr,
)

# TUM-VI cam0 (Kalibr pinhole-equi, 512x512, ~190 deg diagonal): the image corners lie ~105 deg off axis.
TUMVI_CAM0 = EquidistantCamera(
    512,
    512,
    190.97847715128717,
    190.9733070521226,
    254.93170605935475,
    256.8974428996504,
    (0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182),
)
# A headset-like lens: 640x480, 100 deg vertical field of view, mild distortion.
HEADSET_CAM = EquidistantCamera(640, 480, 275.0, 274.0, 319.2, 240.7, (-0.01, 0.004, -0.002, 0.0003))
EUROC_CAM0 = PinholeCamera(
    752, 480, 458.654, 457.296, 367.215, 248.375, (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
)


def _points_at_angles(rng: np.random.Generator, n: int, max_theta_rad: float) -> np.ndarray:
    """Camera-frame points (m), shape (n, 3), up to ``max_theta_rad`` off the optical axis, 0.3-10 m away."""
    theta = rng.uniform(0.0, max_theta_rad, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    dist = rng.uniform(0.3, 10.0, n)
    return dist[:, None] * np.column_stack(
        [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)]
    )


def _pixel_grid(cam, step_px: float = 7.0) -> np.ndarray:
    u, v = np.meshgrid(np.arange(0.0, cam.width, step_px), np.arange(0.0, cam.height, step_px))
    return np.column_stack([u.ravel(), v.ravel()])


@pytest.mark.parametrize("cam", [TUMVI_CAM0, HEADSET_CAM], ids=["tumvi", "headset"])
def test_project_matches_opencv_fisheye(cam):
    rng = np.random.default_rng(1)
    p_C = _points_at_angles(rng, 2000, np.deg2rad(85.0))
    uv_cv, _ = cv2.fisheye.projectPoints(
        p_C.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, np.array(cam.distortion)
    )
    np.testing.assert_allclose(cam.project(p_C), uv_cv.reshape(-1, 2), atol=1e-6)
    # The normalized-coordinate path gives the same pixels.
    np.testing.assert_allclose(
        cam.normalized_to_pixels(p_C[:, :2] / p_C[:, 2:]), uv_cv.reshape(-1, 2), atol=1e-6
    )


@pytest.mark.parametrize("cam", [TUMVI_CAM0, HEADSET_CAM], ids=["tumvi", "headset"])
def test_unproject_round_trips_over_whole_image(cam):
    uv = _pixel_grid(cam)
    bearings = cam.unproject(uv)
    assert np.all(np.isfinite(bearings))
    np.testing.assert_allclose(np.linalg.norm(bearings, axis=1), 1.0, atol=1e-12)
    # Bearings at several depths project back onto the pixel, including those > 90 deg off axis (TUM-VI).
    np.testing.assert_allclose(cam.project(bearings * 3.7), uv, atol=1e-8)
    theta_max_deg = np.rad2deg(np.arccos(bearings[:, 2].min()))
    assert theta_max_deg > (100.0 if cam is TUMVI_CAM0 else 55.0)


@pytest.mark.parametrize("cam", [TUMVI_CAM0, HEADSET_CAM], ids=["tumvi", "headset"])
def test_undistort_matches_opencv_fisheye(cam):
    uv = _pixel_grid(cam)
    bearings = cam.unproject(uv)
    ok = bearings[:, 2] > np.cos(np.deg2rad(80.0))  # normalized coordinates need theta < 90 deg
    xy = cam.undistort_points(uv)
    assert np.all(np.isnan(xy[bearings[:, 2] <= 0.0]))
    xy_cv = cv2.fisheye.undistortPoints(
        uv[ok].reshape(-1, 1, 2),
        cam.K,
        np.array(cam.distortion),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14),
    ).reshape(-1, 2)
    # Compare where it matters, in pixels of a pinhole view of focal fx (OpenCV stops at its own tolerance).
    np.testing.assert_allclose(xy[ok] * cam.fx, xy_cv * cam.fx, atol=1e-4)
    np.testing.assert_allclose(cam.normalized_to_pixels(xy[ok]), uv[ok], atol=1e-8)


def test_equidistant_from_fovy_spans_the_field_of_view():
    cam = EquidistantCamera.from_fovy(320, 240, 100.0)
    top = cam.project(np.array([[0.0, -np.tan(np.deg2rad(50.0)), 1.0]]))
    np.testing.assert_allclose(top, [[159.5, -0.5]], atol=1e-9)  # the top edge of the top pixel row


@pytest.mark.parametrize(
    "cam", [TUMVI_CAM0, HEADSET_CAM, EUROC_CAM0, PinholeCamera.from_fovy(320, 240, 90.0)]
)
def test_projection_jacobian_matches_central_differences(cam):
    rng = np.random.default_rng(2)
    max_theta = np.deg2rad(60.0 if isinstance(cam, EquidistantCamera) else 35.0)
    p_C = _points_at_angles(rng, 200, max_theta)
    p_C[0] = [0.0, 0.0, 2.0]  # on the optical axis
    p_C[1] = [1e-9, -2e-9, 1.5]  # next to it
    jac = cam.project_jacobian(p_C)
    h = 1e-6
    numeric = np.empty_like(jac)
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        numeric[:, :, k] = (cam.project(p_C + step) - cam.project(p_C - step)) / (2 * h)
    np.testing.assert_allclose(jac, numeric, rtol=1e-6, atol=1e-5)


def test_equidistant_behind_the_image_plane_matches_the_angle():
    # 100 deg off axis (Z < 0): the image radius is f * theta_d(100 deg), in the direction of (X, Y).
    cam = EquidistantCamera(400, 400, 100.0, 100.0, 199.5, 199.5)
    theta = np.deg2rad(100.0)
    uv = cam.project(np.array([[np.sin(theta), 0.0, np.cos(theta)]]))
    np.testing.assert_allclose(uv, [[199.5 + 100.0 * theta, 199.5]], atol=1e-9)


def test_pinhole_unproject_is_the_normalized_ray():
    uv = _pixel_grid(EUROC_CAM0, 37.0)
    b = EUROC_CAM0.unproject(uv)
    np.testing.assert_allclose(EUROC_CAM0.project(b * 2.0), uv, atol=1e-6)


KALIBR_EQUI = {
    "camera_model": "pinhole",
    "distortion_model": "equidistant",
    "intrinsics": [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504],
    "distortion_coefficients": list(TUMVI_CAM0.distortion),
    "resolution": [512, 512],
}


def test_factory_builds_each_model_and_round_trips():
    assert camera_from_kalibr(KALIBR_EQUI) == TUMVI_CAM0
    radtan = camera_to_kalibr(EUROC_CAM0)
    assert radtan["distortion_model"] == "radial-tangential"
    assert camera_from_kalibr(radtan) == EUROC_CAM0
    assert camera_from_kalibr({**radtan, "distortion_model": "radtan"}) == EUROC_CAM0
    assert camera_from_kalibr({**KALIBR_EQUI, "distortion_model": "equi"}) == TUMVI_CAM0
    assert camera_to_kalibr(TUMVI_CAM0) == KALIBR_EQUI
    calib = CameraCalibration(TUMVI_CAM0, np.eye(3), np.zeros(3))
    assert calib.camera.distortion_model == "equidistant"


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"camera_model": "omni"}, "field 'camera_model' must be 'pinhole', got 'omni'"),
        ({"distortion_model": "fov"}, "field 'distortion_model' must be one of .* got 'fov'"),
        ({"distortion_coefficients": [0.1, 0.2, 0.3]}, "field 'distortion_coefficients' must hold 4"),
        (
            {"intrinsics": [1.0, 2.0, 3.0]},
            r"field 'intrinsics' must hold 4 finite numbers, got \[1.0, 2.0, 3.0\]",
        ),
        ({"intrinsics": "fx fy"}, "field 'intrinsics' must be a list of 4 numbers, got 'fx fy'"),
        ({"resolution": [512.5, 512]}, "field 'resolution' must be 2 positive integers"),
        ({"intrinsics": [-1.0, 1.0, 0.0, 0.0]}, "field 'intrinsics' needs positive focal lengths"),
        ({"resolution": "12"}, "field 'resolution' must be a list of 2 numbers, got '12'"),
    ],
)
def test_factory_errors_name_field_and_value(change, message):
    with pytest.raises(ValueError, match=f"cam0/sensor.yaml: {message}"):
        camera_from_kalibr({**KALIBR_EQUI, **change}, source="cam0/sensor.yaml")
    missing = dict(KALIBR_EQUI)
    del missing["resolution"]
    with pytest.raises(ValueError, match="missing field 'resolution'"):
        camera_from_kalibr(missing)
