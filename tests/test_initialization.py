"""Tests of vio/initialization.py: static init (synthetic, real EuRoC), dynamic visual-inertial alignment."""

import numpy as np
import pytest
from data_paths import EUROC_MICRO
from scipy.spatial.transform import Rotation
from viotb.vio.camera import CameraCalibration, PinholeCamera
from viotb.vio.initialization import InertialInitializer, InitParams, rotation_from_gravity
from viotb.vio.lie import log_so3, quat_wxyz_to_rotmat
from viotb.vio.types import GRAVITY_M_S2, ImuNoise, ImuSample, gravity_W

EUROC = EUROC_MICRO / "mav0"
IMU_RATE_HZ = 200.0
CAM_RATE_HZ = 20.0
# Camera looks along body +x: x_C = -y_B, y_C = -z_B, z_C = +x_B.
R_BC = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
P_BC = np.array([0.05, -0.02, 0.01])
CALIB = CameraCalibration(PinholeCamera.from_fovy(640, 480, 70.0), R_BC, P_BC)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.rad2deg(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


# ----------------------------------------------------------------------------------------- static
def test_rotation_from_gravity_levels_and_zero_yaw():
    rng = np.random.default_rng(0)
    for up in rng.normal(size=(20, 3)):
        R = rotation_from_gravity(up)
        np.testing.assert_allclose(R.T @ [0.0, 0.0, 1.0], up / np.linalg.norm(up), atol=1e-12)
        assert abs(R[1, 0]) < 1e-12 and R[0, 0] >= 0.0  # yaw 0
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="up_B"):
        rotation_from_gravity(np.zeros(3))


def test_static_init_on_synthetic_still_imu():
    rng = np.random.default_rng(0)
    noise = ImuNoise()
    R_WB_true = Rotation.from_euler("ZYX", [1.0, 0.15, -0.1]).as_matrix()
    bg_true = np.array([0.003, -0.02, 0.01])
    f_B = R_WB_true.T @ (-gravity_W())
    dt = 1.0 / IMU_RATE_HZ
    sg = noise.gyro_noise_density_rad_s_sqrthz / np.sqrt(dt)
    sa = noise.accel_noise_density_m_s2_sqrthz / np.sqrt(dt)
    init = InertialInitializer(CALIB, noise, InitParams(window_s=1.0))
    assert init.try_initialize() is None and "waiting" in init.last_failure
    n = 400
    for k in range(n):
        init.feed_imu(ImuSample(k * dt, bg_true + sg * rng.normal(size=3), f_B + sa * rng.normal(size=3)))
    assert init.is_still()
    res = init.try_initialize()
    assert res is not None and res.method == "static"
    # Tilt: angle between the estimated and true "up" in B within 0.1 deg.
    assert _angle_deg(res.R_WB.T @ [0, 0, 1], R_WB_true.T @ [0, 0, 1]) < 0.1
    # Gyro bias within 4 sigma of the mean of ~200 samples.
    assert np.all(np.abs(res.gyro_bias_rad_s - bg_true) < 4 * sg / np.sqrt(200))
    np.testing.assert_array_equal(res.v_WB, 0.0)
    assert res.gravity_norm_m_s2 == pytest.approx(GRAVITY_M_S2, abs=0.01)
    assert res.cov_diag.shape == (15,) and np.all(res.cov_diag > 0.0)


def test_static_init_recovers_the_accel_bias_along_gravity_only():
    rng = np.random.default_rng(1)
    noise = ImuNoise()
    R_WB_true = Rotation.from_euler("ZYX", [0.3, 0.05, 0.08]).as_matrix()
    ba_true = np.array([0.04, -0.03, 0.06])
    up_B = R_WB_true.T @ [0, 0, 1]
    dt = 1.0 / IMU_RATE_HZ
    sa = noise.accel_noise_density_m_s2_sqrthz / np.sqrt(dt)
    init = InertialInitializer(CALIB, noise, InitParams(window_s=1.0))
    for k in range(400):
        f_B = R_WB_true.T @ (-gravity_W()) + ba_true + sa * rng.normal(size=3)
        init.feed_imu(ImuSample(k * dt, 1e-4 * rng.normal(size=3), f_B))
    res = init.try_initialize()
    assert res is not None and res.method == "static"
    # The component along gravity: |f| - g = up . ba to first order (the horizontal part tilts "up" instead).
    expected = float(np.linalg.norm(R_WB_true.T @ (-gravity_W()) + ba_true)) - GRAVITY_M_S2
    assert float(res.accel_bias_m_s2 @ up_B) == pytest.approx(float(up_B @ ba_true), abs=2e-3)
    mean_sigma = 4 * sa / np.sqrt(200)
    assert float(np.linalg.norm(res.accel_bias_m_s2)) == pytest.approx(abs(expected), abs=mean_sigma)
    # Nothing is claimed across gravity.
    horizontal = res.accel_bias_m_s2 - (res.accel_bias_m_s2 @ res.R_WB.T[:, 2]) * res.R_WB.T[:, 2]
    assert np.linalg.norm(horizontal) < 1e-12


def _load_euroc_window(t0: float, t1: float):
    imu = np.loadtxt(EUROC / "imu0" / "data.csv", delimiter=",", comments="#")
    gt = np.loadtxt(EUROC / "state_groundtruth_estimate0" / "data.csv", delimiter=",", comments="#")
    t_imu = imu[:, 0] * 1e-9
    t_gt = gt[:, 0] * 1e-9
    sel_imu = (t_imu >= t0) & (t_imu <= t1)
    sel_gt = (t_gt >= t0) & (t_gt <= t1)
    return t_imu[sel_imu], imu[sel_imu], gt[sel_gt]


@pytest.mark.skipif(not EUROC.exists(), reason="EuRoC micro dataset not present")
def test_static_init_on_real_euroc_micro():
    t0, t1 = 1403715273.262, 1403715277.95
    t_imu, imu, gt = _load_euroc_window(t0, t1)
    init = InertialInitializer(CALIB, ImuNoise(), InitParams(window_s=t1 - t0 - 0.01))
    for t, row in zip(t_imu, imu, strict=True):
        init.feed_imu(ImuSample(float(t), row[1:4], row[4:7]))
    res = init.try_initialize()
    assert res is not None, init.last_failure
    assert res.method == "static"
    assert res.gravity_norm_m_s2 == pytest.approx(GRAVITY_M_S2, abs=0.1)
    # Roll/pitch: the world up axis seen in B, estimated vs ground truth (q_RS_wxyz columns 4..7).
    up_B_est = res.R_WB.T @ [0.0, 0.0, 1.0]
    for q in gt[:, 4:8]:
        assert _angle_deg(up_B_est, quat_wxyz_to_rotmat(q).T @ [0.0, 0.0, 1.0]) < 1.0
    np.testing.assert_allclose(res.gyro_bias_rad_s, gt[:, 11:14].mean(axis=0), atol=2e-3)


# ---------------------------------------------------------------------------------------- dynamic
def _truth(t: np.ndarray, excited: bool):
    """Position (m), velocity, acceleration (m/s^2) in W and R_WB for an excited or constant-velocity path."""
    t = np.atleast_1d(t)
    v_const = np.array([0.8, 0.1, 0.05])
    if not excited:
        p = v_const * t[:, None]
        return p, np.tile(v_const, (t.size, 1)), np.zeros((t.size, 3)), np.stack([np.eye(3)] * t.size)
    amp = np.array([0.6, 0.5, 0.3])
    w = np.array([2.2, 1.7, 2.6])
    ph = np.array([0.0, 0.4, 1.0])
    p = v_const * t[:, None] + amp * np.sin(w * t[:, None] + ph)
    v = v_const + amp * w * np.cos(w * t[:, None] + ph)
    a = -amp * w**2 * np.sin(w * t[:, None] + ph)
    eul = np.column_stack([0.3 * np.sin(1.1 * t), 0.2 * np.sin(1.4 * t + 0.3), 0.25 * np.sin(0.9 * t + 1.0)])
    R = Rotation.from_euler("ZYX", eul).as_matrix()
    return p, v, a, R


def _imu_samples(t_end: float, excited: bool, bg: np.ndarray) -> list[ImuSample]:
    """Noise-free IMU at 200 Hz: instantaneous readings at the sample times.

    As the IMU model and real IMUs give them; the estimators interpolate between samples.
    """
    dt, h = 1.0 / IMU_RATE_HZ, 1e-5
    out = []
    for t in np.arange(0.0, t_end + 1e-9, dt):
        _, _, a, R = _truth(np.array([t]), excited)
        _, _, _, R0 = _truth(np.array([t - h]), excited)
        _, _, _, R1 = _truth(np.array([t + h]), excited)
        gyro = log_so3(R0[0].T @ R1[0]) / (2.0 * h)  # body rate at t (central difference)
        accel = R[0].T @ (a[0] - gravity_W())
        out.append(ImuSample(float(t), gyro + bg, accel))
    return out


def _feed_synthetic(
    init: InertialInitializer,
    t_end: float,
    excited: bool,
    bg: np.ndarray,
    rng,
    try_each_frame: bool = False,
    failures: list[str] | None = None,
):
    """Feed the synthetic IMU and features.

    With ``try_each_frame``, try to initialize after every frame and return the first result (None if none).
    """
    landmarks_W = np.column_stack(
        [rng.uniform(4.0, 8.0, 150), rng.uniform(-4.0, 4.0, 150), rng.uniform(-2.0, 3.0, 150)]
    )
    imu = _imu_samples(t_end, excited, bg)
    frame_times = np.arange(0.0, t_end + 1e-9, 1.0 / CAM_RATE_HZ)
    fi = 0
    for s in imu:
        init.feed_imu(s)
        while fi < frame_times.size and frame_times[fi] <= s.t_s + 1e-12:
            p, _, _, R = _truth(np.array([frame_times[fi]]), excited)
            R_WC = R[0] @ R_BC
            p_WC = p[0] + R[0] @ P_BC
            p_C = (landmarks_W - p_WC) @ R_WC
            xy = p_C[:, :2] / p_C[:, 2:3]
            ok = (p_C[:, 2] > 0.5) & (np.abs(xy[:, 0]) < 0.7) & (np.abs(xy[:, 1]) < 0.5)
            noisy = xy[ok] + (0.5 / CALIB.camera.fx) * rng.normal(size=(int(ok.sum()), 2))  # 0.5 px
            init.feed_features(float(frame_times[fi]), np.flatnonzero(ok), noisy)
            fi += 1
            if try_each_frame and (res := init.try_initialize()) is not None:
                return res
            if failures is not None and try_each_frame:
                failures.append(init.last_failure)
    return None


def _synthetic_window(rng: np.random.Generator, max_frames: int, min_obs: int, max_tracks: int):
    """The dynamic alignment's window (``init_dynamic._Window``) over 1 s of the excited synthetic scene."""
    from viotb.vio.init_dynamic import _Window, select_tracks
    from viotb.vio.init_preintegration import preintegrate_to

    init = InertialInitializer(CALIB, ImuNoise(), InitParams(window_s=1.0))
    _feed_synthetic(init, 1.0, True, np.zeros(3), rng)
    times, tracks = select_tracks(init._window_frames(), max_frames, min_obs, max_tracks)
    pims, _ = preintegrate_to(list(init._imu), times, times[-1], ImuNoise())
    return _Window(times, tracks, pims, CALIB)


def test_dynamic_init_recovers_velocity_gravity_scale_and_gyro_bias():
    rng = np.random.default_rng(0)
    bg_true = np.array([0.01, -0.015, 0.02])
    t_end = 2.5  # a 1.5 s window leaves the scale sigma at 0.7 % with the accelerometer bias unknown
    init = InertialInitializer(CALIB, ImuNoise(), InitParams(window_s=1.5))
    _feed_synthetic(init, t_end, True, bg_true, rng)
    assert not init.is_still()
    assert init.excitation_m_s2() > 1.0
    res = init.try_initialize()
    assert res is not None, init.last_failure
    assert res.method == "dynamic"
    t_last = res.t_s
    _, v_true, _, R_true = _truth(np.array([t_last]), True)
    # Velocity in the true body frame (frame-independent of the yaw gauge) within 5 %.
    v_B_est = res.R_WB.T @ res.v_WB
    v_B_true = R_true[0].T @ v_true[0]
    assert np.linalg.norm(v_B_est - v_B_true) < 0.05 * np.linalg.norm(v_B_true)
    # Scale: velocity norm within 2 %.
    assert abs(np.linalg.norm(res.v_WB) / np.linalg.norm(v_true[0]) - 1.0) < 0.02
    # Gravity direction in B: the accelerometer bias is estimated under its 0.1 m/s^2 prior, and over a short
    # window its horizontal part trades with the tilt (0.1 / 9.81 rad = 0.58 deg, 1 sigma): within 3 sigma.
    assert _angle_deg(res.R_WB.T @ [0, 0, 1], R_true[0].T @ [0, 0, 1]) < 1.75
    # Gyro bias refined by the Gauss-Newton step.
    np.testing.assert_allclose(res.gyro_bias_rad_s, bg_true, atol=3e-3)
    assert res.gravity_norm_m_s2 == pytest.approx(GRAVITY_M_S2, rel=0.05)
    # The observability test passed: the reported scale sigma is below the limit.
    assert 0.0 < res.scale_sigma <= InitParams().max_scale_sigma
    assert init.last_result is res


def test_moving_start_initializes_early_frame_by_frame_against_truth():
    """A start in motion, tried after every frame (as the estimators do).

    It initializes as soon as the window determines the scale (scale sigma 0.5 %, the accelerometer bias
    unknown within 0.1 m/s^2), here 2.2 s after the first image, with the scale within 2 %.
    """
    rng = np.random.default_rng(3)
    bg_true = np.array([-0.01, 0.005, 0.015])
    init = InertialInitializer(CALIB, ImuNoise(), InitParams(window_s=1.5))
    res = _feed_synthetic(init, 3.0, True, bg_true, rng, try_each_frame=True)
    assert res is not None and res.method == "dynamic", init.last_failure
    assert 1.5 < res.t_s <= 2.5  # the first image is at t = 0; the 1.5 s is not met here
    _, v_true, _, R_true = _truth(np.array([res.t_s]), True)
    assert abs(np.linalg.norm(res.v_WB) / np.linalg.norm(v_true[0]) - 1.0) < 0.02
    assert np.linalg.norm(res.R_WB.T @ res.v_WB - R_true[0].T @ v_true[0]) < 0.05 * np.linalg.norm(v_true[0])
    assert _angle_deg(res.R_WB.T @ [0, 0, 1], R_true[0].T @ [0, 0, 1]) < 1.75  # 3 sigma of the ba-tilt trade


def test_dynamic_init_refuses_constant_velocity_as_scale_unobservable():
    """Constant velocity: the images fix the trajectory only up to scale, the IMU sees only gravity.

    The initializer must refuse (and keep refusing frame after frame), not guess.
    """
    rng = np.random.default_rng(0)
    init = InertialInitializer(CALIB, ImuNoise(), InitParams(window_s=1.5))
    failures: list[str] = []
    res = _feed_synthetic(init, 1.5, False, np.zeros(3), rng, try_each_frame=True, failures=failures)
    assert not init.is_still()  # features move: parallax rules out "still"
    tried = [f for f in failures if "waiting" not in f]
    # Every frame from 0.5 s to 1.5 s reports a refusal (a dynamic try on every second frame).
    assert res is None and len(tried) == 21
    # Refused: the scale is not determined, or no scale fits (the free |g| or the reprojection RMS).
    assert all("not observable" in f or "reprojection RMS" in f or "|g|" in f for f in tried)


def test_no_dynamic_guess_before_the_static_window_at_rest():
    """At rest with half a window: no parallax, so no dynamic attempt (the static path waits)."""
    rng = np.random.default_rng(2)
    init = InertialInitializer(CALIB, ImuNoise(), InitParams(window_s=1.5))
    f_B = -gravity_W()
    for k in range(int(0.8 * IMU_RATE_HZ)):
        t = k / IMU_RATE_HZ
        init.feed_imu(ImuSample(t, 1e-4 * rng.normal(size=3), f_B + 1e-3 * rng.normal(size=3)))
        if k % 10 == 0:
            init.feed_features(
                t, np.arange(40), np.tile([[0.1, -0.05]], (40, 1)) + 1e-4 * rng.normal(size=(40, 2))
            )
    assert init.try_initialize() is None
    assert "parallax" in init.last_failure


def test_trajectory_scale_functional_is_linear_in_the_scale():
    """L(s p) = s L(p) for the window's trajectory length; dL/dx against finite differences."""
    from viotb.vio.init_dynamic import _trajectory_scale

    rng = np.random.default_rng(0)
    p_k = np.vstack([np.zeros(3), rng.normal(size=(6, 3))])
    L, _ = _trajectory_scale(p_k, np.zeros((7, 3, 1)))
    assert _trajectory_scale(1.03 * p_k, np.zeros((7, 3, 1)))[0] == pytest.approx(1.03 * L, rel=1e-12)
    # x moves every frame by t_k * x (a velocity): dL/dx against a central difference.
    t = np.linspace(0.0, 1.0, 7)
    J = t[:, None, None] * np.eye(3)[None]
    _, w = _trajectory_scale(p_k, J)
    for i in range(3):
        d = 1e-6 * np.eye(3)[i]
        num = (
            _trajectory_scale(p_k + t[:, None] * d, J)[0] - _trajectory_scale(p_k - t[:, None] * d, J)[0]
        ) / 2e-6
        assert w[i] == pytest.approx(num, rel=1e-6, abs=1e-9)


def test_refinement_jacobians_match_finite_differences():
    """The analytic reprojection Jacobians of the refinement against central differences."""
    from viotb.vio.init_refine import reprojection

    rng = np.random.default_rng(1)
    win = _synthetic_window(rng, 6, 4, 10)
    R_g = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    pf = rng.uniform(3.0, 6.0, (win.n_f, 3)) * [1.0, 0.3, 0.3]
    for bg_on in (0.0, 1.0):
        z = np.array(
            [0.5, -0.2, 0.1, 0.02, -0.03, 0.01 * bg_on, -0.02 * bg_on, 0.015 * bg_on, 0.05, -0.08, 0.03]
        )
        _, Jg, _ = reprojection(win, z, pf, R_g, 1.0)
        for i in range(11):
            d = 1e-6 * np.eye(11)[i]
            num = (
                reprojection(win, z + d, pf, R_g, 1.0)[0] - reprojection(win, z - d, pf, R_g, 1.0)[0]
            ) / 2e-6
            err = np.max(np.abs(Jg[:, :, i] - num)) / np.max(np.abs(num))
            # Exact but for the gyro-bias columns at a non-zero bias: there they are first order in
            # Exp(J (bg + d)) ~ Exp(J bg) Exp(J d) (the right Jacobian of J bg, ~0.02 rad here, is dropped).
            assert err < (0.03 if 5 <= i < 8 and bg_on else 1e-6), (bg_on, i, err)
    r, Jg, Jf = reprojection(win, z, pf, R_g, 1.0)
    for a in range(3):
        d = np.zeros_like(pf)
        d[:, a] = 1e-6
        num = (reprojection(win, z, pf + d, R_g, 1.0)[0] - reprojection(win, z, pf - d, R_g, 1.0)[0]) / 2e-6
        np.testing.assert_allclose(Jf[:, :, a], num, rtol=1e-4, atol=1e-6)


def test_dynamic_init_returns_none_without_features():
    init = InertialInitializer(CALIB, ImuNoise(), InitParams(window_s=1.5, still_max_disparity=-1.0))
    for k, s in enumerate(_imu_samples(1.5, True, np.zeros(3))):
        init.feed_imu(s)
        if k % 10 == 0:  # 20 Hz frames of only 5 features (moving: parallax)
            init.feed_features(s.t_s, np.arange(5), np.full((5, 2), 0.02 * s.t_s))
    assert init.try_initialize() is None
    assert "features" in init.last_failure


def test_bad_input_errors():
    init = InertialInitializer(CALIB)
    init.feed_imu(ImuSample(1.0, np.zeros(3), np.array([0, 0, 9.81])))
    with pytest.raises(ValueError, match="t_s"):
        init.feed_imu(ImuSample(0.5, np.zeros(3), np.array([0, 0, 9.81])))
    with pytest.raises(ValueError, match="xy_norm"):
        init.feed_features(1.0, np.arange(3), np.zeros((2, 2)))
