"""Triangulated keyframe landmarks and their uncertainty against the closed form of a two-view stereo pair.

Two cameras looking along +z (body = camera), the second translated by ``b`` along x; for a point midway
between them on the principal row, ``(b / 2, 0, z)`` in the first camera's frame, the least-squares point
from pixel noise ``sigma`` in both views has the closed-form standard deviations

    sigma_z = sqrt(2) z^2 sigma / (f b)      (disparity f b / z, noise sqrt(2) sigma)
    sigma_x = sigma_y = z sigma / (sqrt(2) f)  (the mean of two rays)

which the keyframe's ``landmark_sigma_m_per_px`` (square root of the covariance trace, per pixel) must give.
"""

from __future__ import annotations

import numpy as np
import pytest
from viotb.vio.camera import CameraCalibration, PinholeCamera
from viotb.vio.loop.keyframes import Keyframe, KeyframeDatabase

F_PX = 120.0
CALIB = CameraCalibration(PinholeCamera(320, 240, F_PX, F_PX, 160.0, 120.0), np.eye(3), np.zeros(3))


def _keyframe(index: int, p_WB: np.ndarray, points_W: np.ndarray, desc: np.ndarray, octave: int = 0):
    """A keyframe at ``p_WB`` (no rotation) whose features are the exact projections of ``points_W``."""
    p_C = points_W - p_WB
    uv = F_PX * p_C[:, :2] / p_C[:, 2:3] + np.array([160.0, 120.0])
    n = len(points_W)
    return Keyframe(
        index,
        float(index),
        0,
        np.eye(3),
        np.asarray(p_WB, dtype=float),
        uv.astype(np.float32),
        desc,
        np.full((n, 3), np.nan),
        octaves=np.full(n, octave, dtype=np.int8),
        landmark_sigma_m_per_px=np.full(n, np.inf),
    )


def _scene(baseline_m: float, rng: np.random.Generator):
    depths = np.linspace(2.0, 3.0, 12)
    points_W = np.column_stack([np.full(12, -baseline_m / 2.0), np.zeros(12), depths])
    desc = rng.integers(0, 256, size=(12, 32), dtype=np.uint8)  # distinct: exact matches only
    return points_W, desc


def _closed_form_sigma(z_m: np.ndarray, baseline_m: float) -> np.ndarray:
    s_z = np.sqrt(2.0) * z_m**2 / (F_PX * baseline_m)
    s_xy = z_m / (np.sqrt(2.0) * F_PX)
    return np.sqrt(s_z**2 + 2.0 * s_xy**2)


@pytest.mark.parametrize("octave", [0, 2])
def test_two_view_landmarks_are_exact_and_their_sigma_is_the_stereo_closed_form(octave):
    rng = np.random.default_rng(0)
    b = 0.3
    points_W, desc = _scene(b, rng)
    prev = _keyframe(0, np.array([-b, 0.0, 0.0]), points_W, desc, octave)
    new = _keyframe(1, np.zeros(3), points_W, desc, octave)
    made = KeyframeDatabase().triangulate(prev, new, CALIB)
    assert made == len(points_W)
    # Body = world at the origin; keypoints are float32 (1e-5 px), hence 2e-5 m.
    np.testing.assert_allclose(new.landmarks_B, points_W, atol=2e-5)
    np.testing.assert_allclose(prev.landmarks_B, points_W - prev.p_WB_odom, atol=2e-5)
    # Level-o keypoints carry 1.2**o times the level-0 noise in both views: the sigma scales by it.
    expected = _closed_form_sigma(points_W[:, 2], b) * 1.2**octave
    np.testing.assert_allclose(new.landmark_sigma_m_per_px, expected, rtol=1e-5)  # float32 pixels
    np.testing.assert_allclose(prev.landmark_sigma_m_per_px, expected, rtol=1e-5)


def test_a_wider_baseline_replaces_a_landmark_a_narrower_one_does_not_and_given_ones_stay():
    rng = np.random.default_rng(1)
    points_W, desc = _scene(0.2, rng)
    db = KeyframeDatabase()
    new = _keyframe(3, np.zeros(3), points_W, desc)
    new.landmarks_B[0] = [9.0, 9.0, 9.0]  # as if given by the estimator: never replaced
    new.landmark_sigma_m_per_px[0] = 0.0
    db.triangulate(_keyframe(0, np.array([-0.2, 0.0, 0.0]), points_W, desc), new, CALIB)
    narrow = new.landmark_sigma_m_per_px.copy()
    wide = _keyframe(1, np.array([-0.6, 0.0, 0.0]), points_W, desc)
    db.triangulate(wide, new, CALIB)
    replaced = new.landmark_sigma_m_per_px != narrow
    np.testing.assert_array_equal(replaced, np.arange(len(points_W)) > 0)
    # The replaced sigmas are those of the wide pair alone.
    alone = _keyframe(4, np.zeros(3), points_W, desc)
    db.triangulate(_keyframe(2, np.array([-0.6, 0.0, 0.0]), points_W, desc), alone, CALIB)
    np.testing.assert_allclose(new.landmark_sigma_m_per_px[1:], alone.landmark_sigma_m_per_px[1:])
    assert np.all(new.landmark_sigma_m_per_px[1:] < 0.5 * narrow[1:])
    np.testing.assert_allclose(new.landmarks_B[1:], points_W[1:], atol=2e-5)
    # A narrower pair afterwards changes nothing.
    before = new.landmark_sigma_m_per_px.copy()
    db.triangulate(_keyframe(5, np.array([-0.25, 0.0, 0.0]), points_W, desc), new, CALIB)
    np.testing.assert_array_equal(new.landmark_sigma_m_per_px, before)
    np.testing.assert_array_equal(new.landmarks_B[0], [9.0, 9.0, 9.0])


def test_landmark_sigma_matches_the_monte_carlo_spread_of_noisy_triangulations():
    # The same pair with 0.5 px Gaussian noise on every keypoint: the spread of the triangulated points
    # over 400 draws against the predicted sigma (linearized; the depth noise is 1-3 % here).
    rng = np.random.default_rng(2)
    b, sigma_px = 0.3, 0.5
    points_W, desc = _scene(b, rng)
    db = KeyframeDatabase()
    draws, predicted = [], None
    for _ in range(400):
        prev = _keyframe(0, np.array([-b, 0.0, 0.0]), points_W, desc)
        new = _keyframe(1, np.zeros(3), points_W, desc)
        for kf in (prev, new):
            kf.keypoints_uv_px += rng.normal(scale=sigma_px, size=kf.keypoints_uv_px.shape).astype(np.float32)
        db.triangulate(prev, new, CALIB)
        if np.all(np.isfinite(new.landmarks_B[:, 0])):
            draws.append(new.landmarks_B.copy())
            predicted = _closed_form_sigma(points_W[:, 2], b) * sigma_px
    draws = np.array(draws)
    assert len(draws) > 350
    spread = np.sqrt(np.sum(np.var(draws, axis=0), axis=1))
    np.testing.assert_allclose(spread, predicted, rtol=0.15)
