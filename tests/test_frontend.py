"""Tests of vio/frontend.py: KLT (known shift, real EuRoC frames), simulated tracker, feature database."""

import cv2
import numpy as np
import pytest
from data_paths import EUROC_MICRO
from viotb.vio.camera import PinholeCamera
from viotb.vio.frontend import FeatureDatabase, KltParams, KltTracker, SimFeatureTracker
from viotb.vio.types import CameraFrame, FeatureObservations

EUROC_CAM = EUROC_MICRO / "mav0" / "cam0"


def _texture(rng: np.random.Generator, h: int = 240, w: int = 320) -> np.ndarray:
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 255.0
    return img.astype(np.uint8)


def _shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    M = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])
    return cv2.warpAffine(
        img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )


def test_klt_tracks_a_known_shift():
    rng = np.random.default_rng(0)
    cam = PinholeCamera.from_fovy(320, 240, 60.0)
    trk = KltTracker(cam)
    img0 = _texture(rng)
    a = trk.process(CameraFrame(0.0, image=img0), 0.0)
    assert 120 <= len(a) <= KltParams().max_features
    b = trk.process(CameraFrame(0.05, image=_shift(img0, 2.3, -1.7)), 0.05)
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    assert len(common) > 0.8 * len(a)
    d = b.uv_px[ib] - a.uv_px[ia]
    np.testing.assert_allclose(np.median(d, axis=0), [2.3, -1.7], atol=0.05)
    # Undistorted normalized coordinates of an undistorted camera: (u - cx) / fx.
    np.testing.assert_allclose(b.xy_norm[:, 0], (b.uv_px[:, 0] - cam.cx) / cam.fx, atol=1e-12)


def test_klt_blank_missing_and_wrong_size_images():
    cam = PinholeCamera.from_fovy(320, 240, 60.0)
    trk = KltTracker(cam)
    assert len(trk.process(CameraFrame(0.0, image=np.full((240, 320), 128, np.uint8)), 0.0)) == 0
    assert len(trk.process(CameraFrame(0.1, image=None), 0.1)) == 0
    assert len(trk.process(CameraFrame(0.2, image=np.zeros((0, 0), np.uint8)), 0.2)) == 0
    with pytest.raises(ValueError, match=r"image shape \(480, 640\) does not match the camera \(240x320"):
        trk.process(CameraFrame(0.3, image=np.zeros((480, 640), np.uint8)), 0.3)


def test_klt_on_real_euroc_frames_of_a_still_rig():
    files = sorted((EUROC_CAM / "data").glob("*.png"))[:3]
    cam = PinholeCamera(
        752, 480, 458.654, 457.296, 367.215, 248.375, (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    )
    trk = KltTracker(cam)
    tracks = [
        trk.process(CameraFrame(float(i), image=cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)), float(i))
        for i, f in enumerate(files)
    ]
    assert all(len(t) >= 140 for t in tracks)  # target 180; FAST finds ~150 corners on frame 0
    common, ia, ib = np.intersect1d(tracks[0].ids, tracks[2].ids, return_indices=True)
    assert len(common) > 0.9 * len(tracks[0])
    assert np.median(np.linalg.norm(tracks[2].uv_px[ib] - tracks[0].uv_px[ia], axis=1)) < 0.2
    # Normalized coordinates re-distort to the measured pixels (OpenCV undistortion vs our camera model).
    np.testing.assert_allclose(cam.normalized_to_pixels(tracks[2].xy_norm), tracks[2].uv_px, atol=1e-6)
    # Coordinates carried over from the previous frame are exactly a fresh undistortion of the pixels.
    for t in tracks:
        np.testing.assert_array_equal(t.xy_norm, trk.undistort(t.uv_px))


def test_sim_tracker_undistorts_and_handles_empty():
    cam = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5, (-0.2, 0.05, 0.001, 0.0))
    xy = np.array([[0.1, -0.2], [0.0, 0.0], [-0.3, 0.25]])
    obs = FeatureObservations(np.array([4, 9, 2]), cam.normalized_to_pixels(xy))
    t = SimFeatureTracker(cam).process(CameraFrame(1.0, features=obs), 1.01)
    np.testing.assert_allclose(t.xy_norm, xy, atol=1e-9)
    assert t.ids.tolist() == [4, 9, 2] and t.t_imu_s == 1.01
    assert len(SimFeatureTracker(cam).process(CameraFrame(1.0), 1.0)) == 0


def test_feature_database_queries():
    db = FeatureDatabase(max_frames=3, initial_features=2)
    db.add(1.0, np.array([10, 11, 12]), np.array([[0.0, 0.0], [0.1, 0.1], [0.2, 0.2]]))
    db.add(2.0, np.array([10, 12, 13]), np.array([[0.01, 0.0], [0.2, 0.21], [0.3, 0.3]]))
    assert db.features_lost(2.0).tolist() == [11]
    assert sorted(db.features_seen_at(1.0).tolist()) == [10, 11, 12]
    assert db.track_lengths(np.array([10, 11, 13, 99])).tolist() == [2, 1, 1, 0]
    xy, mask = db.observations(np.array([12, 13]), np.array([1.0, 2.0]))
    assert mask.tolist() == [[True, True], [False, True]]
    np.testing.assert_allclose(xy[0], [[0.2, 0.2], [0.2, 0.21]])
    # A time without a frame and an unknown id give empty views.
    xy, mask = db.observations(np.array([13, 99, 10]), np.array([2.0, 7.0, 1.0]))
    assert mask.tolist() == [[True, False, False], [False, False, False], [True, False, True]]
    np.testing.assert_allclose(xy[[0, 2]][:, [0, 2]], [[[0.3, 0.3], [0.0, 0.0]], [[0.01, 0.0], [0.0, 0.0]]])
    db.remove_frame(1.0)
    assert db.num_features == 3  # 11 had only the removed frame
    db.add(3.0, np.array([13]), np.array([[0.31, 0.3]]))
    db.add(4.0, np.array([13]), np.array([[0.32, 0.3]]))
    db.add(5.0, np.array([13]), np.array([[0.33, 0.3]]))  # full: evicts the oldest frame (2.0)
    np.testing.assert_allclose(db.frame_times, [3.0, 4.0, 5.0])
    assert db.track_lengths(np.array([13, 10])).tolist() == [3, 0]
    db.remove_features(np.array([13]))
    assert db.num_features == 0


def test_equidistant_camera_goes_through_the_klt_front_end():
    """A fisheye (equidistant) camera is undistorted with its own model, not OpenCV's radial-tangential."""
    from viotb.vio.camera import EquidistantCamera

    cam = EquidistantCamera(320, 240, 120.0, 121.0, 160.2, 119.7, (0.05, -0.02, 0.004, -0.001))
    trk = KltTracker(cam)
    rng = np.random.default_rng(3)
    p_C = np.column_stack([rng.uniform(-1.0, 1.0, (50, 2)), np.ones(50)]) * rng.uniform(1.0, 5.0, (50, 1))
    uv = cam.project(p_C)
    np.testing.assert_allclose(trk.undistort(uv), p_C[:, :2] / p_C[:, 2:], atol=1e-9)
    # Tracking a shifted texture: every observation leaves as the model's undistortion of its pixel.
    img0 = _texture(rng)
    trk.process(CameraFrame(0.0, image=img0), 0.0)
    b = trk.process(CameraFrame(0.05, image=_shift(img0, 1.5, 0.5)), 0.05)
    assert len(b) > 100
    np.testing.assert_allclose(b.xy_norm, cam.undistort_points(b.uv_px), atol=1e-12)


def test_klt_backward_pass_on_kept_points_equals_the_full_forward_backward_check():
    """Tracking back only the points the forward pass kept gives the tracks of the full backward pass.

    Reference: both LK passes over every point, then the status, forward-backward and border tests (what
    the tracker did before it skipped the rejected points); on a shifted and slightly zoomed texture.
    """
    rng = np.random.default_rng(2)
    cam = PinholeCamera(320, 240, 120.0, 120.0, 160.0, 120.0)
    img0 = _texture(rng)
    M = np.array([[1.02, 0.0, -1.5], [0.0, 1.02, 6.0]])  # zoom + shift: some points leave the image
    img1 = cv2.warpAffine(img0, M, (320, 240), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    trk = KltTracker(
        cam, KltParams(anchor_templates=False)
    )  # the LK passes alone (anchoring: test_klt_anchor)
    trk.process(CameraFrame(0.0, image=img0), 0.0)
    p, prev = trk.params, trk._prev_pts.copy()
    lk = {"winSize": (p.win_size_px, p.win_size_px), "maxLevel": p.pyramid_levels}
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(img0, img1, prev.reshape(-1, 1, 2), None, **lk)
    p0r, st2, _ = cv2.calcOpticalFlowPyrLK(img1, img0, p1, None, **lk)
    fb = np.linalg.norm(p0r.reshape(-1, 2) - prev, axis=1)
    good = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < p.fb_max_error_px)
    good &= cam.in_image(p1.reshape(-1, 2).astype(float), p.border_px)
    assert 0 < good.sum() < len(prev)  # the check rejects some points and keeps most
    pts, ids, xy, _ = trk._track(img1, None)
    kept = np.isin(ids, trk._prev_ids[good])
    assert kept.all()  # RANSAC only removes more
    np.testing.assert_array_equal(pts, p1.reshape(-1, 2)[good][np.isin(trk._prev_ids[good], ids)])
    np.testing.assert_array_equal(xy, trk.undistort(pts))  # each kept point undistorted once, the same


def test_backward_pass_from_the_previous_points_keeps_good_tracks_and_drops_a_mismatch():
    """``fb_max_level``: the backward pass starts at the previous points (VINS-Fusion ``FLOW_BACK``)."""
    rng = np.random.default_rng(5)
    cam = PinholeCamera(320, 240, 120.0, 120.0, 160.0, 120.0)
    img0 = _texture(rng)
    img1 = _shift(img0, 2.3, -1.1)
    out = {}
    for level in (None, 1):
        trk = KltTracker(cam, KltParams(fb_max_level=level))
        first = trk.process(CameraFrame(0.0, image=img0), 0.0)
        second = trk.process(CameraFrame(0.05, image=img1), 0.05)
        kept = np.isin(second.ids, first.ids)
        out[level] = (second.ids[kept], second.uv_px[kept])
        # The kept tracks moved with the shift (the image content moved by +2.3, -1.1 px; a few near the
        # reflected border less exactly).
        moved = second.uv_px[kept] - first.uv_px[np.searchsorted(first.ids, second.ids[kept])]
        assert kept.mean() > 0.8
        assert np.median(np.linalg.norm(moved - [2.3, -1.1], axis=1)) < 0.05
        # A frame of another texture: the checks (and RANSAC) drop over 90 % of the tracks (here the full
        # search keeps 7 of 180, the start at the previous points 12: the weaker check of the two).
        third = trk.process(CameraFrame(0.1, image=_texture(np.random.default_rng(6))), 0.1)
        assert np.isin(third.ids, second.ids).mean() < 0.1
    np.testing.assert_array_equal(out[None][0], out[1][0])  # the same tracks kept on a clean shift
    np.testing.assert_array_equal(out[None][1], out[1][1])
