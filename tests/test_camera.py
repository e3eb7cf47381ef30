"""Tests of vio/camera.py against OpenCV with the real EuRoC cam0 calibration."""

import cv2
import numpy as np
import pytest
from viotb.vio.camera import PinholeCamera

EUROC_CAM0 = PinholeCamera(
    width=752,
    height=480,
    fx=458.654,
    fy=457.296,
    cx=367.215,
    cy=248.375,
    distortion=(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
)


def _points_in_view(rng: np.random.Generator, n: int) -> np.ndarray:
    """Camera-frame points (m), shape (n, 3), that land inside the EuRoC image."""
    xy = np.column_stack([rng.uniform(-0.7, 0.7, n), rng.uniform(-0.45, 0.45, n)])
    depth = rng.uniform(0.5, 8.0, n)
    return np.column_stack([xy * depth[:, None], depth])


def test_project_matches_opencv_project_points():
    rng = np.random.default_rng(0)
    p_C = _points_in_view(rng, 500)
    uv_cv, _ = cv2.projectPoints(
        p_C.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), EUROC_CAM0.K, np.array(EUROC_CAM0.distortion)
    )
    np.testing.assert_allclose(EUROC_CAM0.project(p_C), uv_cv.reshape(-1, 2), atol=1e-9)


def test_project_without_distortion_is_pinhole():
    cam = PinholeCamera(320, 240, 200.0, 210.0, 159.5, 119.5)
    uv = cam.project(np.array([[0.5, -0.25, 2.0]]))
    np.testing.assert_allclose(uv, [[159.5 + 200.0 * 0.25, 119.5 - 210.0 * 0.125]], atol=1e-12)


def test_undistort_points_matches_opencv():
    rng = np.random.default_rng(0)
    uv = np.column_stack([rng.uniform(0, 751, 500), rng.uniform(0, 479, 500)])
    # OpenCV's default stops after 5 iterations (up to ~0.3 px off in EuRoC's corners); converge it fully.
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    xy_cv = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), EUROC_CAM0.K, np.array(EUROC_CAM0.distortion), None, None, criteria=criteria
    ).reshape(-1, 2)
    xy = EUROC_CAM0.undistort_points(uv)
    np.testing.assert_allclose(xy, xy_cv, atol=1e-8)
    # Re-distorting gives the input pixels back (fixed point reached over the whole image).
    np.testing.assert_allclose(EUROC_CAM0.normalized_to_pixels(xy), uv, atol=1e-6)


def test_undistort_inverts_project_in_the_central_region():
    rng = np.random.default_rng(0)
    p_C = _points_in_view(rng, 300)
    p_C[:, :2] *= 0.6  # keep well inside the image where the fixed-point iteration converges tightly
    xy_true = p_C[:, :2] / p_C[:, 2:3]
    np.testing.assert_allclose(EUROC_CAM0.undistort_points(EUROC_CAM0.project(p_C)), xy_true, atol=1e-9)


def test_from_fovy_closed_form():
    cam = PinholeCamera.from_fovy(320, 240, 90.0)
    assert cam.fx == pytest.approx(120.0, abs=1e-12)  # (240 / 2) / tan(45 deg)
    assert cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (159.5, 119.5)
    # A point on the top edge of the vertical field of view lands half a pixel outside row 0 ... row 239.
    uv = cam.project(np.array([[0.0, -1.0, 1.0]]))
    assert uv[0, 1] == pytest.approx(-0.5, abs=1e-12)
    cam60 = PinholeCamera.from_fovy(640, 480, 60.0)
    assert cam60.fy == pytest.approx(240.0 / np.tan(np.deg2rad(30.0)), rel=1e-15)
    np.testing.assert_allclose(cam60.K, [[cam60.fx, 0, 319.5], [0, cam60.fy, 239.5], [0, 0, 1]], atol=0)


def test_in_image_mask():
    uv = np.array([[0.0, 0.0], [751.0, 479.0], [-0.1, 10.0], [10.0, 479.5], [5.0, 5.0]])
    np.testing.assert_array_equal(EUROC_CAM0.in_image(uv), [True, True, False, False, True])
    np.testing.assert_array_equal(EUROC_CAM0.in_image(uv, border_px=10.0), [False] * 5)
