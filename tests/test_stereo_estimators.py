"""Stereo in the estimators: front end (vio/frontend_stereo.py), database, MSCKF update and window factors.

The look-around stream (``stereo_world.py``) is analytic: the head yaws +-57 deg in place, so a single
camera sees little parallax and the stereo baseline is what fixes the translation.
"""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from stereo_world import LookAroundWorld, run_look_around
from viotb.vio.camera import CameraCalibration, PinholeCamera
from viotb.vio.factory import make_estimator
from viotb.vio.feature_database import FeatureDatabase
from viotb.vio.frontend import KltTracker, SimFeatureTracker
from viotb.vio.frontend_stereo import StereoTracker
from viotb.vio.lie import exp_so3
from viotb.vio.msckf import MsckfEstimator, MsckfParams
from viotb.vio.msckf_update import _stacked_jacobian
from viotb.vio.types import CameraFrame, FeatureObservations, ImuNoise
from viotb.vio.window import WindowEstimator, WindowParams, reprojection

SIM_MSCKF = MsckfParams(frontend="sim", pixel_sigma_px=0.5)
SIM_WINDOW = WindowParams(frontend="sim", pixel_sigma_px=0.5)


def _ate_m(rows) -> float:
    err = np.array([e for _, e in rows])
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


# ------------------------------------------------------------------------------------------ front end
def test_feature_database_keeps_each_camera_apart():
    db = FeatureDatabase(max_frames=4, initial_features=2, num_cameras=2)
    db.add(1.0, np.array([7, 8]), np.array([[0.1, 0.2], [0.3, 0.4]]))
    db.add(1.0, np.array([8, 9]), np.array([[0.5, 0.6], [0.7, 0.8]]), cam=1)  # 9: seen only by cam1
    db.add(2.0, np.array([9]), np.array([[0.9, 1.0]]), cam=1)
    xy0, m0 = db.observations(np.array([8, 9]), np.array([1.0, 2.0]))
    xy1, m1 = db.observations(np.array([8, 9]), np.array([1.0, 2.0]), cam=1)
    np.testing.assert_array_equal(m0, [[True, False], [False, False]])
    np.testing.assert_array_equal(m1, [[True, False], [True, True]])
    np.testing.assert_allclose(xy0[0, 0], [0.3, 0.4])
    np.testing.assert_allclose(xy1[:, 0], [[0.5, 0.6], [0.7, 0.8]])
    np.testing.assert_array_equal(db.track_lengths(np.array([7, 8, 9, 42])), [1, 2, 2, 0])
    np.testing.assert_array_equal(np.sort(db.features_lost(2.0)), [7, 8])  # 9 is still seen, by cam1
    np.testing.assert_array_equal(np.sort(db.features_seen_at(2.0)), [9])
    db.remove_frame(1.0)
    assert db.num_features == 1
    with pytest.raises(ValueError, match="camera 1 outside 0..0"):
        FeatureDatabase(3).add(0.0, np.array([1]), np.zeros((1, 2)), cam=1)


def _rectified_pair(f_px: float = 200.0, baseline_m: float = 0.1):
    """Two parallel 320x240 pinholes, cam1 ``baseline_m`` along cam0's x (the classic rectified rig)."""
    cam = PinholeCamera(320, 240, f_px, f_px, 159.5, 119.5)
    c0 = CameraCalibration(cam, np.eye(3), np.zeros(3))
    c1 = CameraCalibration(cam, np.eye(3), np.array([baseline_m, 0.0, 0.0]))
    return cam, c0, c1


def test_sim_stereo_tracker_adds_cam1_with_its_own_intrinsics():
    cam, c0, _ = _rectified_pair()
    cam1 = PinholeCamera(320, 240, 180.0, 181.0, 150.0, 110.0, (-0.1, 0.01, 0.0, 0.0))
    c1 = CameraCalibration(cam1, np.eye(3), np.array([0.1, 0.0, 0.0]))
    trk = StereoTracker(SimFeatureTracker(cam), c0, c1)
    p_C1 = np.array([[0.2, -0.1, 2.0], [-0.5, 0.3, 3.0], [0.0, 0.0, 1.0]])
    left = FeatureObservations(np.array([1, 2]), cam.project(p_C1[:2] + [0.1, 0.0, 0.0]))
    right = FeatureObservations(np.array([1, 2, 5]), np.vstack([cam1.project(p_C1[:2]), [[np.nan, 1.0]]]))
    tr = trk.process(CameraFrame(0.0, features=left, features_right=right), 0.0)
    np.testing.assert_array_equal(tr.ids_right, [1, 2])  # the non-finite pixel is dropped
    np.testing.assert_allclose(tr.xy_norm_right, p_C1[:2, :2] / p_C1[:2, 2:], atol=1e-9)
    assert tr.num_cameras == 2 and tr.camera(1)[0] is tr.ids_right
    mono = trk.process(CameraFrame(0.1, features=left), 0.1)  # no right data: the mono tracks
    assert mono.num_cameras == 1 and len(mono.ids_right) == 0


def test_klt_stereo_tracker_finds_the_disparity_of_a_plane():
    """A textured plane at depth Z seen by a rectified pair: the right image is the left shifted by f b/Z."""
    cam, c0, c1 = _rectified_pair()
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (240, 400)).astype(np.float32), (0, 0), 2.0)
    img = ((img - img.min()) / (img.max() - img.min()) * 255.0).astype(np.uint8)
    depth_m = 2.5
    disparity = cam.fx * 0.1 / depth_m  # 8 px
    left = img[:, 40:360].copy()
    # A point at u in the left image sits at u - disparity in the right one: right(u) = img(u + 40 + d).
    right = cv2.warpAffine(img, np.array([[1.0, 0.0, -40.0 - disparity], [0.0, 1.0, 0.0]]), (320, 240))
    trk = StereoTracker(KltTracker(cam), c0, c1)
    for t in (0.0, 0.05):  # the second frame starts from the first frame's depths
        tr = trk.process(CameraFrame(t, image=left, image_right=right), t)
        assert len(tr.ids_right) > 0.8 * len(tr)
        assert set(tr.ids_right.tolist()) <= set(tr.ids.tolist())
        _, ia, ib = np.intersect1d(tr.ids, tr.ids_right, return_indices=True)
        du = tr.uv_px[ia] - tr.uv_px_right[ib]
        inner = (tr.uv_px[ia, 0] > 20) & (tr.uv_px[ia, 0] < 300)
        np.testing.assert_allclose(np.median(du[inner], axis=0), [disparity, 0.0], atol=0.05)
        np.testing.assert_allclose(tr.xy_norm_right, cam.undistort_points(tr.uv_px_right), atol=1e-12)


# ------------------------------------------------------------------------------------------ Jacobians
def _toed_rig():
    cam = PinholeCamera.from_fovy(320, 240, 70.0)
    R_fwd = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    c1 = CameraCalibration(cam, R_fwd @ exp_so3(np.array([0.02, 0.05, -0.01])), np.array([0.08, -0.05, 0.01]))
    c0 = CameraCalibration(cam, R_fwd, np.array([0.08, 0.05, 0.0]))
    return c0, c1


def _project(R_WB, p_WB, calib, p_W):
    p_C = calib.R_BC.T @ (R_WB.T @ (p_W - p_WB) - calib.p_BC)
    return p_C[:2] / p_C[2]


def _numeric_pose_and_point(R_WB, p_WB, calib, p_W, eps=1e-6):
    """Central differences of the cam projection w.r.t. ``[dtheta, dp]`` (R = R Exp(dtheta)) and ``p_W``."""
    J_pose, J_pt = np.zeros((2, 6)), np.zeros((2, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        J_pose[:, i] = (
            _project(R_WB @ exp_so3(d), p_WB, calib, p_W) - _project(R_WB @ exp_so3(-d), p_WB, calib, p_W)
        ) / (2 * eps)
        J_pose[:, 3 + i] = (_project(R_WB, p_WB + d, calib, p_W) - _project(R_WB, p_WB - d, calib, p_W)) / (
            2 * eps
        )
        J_pt[:, i] = (_project(R_WB, p_WB, calib, p_W + d) - _project(R_WB, p_WB, calib, p_W - d)) / (2 * eps)
    return J_pose, J_pt


def test_cam1_reprojection_jacobians_match_central_differences():
    """Window factor and MSCKF view Jacobians of cam1 (its own toed-out extrinsics) vs central differences."""
    c0, c1 = _toed_rig()
    rng = np.random.default_rng(5)
    R_WB = exp_so3(rng.normal(0.0, 0.3, 3))
    p_WB = rng.normal(0.0, 0.5, 3)
    p_W = p_WB + R_WB @ np.array([3.0, 0.4, -0.3])  # ~3 m ahead of the head
    J_pose_num, J_pt_num = _numeric_pose_and_point(R_WB, p_WB, c1, p_W)
    z, depth, J_pose, J_pt = reprojection(R_WB[None], p_WB[None], p_W[None], c1.R_BC, c1.p_BC)
    np.testing.assert_allclose(z[0], _project(R_WB, p_WB, c1, p_W), atol=1e-14)
    np.testing.assert_allclose(J_pose[0], J_pose_num, atol=1e-7)
    np.testing.assert_allclose(J_pt[0], J_pt_num, atol=1e-7)
    # MSCKF: views [cam0 clones..., cam1 clones...]; cam1's rows use cam1's extrinsics, no extrinsic column.
    st = SimpleNamespace(R_BC=c0.R_BC, p_BC=c0.p_BC)
    R2 = np.stack([np.eye(3), R_WB])
    p2 = np.stack([np.zeros(3), p_WB])
    jac = _stacked_jacobian(R2, p2, st, c1, p_W[None])
    assert jac.H_pose.shape == (1, 4, 2, 6)
    np.testing.assert_allclose(jac.z_norm[0, 3], _project(R_WB, p_WB, c1, p_W), atol=1e-14)
    np.testing.assert_allclose(jac.H_pose[0, 3], J_pose_num, atol=1e-7)
    np.testing.assert_allclose(jac.H_feature[0, 3], J_pt_num, atol=1e-7)
    np.testing.assert_array_equal(jac.H_extrinsic[0, 2:], 0.0)
    J0_pose, J0_pt = _numeric_pose_and_point(R_WB, p_WB, c0, p_W)
    np.testing.assert_allclose(jac.H_pose[0, 1], J0_pose, atol=1e-7)
    np.testing.assert_allclose(jac.H_feature[0, 1], J0_pt, atol=1e-7)


# --------------------------------------------------------------------------------- mono stays mono
@pytest.mark.parametrize("name", ["msckf", "window"])
def test_stereo_estimator_on_mono_frames_is_bit_identical_to_mono(name):
    """Given cam1's calibration but frames without right data, every estimate equals the mono one exactly."""
    runs = []
    for right in (False, True):
        world = LookAroundWorld(np.random.default_rng(7), n_landmarks=400)
        est = make_estimator(
            name,
            world.calib0,
            ImuNoise(),
            frontend="sim",
            params=SIM_MSCKF,
            window_params=SIM_WINDOW,
            calib_right=world.calib1 if right else None,
        )
        rows = run_look_around(est, world, seed=1, seconds=1.5, stereo=False)
        runs.append(np.array([e for _, e in rows]))
    np.testing.assert_array_equal(runs[0], runs[1])


# -------------------------------------------------------------------------------- look around in place
@pytest.fixture(scope="module")
def look_around_msckf():
    out = {}
    for stereo in (False, True):
        world = LookAroundWorld(np.random.default_rng(7))
        est = MsckfEstimator(
            world.calib0, ImuNoise(), SIM_MSCKF, calib_right=world.calib1 if stereo else None
        )
        out[stereo] = (run_look_around(est, world, seed=3, seconds=6.0, stereo=stereo), est)
    return out


def test_stereo_msckf_beats_mono_looking_around(look_around_msckf):
    """Measured over 6 s, ATE mono / stereo (mm): seed 3 21.6 / 9.4, seed 4 15.6 / 6.8, seed 5 20.3 / 7.4."""
    ate_mono, ate_stereo = (_ate_m(look_around_msckf[s][0]) for s in (False, True))
    est = look_around_msckf[True][1]
    assert not est.health().diverged
    assert est.last_stats.used > 0
    assert ate_stereo < 0.6 * ate_mono
    assert ate_stereo < 0.015


def test_stereo_window_beats_mono_looking_around():
    """Measured over 3 s, ATE mono / stereo (mm): seed 3 6.5 / 5.0, seed 4 8.0 / 5.1, seed 5 21.2 / 3.0.

    (Before the window's rotation-compensated keyframing, which makes a keyframe of every 3rd frame of a
    turn in place instead of nearly every frame: 12.5 / 5.7, 5.0 / 3.8, 9.7 / 3.4.)
    """
    ates: dict[bool, list[float]] = {False: [], True: []}
    for seed in (3, 5):  # one seed is one draw: the mono error varies 3x between seeds
        for stereo in (False, True):
            world = LookAroundWorld(np.random.default_rng(7), n_landmarks=600)
            est = WindowEstimator(
                world.calib0, ImuNoise(), SIM_WINDOW, calib_right=world.calib1 if stereo else None
            )
            ates[stereo].append(_ate_m(run_look_around(est, world, seed=seed, seconds=3.0, stereo=stereo)))
            assert not est.health().diverged
    assert sum(ates[True]) < 0.6 * sum(ates[False]), ates
    assert max(ates[True]) < 0.01, ates


# ------------------------------------------------------------------------------------- rendered images
@pytest.mark.slow
def test_stereo_msckf_on_rendered_headset_images_beats_mono():
    """The headset's two cameras rendered in the textured room while the head looks around (KLT front end).

    Measured (6 s, 320x240, seed 3): ATE mono 27.8 mm, stereo 13.8 mm.
    """
    import os

    os.environ.setdefault("MUJOCO_GL", "egl")
    from viotb.envs.sim.render import OffscreenRenderer, camera_calibration, rgb_to_gray
    from viotb.envs.sim.simulation import Simulation
    from viotb.models.constants import HEAD_BODY, HEADSET_CAMERAS

    sim = Simulation("headset", "textured_room")
    c0, c1 = (camera_calibration(sim.model, name, HEAD_BODY, 320, 240) for name in HEADSET_CAMERAS)
    world = LookAroundWorld(np.random.default_rng(0))
    world.calib0, world.calib1 = c0, c1
    frames: dict[float, list[np.ndarray]] = {}
    with OffscreenRenderer(sim.model, 320, 240, camera=HEADSET_CAMERAS[0]) as renderer:

        def render(t: float) -> list[np.ndarray]:
            key = round(t, 6)
            if key not in frames:
                R, p, *_ = world.pose(t)
                sim.set_pose(R, p)
                frames[key] = [
                    np.clip(np.rint(rgb_to_gray(renderer.render_rgb(sim.data, camera=c))), 0, 255).astype(
                        np.uint8
                    )
                    for c in HEADSET_CAMERAS
                ]
            return frames[key]

        ates = {}
        for stereo in (False, True):
            est = MsckfEstimator(
                c0, ImuNoise(), MsckfParams(frontend="klt"), calib_right=c1 if stereo else None
            )

            def frame_of(t: float, stereo: bool = stereo) -> CameraFrame:
                left, right = render(t)
                return CameraFrame(t_s=t, image=left, image_right=right if stereo else None)

            ates[stereo] = _ate_m(
                run_look_around(est, world, seed=3, seconds=6.0, stereo=stereo, frame_of=frame_of)
            )
            assert not est.health().diverged
    assert ates[True] < 0.6 * ates[False], ates
    assert ates[True] < 0.02, ates
