"""Dynamic (visual-inertial) initialization with an observability test: accept only a determined scale.

The solve follows open_vins' ``DynamicInitializer`` (Dong-Si & Mourikis, "Estimator initialization in
vision-aided inertial navigation with unknown camera-IMU calibration", IROS 2012; Kaiser, Martinelli et al.,
"Simultaneous state initialization and gyroscope bias calibration in visual inertial aided navigation",
RA-L 2017). With gyro-preintegrated rotations the position of body frame k in the first body frame B0 is
``p_k = v0 t_k + 1/2 g0 t_k^2 + dp_0k`` (Forster 2017 eq. 33 written in B0), so each bearing ``(x, y)``
of feature f in camera k gives two equations linear in ``(v0, g0, p_f)``::

    [[1, 0, -x], [0, 1, -y]] R_CkB0 (p_f - v0 t_k - 1/2 g0 t_k^2) = [[1, 0, -x], [0, 1, -y]] R_CkB0 c_k

with ``c_k = dp_0k + dR_0k p_BC``.

Steps of :func:`dynamic_alignment`:

1. Frames (evenly subsampled) and the features tracked in enough of them.
2. Zero-bias preintegration from the first frame to every frame and to the newest IMU sample
   (:class:`~viotb.vio.init_preintegration.RunningPreintegration`, kept between tries; readings
   interpolated linearly between samples, as the propagator does, each applied at its step's midpoint
   rotation).
3. The linear system, solved twice with the features eliminated by the Schur complement: the second time
   each observation's two rows are divided by the feature depth of the first solution, so that the
   residuals are normalized image errors.
4. ``|g0|`` must be near 9.81 (VINS-Mono's ``LinearAlignment`` test; open_vins checks it as well).
5. ``|g| = 9.81`` enforced, ``v0, p_f`` re-solved with gravity fixed.
6. Levenberg-Marquardt on the normalized reprojection errors over ``(v0, gravity direction, gyro bias,
   accelerometer bias, p_f)`` (:mod:`viotb.vio.init_refine`), the features eliminated by the Schur
   complement, the biases entering through the preintegration bias Jacobians (Forster eq. 44), the
   accelerometer bias with a zero-mean prior (``sigma_accel_bias_m_s2``, as open_vins' MLE step has one):
   over a short window its vertical part acts like an error of ``|g|`` and scales the trajectory, so it
   must be in the covariance of the scale.
7. Observability of the window, instead of a fixed accelerometer-excitation threshold: the first-order
   covariance of the estimate (:func:`_observability`) from the image noise (the reduced information,
   noise the residual RMS, at least ``pixel_sigma_px``, with the bias prior) and from the IMU
   (:mod:`viotb.vio.init_dynamic_cov`: preintegration noise, bias random walk, and the scale-factor and
   misalignment errors that the initializer does not calibrate), propagated through the solve. The relative
   1-sigma of the metric scale (the larger of those of the trajectory length, :func:`_trajectory_scale`,
   and of the speed at the newest sample) and the 1-sigma of the gravity direction at the newest sample
   must be below ``max_scale_sigma`` / ``max_tilt_sigma_rad``. Constant velocity, rest or pure rotation
   leave the scale undetermined: the window is refused, not guessed. open_vins gates on the rotation angle
   (``init_dyn_min_deg``) and on the reciprocal condition number of the information matrix
   (``init_dyn_min_rec_cond``), VINS-Mono on the accelerometer variance and ``s > 0``; the scale sigma is
   the quantity those stand in for. Then the reprojection RMS, and the state at the newest IMU sample with
   the covariance of step 7.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.init_dynamic_cov import preintegration_error_cov
from viotb.vio.init_preintegration import RunningPreintegration
from viotb.vio.init_refine import (
    N_GLOBAL,
    frame_poses,
    globals_of,
    normal_equations,
    refine,
    reprojection,
    schur_step,
)
from viotb.vio.lie import skew
from viotb.vio.types import GRAVITY_M_S2, ImuNoise, ImuSample
from viotb.vio.update_helpers import random_walk_whitener, track_path_px

Frame = tuple[float, np.ndarray, np.ndarray]
"""One frame of features: ``(t_s, ids (M,), xy_norm (M, 2))``."""


def select_tracks(frames: list[Frame], max_frames: int, min_obs: int, max_features: int):
    """Frames (evenly subsampled to ``max_frames``) and tracks: ``(times, {id: [(frame index, xy)]})``.

    Only features seen in at least ``min_obs`` of the kept frames enter, the ``max_features`` longest.
    """
    if len(frames) > max_frames:
        idx = np.round(np.linspace(0, len(frames) - 1, max_frames)).astype(int)
        frames = [frames[i] for i in idx]
    tracks: dict[int, list[tuple[int, np.ndarray]]] = {}
    for k, (_, ids, xy) in enumerate(frames):
        for fid, obs in zip(ids, xy, strict=True):
            tracks.setdefault(int(fid), []).append((k, obs))
    tracks = {fid: obs for fid, obs in tracks.items() if len(obs) >= min_obs}
    longest = sorted(tracks, key=lambda f: -len(tracks[f]))[:max_features]
    return [f[0] for f in frames], {fid: tracks[fid] for fid in sorted(longest)}


def _trajectory_scale(p_k: np.ndarray, dp_dx: np.ndarray) -> tuple[float, np.ndarray]:
    """The window's metric scale as a linear functional: ``L = sum_k e_k . p_k`` and ``dL/dx``.

    ``e_k`` is the unit direction of ``p_k - p_0`` (``p_0 = 0``), so ``L`` is the summed distance of the
    frames from the first; scaling the trajectory by ``1 + s`` changes ``L`` by ``s L``, so
    ``sigma_L / L`` is the relative sigma of the scale. Unlike a mean feature depth it carries no
    per-feature triangulation noise.

    Args:
        p_k: Frame positions in B0 (m), shape (K, 3), ``p_k[0] = 0``.
        dp_dx: Their Jacobians, shape (K, 3, n).
    """
    dist = np.linalg.norm(p_k, axis=1)
    moved = dist > 1e-9
    e = np.zeros_like(p_k)
    e[moved] = p_k[moved] / dist[moved, None]
    return float(np.sum(dist)), np.einsum("ki,kin->n", e, dp_dx)


def _tilt_sigma_rad(cov_dir: np.ndarray) -> float:
    """Largest 1-sigma (rad) of a 2x2 gravity-direction (tangent) covariance; inf if not finite."""
    if not np.all(np.isfinite(cov_dir)):
        return float("inf")
    return float(np.sqrt(max(float(np.max(np.linalg.eigvalsh(0.5 * (cov_dir + cov_dir.T)))), 0.0)))


class _Window:
    """The arrays of one dynamic solve: observations, preintegrated frames, calibration.

    With ``rw_to_white_var`` > 0 a track's image error is white plus a random walk growing with the
    image path the feature has travelled (KLT's drift, ``KltParams.track_random_walk_px2_per_px``;
    ``q`` per px, relative to the white variance): ``whiten`` applies each feature's
    :func:`~viotb.vio.update_helpers.random_walk_whitener` (the MSCKF's model) to its rows, so that the
    refinement is generalized least squares and the covariance counts the correlated errors.
    """

    def __init__(self, times, tracks, pims, calib: CameraCalibration, rw_to_white_var: float = 0.0) -> None:
        self.fids = list(tracks)
        self.n_f = len(self.fids)
        self.obs_frame = np.array([k for fid in self.fids for k, _ in tracks[fid]])
        self.obs_feat = np.array([j for j, fid in enumerate(self.fids) for _ in tracks[fid]])
        self.obs_xy = np.array([xy for fid in self.fids for _, xy in tracks[fid]])
        # Observations are grouped by feature, in feature order: the first observation of each.
        self.feat_starts = np.flatnonzero(np.r_[True, np.diff(self.obs_feat) != 0])
        self.dts = np.array([t - times[0] for t in times])
        self.dR = np.stack([pm.delta_R for pm in pims])
        self.dp = np.stack([pm.delta_p for pm in pims])
        self.JR_bg = np.stack([pm.d_R_d_bg for pm in pims])
        self.Jp_bg = np.stack([pm.d_p_d_bg for pm in pims])
        self.Jp_ba = np.stack([pm.d_p_d_ba for pm in pims])
        self.R_BC = np.asarray(calib.R_BC, float)
        self.p_BC = np.asarray(calib.p_BC, float)
        self.W = None  # per-feature whitening (n_f, K, K), or None: white errors
        if rw_to_white_var > 0.0:
            n_k = len(times)
            xy = np.zeros((self.n_f, n_k, 2))
            mask = np.zeros((self.n_f, n_k), dtype=bool)
            xy[self.obs_feat, self.obs_frame] = self.obs_xy
            mask[self.obs_feat, self.obs_frame] = True
            path_px = track_path_px(xy, mask, np.full(n_k, float(calib.camera.fx)), n_k)
            self.W = random_walk_whitener(path_px, mask, np.zeros(n_k, dtype=int), rw_to_white_var)

    def whiten(self, a: np.ndarray, transpose: bool = False) -> np.ndarray:
        """Each feature's whitening ``W_f`` (or ``W_f^T``) applied to per-observation rows.

        Args:
            a: Rows of every observation, shape (n_obs, 2, ...) (one image axis at a time is whitened).
            transpose: Apply ``W_f^T`` instead (maps the sensitivities of whitened rows back onto the
                observations, step 7b).

        Returns:
            The same shape; ``a`` itself when the errors are white.
        """
        if self.W is None:
            return a
        pad = np.zeros((self.n_f, len(self.dts), *a.shape[1:]))
        pad[self.obs_feat, self.obs_frame] = a
        W = np.transpose(self.W, (0, 2, 1)) if transpose else self.W
        out = np.einsum("fuv,fv...->fu...", W, pad)
        return out[self.obs_feat, self.obs_frame]

    @property
    def n_obs(self) -> int:
        return int(self.obs_xy.shape[0])

    def linear_rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The linear system's two rows per observation, by blocks (step 3).

        Returns:
            ``(A_g (n_obs, 2, 6), A_f (n_obs, 2, 3), b (n_obs, 2))``: the columns of ``[v0, g0]`` and of the
            observation's feature ``p_f``, and the right-hand side.
        """
        k = self.obs_frame
        xy = self.obs_xy
        proj = np.zeros((self.n_obs, 2, 3))
        proj[:, 0, 0] = proj[:, 1, 1] = 1.0
        proj[:, :, 2] = -xy
        M = proj @ np.transpose(self.dR[k] @ self.R_BC, (0, 2, 1))  # (n, 2, 3)
        t = self.dts[k][:, None, None]
        A_g = np.concatenate([-M * t, -0.5 * M * t * t], axis=2)
        c = self.dp[k] + self.dR[k] @ self.p_BC
        return A_g, M, np.einsum("nij,nj->ni", M, c)

    def solve_linear(
        self, A_g: np.ndarray, A_f: np.ndarray, b: np.ndarray, weights: np.ndarray
    ) -> np.ndarray | None:
        """Weighted least squares of the block rows, features eliminated by the Schur complement.

        Args:
            A_g: Global columns, shape (n_obs, 2, G).
            A_f: Feature columns, shape (n_obs, 2, 3).
            b: Right-hand side, shape (n_obs, 2).
            weights: Row weight of each observation, shape (n_obs,).

        Returns:
            ``x = [globals (G), p_f (3 n_f)]``, or None when the reduced system is singular.
        """
        try:
            _, d_glob, d_feat = schur_step(*normal_equations(self, b, A_g, A_f, weights**2), 0.0)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(d_glob)):
            return None
        return -np.concatenate([d_glob, d_feat.ravel()])

    def obs_depths(self, x: np.ndarray) -> np.ndarray:
        """Depth (m) of every observation for the linear ``x``, shape (n_obs,)."""
        k, j = self.obs_frame, self.obs_feat
        t = self.dts[k][:, None]
        p_k = x[0:3] * t + 0.5 * x[3:6] * t * t + self.dp[k]
        p_f = x[6:].reshape(self.n_f, 3)[j]
        r = np.einsum("nij,j->ni", self.dR[k], self.R_BC[:, 2])
        return np.einsum("ni,ni->n", r, p_f - p_k - self.dR[k] @ self.p_BC)


def dynamic_alignment(
    samples: list[ImuSample],
    frames: list[Frame],
    calib: CameraCalibration,
    noise: ImuNoise,
    params,
    preintegration: RunningPreintegration | None = None,
):
    """Initialize from a moving window, or refuse.

    Args:
        samples: IMU samples covering the frames up to the newest sample (the state's time).
        frames: Feature frames of the window, in time order.
        calib: ``R_BC``, ``p_BC`` and the focal length (for the pixel-noise floor).
        noise: IMU noise densities (preintegration).
        params: :class:`~viotb.vio.initialization.InitParams`.
        preintegration: Reused between tries (snapshots at every frame of the window); None: a fresh one.

    Returns:
        ``(solution, failure)``: ``solution`` is a dict ``{t_s, v0, g, bg, ba, dR_end, dv_end, dp_end, T,
        g_norm, rms}`` in B0 with the entries of :func:`_observability`, or None with ``failure`` saying
        why.
    """
    p = params
    # 1. Frames and tracks.
    times, tracks = select_tracks(frames, p.max_frames, p.min_feature_obs, p.max_features)
    if len(times) < p.min_frames or len(tracks) < p.min_features:
        return None, (
            f"dynamic init needs {p.min_frames} frames and {p.min_features} features seen "
            f"{p.min_feature_obs} times; have {len(times)} frames, {len(tracks)} features"
        )
    # 2. Preintegration.
    t_end = samples[-1].t_s
    run = preintegration if preintegration is not None else RunningPreintegration(noise)
    every = [f[0] for f in frames if times[0] <= f[0] <= t_end]
    snaps, pim_end = run.snapshots(samples, every, t_end)
    by_time = dict(zip(every, snaps, strict=True))
    pims = [by_time[tk] for tk in times]
    win = _Window(times, tracks, pims, calib, p.track_random_walk_px2_per_px / p.pixel_sigma_px**2)
    sigma_floor = p.pixel_sigma_px / float(calib.camera.fx)

    # 3. Weighted linear solve (rows divided by the feature depth of the previous solution).
    A_g, A_f, b = win.linear_rows()
    weights = np.ones(win.n_obs)
    for _ in range(2):
        x_lin = win.solve_linear(A_g, A_f, b, weights)
        depths = win.obs_depths(x_lin) if x_lin is not None else np.full(win.n_obs, np.nan)
        if not np.all(np.isfinite(depths)):
            return None, "linear alignment failed (singular or non-finite solution)"
        weights = 1.0 / np.maximum(np.abs(depths), p.min_depth_m)
    g_lin = x_lin[3:6]
    g_norm = float(np.linalg.norm(g_lin))
    # 4. Gravity magnitude.
    if not np.isfinite(g_norm) or abs(g_norm / GRAVITY_M_S2 - 1.0) > p.max_gravity_norm_error:
        return None, f"linear alignment gave |g| = {g_norm:.3f} m/s^2 (weak excitation?)"
    # 5. Enforce |g| = 9.81 and re-solve v0, p_f with gravity fixed.
    g_dir0 = g_lin / g_norm
    x_fix = win.solve_linear(A_g[:, :, 0:3], A_f, b - A_g[:, :, 3:6] @ (GRAVITY_M_S2 * g_dir0), weights)
    if x_fix is None:
        return None, "linear alignment failed (singular with gravity fixed)"
    # 6. Levenberg-Marquardt on the reprojection errors, features eliminated by the Schur complement.
    tangent = np.linalg.svd(np.eye(3) - np.outer(g_dir0, g_dir0))[0][:, :2]  # (3, 2), orthogonal to g
    R_g = np.column_stack([tangent, g_dir0])  # maps e_z onto g_dir0
    z_glob = np.concatenate([x_fix[0:3], np.zeros(N_GLOBAL - 3)])
    pf = x_fix[3:].reshape(win.n_f, 3).copy()
    prior = np.zeros(N_GLOBAL)
    prior[8:11] = 1.0 / p.sigma_accel_bias_m_s2**2  # the residuals are whitened (units of sigma)
    z_glob, pf, S, rms = refine(win, R_g, z_glob, pf, sigma_floor, prior, p.max_refine_iterations)
    if not np.isfinite(rms) or rms > p.max_reprojection_rms:
        return None, f"refinement reprojection RMS {rms:.4f} > {p.max_reprojection_rms}"
    # 7. Observability: the covariance of the scale, the velocity and the gravity direction at the end.
    v0, g, bg, ba, _ = globals_of(z_glob, R_g)
    imu_cov = preintegration_error_cov(
        [*pims, pim_end], noise, p.imu_scale_sigma, p.imu_misalignment_sigma_rad
    )
    obs = _observability(win, [*pims, pim_end], z_glob, pf, R_g, sigma_floor, rms, prior, imu_cov)
    if not obs["scale_sigma"] <= p.max_scale_sigma or not obs["tilt_sigma_rad"] <= p.max_tilt_sigma_rad:
        return None, (
            f"scale/gravity not observable yet: scale sigma {100 * obs['scale_sigma']:.2f} % (trajectory "
            f"{100 * obs['length_sigma']:.2f} %, speed {100 * obs['speed_sigma']:.2f} %), tilt sigma "
            f"{np.rad2deg(obs['tilt_sigma_rad']):.2f} deg (window {win.dts[-1]:.2f} s)"
        )
    dR_end, dv_end, dp_end = pim_end.corrected(bg, ba)
    return {
        "t_s": t_end,
        "v0": v0,
        "g": g,
        "bg": bg,
        "ba": ba,
        "dR_end": dR_end,
        "dv_end": dv_end,
        "dp_end": dp_end,
        "T": pim_end.dt_s,
        "g_norm": g_norm,
        "rms": rms,
        **obs,
    }, ""


def _observability(win: _Window, pims, z_glob, pf, R_g, sigma: float, rms: float, prior, imu_cov):
    """Step 7: first-order covariance of the window's scale, end velocity, end "up" axis and biases.

    Two independent error sources (:mod:`viotb.vio.init_dynamic_cov`): the image noise (the residual RMS,
    at least ``sigma``), whose share is the inverse of the reduced information ``S + prior``; and the
    preintegration errors ``eta`` (white noise and bias random walk), which move the estimate by
    ``-info^-1 G eta`` (``G``: the reduced cross-information of the frame-pose errors) and enter the
    end state directly.

    Args:
        win: The window.
        pims: Preintegrations from the first frame to every frame and to the end, K + 1 of them.
        z_glob: Refined ``[v0, dg, bg, ba]``.
        pf: Refined feature positions (m), shape (n_f, 3).
        R_g: Gravity-direction chart.
        sigma: Image-noise floor (normalized coordinates).
        rms: Refined reprojection RMS (normalized coordinates).
        prior: Information of the zero-mean prior on ``z_glob`` (units of ``sigma``), shape (11,).
        imu_cov: Joint covariance of the errors of ``pims``, shape (9 (K + 1), 9 (K + 1))
            (:func:`~viotb.vio.init_dynamic_cov.preintegration_error_cov`).

    Returns:
        ``{scale_sigma, length_sigma, length_m, speed_sigma, tilt_sigma_rad, cov_v_B0 (3, 3),
        cov_bg (3, 3), cov_ba (3, 3)}``: ``scale_sigma`` the larger of the relative sigmas of the
        trajectory length (:func:`_trajectory_scale`) and of the end speed.
    """
    inf = {"scale_sigma": np.inf, "length_sigma": np.inf, "speed_sigma": np.inf, "tilt_sigma_rad": np.inf}
    v0, g, bg, ba, G = globals_of(z_glob, R_g)
    n_k = len(win.dts)
    pim_end = pims[-1]
    # 7a. Reprojection Jacobians at the solution and the reduced information (noise: RMS, >= floor).
    r, Jg, Jf, Jpose = reprojection(win, z_glob, pf, R_g, sigma, with_pose=True)
    c2 = max(rms / sigma, 1.0) ** 2
    H_gg, H_gf, H_ff, _, _ = normal_equations(win, r, Jg, Jf)
    try:
        W = H_gf @ np.linalg.inv(H_ff + 1e-12 * np.eye(3))  # (n_f, G, 3)
        info = (H_gg - np.einsum("nij,nkj->ik", W, H_gf)) / c2 + np.diag(prior)
        cov_g = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return inf
    # 7b. Sensitivity to the frame-pose errors [dtheta_k, dp_k]: G_eta = sum_obs (J_g - J_f W^T)^T J_pose.
    L_red = Jg - Jf @ np.transpose(W[win.obs_feat], (0, 2, 1))  # (n_obs, 2, G), whitened rows
    L_red = win.whiten(L_red, transpose=True)  # onto the observations, whose pose errors J_pose maps
    G_obs = np.einsum("nki,nkj->nij", L_red, Jpose) / c2  # (n_obs, G, 6)
    G_eta = np.zeros((N_GLOBAL, n_k + 1, 9))
    np.add.at(G_eta[:, :, 0:3], (slice(None), win.obs_frame), np.transpose(G_obs[:, :, 0:3], (1, 0, 2)))
    np.add.at(G_eta[:, :, 6:9], (slice(None), win.obs_frame), np.transpose(G_obs[:, :, 3:6], (1, 0, 2)))
    # 7c. The quantities: trajectory length, end speed, end up axis (3), end velocity (3), bg, ba.
    R_k, p_k = frame_poses(win, v0, g, bg, ba)
    J_k = np.zeros((n_k, 3, N_GLOBAL))
    J_k[:, :, 0:3] = win.dts[:, None, None] * np.eye(3)
    J_k[:, :, 3:5] = 0.5 * win.dts[:, None, None] ** 2 * G
    J_k[:, :, 5:8] = win.Jp_bg
    J_k[:, :, 8:11] = win.Jp_ba
    length, w_L = _trajectory_scale(p_k, J_k)
    dR_end, dv_end, _ = pim_end.corrected(bg, ba)
    v_end = v0 + g * pim_end.dt_s + dv_end
    speed = float(np.linalg.norm(v_end))
    up_end = -dR_end.T @ g / GRAVITY_M_S2
    Jq_g = np.zeros((14, N_GLOBAL))
    Jq_eta = np.zeros((14, n_k + 1, 9))
    Jq_g[0] = w_L
    dist = np.linalg.norm(p_k, axis=1)
    Jq_eta[0, :n_k, 6:9] = np.where(dist[:, None] > 1e-9, p_k / np.maximum(dist, 1e-9)[:, None], 0.0)
    J_v = np.zeros((3, N_GLOBAL))
    J_v[:, 0:3] = np.eye(3)
    J_v[:, 3:5] = pim_end.dt_s * G
    J_v[:, 5:8] = pim_end.d_v_d_bg
    J_v[:, 8:11] = pim_end.d_v_d_ba
    e_v = v_end / max(speed, 1e-9)
    Jq_g[1], Jq_eta[1, n_k, 3:6] = e_v @ J_v, e_v
    Jq_g[2:5, 3:5] = -dR_end.T @ G / GRAVITY_M_S2
    Jq_g[2:5, 5:8] = skew(up_end) @ pim_end.d_R_d_bg
    Jq_eta[2:5, n_k, 0:3] = skew(up_end)
    Jq_g[5:8], Jq_eta[5:8, n_k, 3:6] = J_v, np.eye(3)
    Jq_g[8:14, 5:11] = np.eye(6)
    # 7d. Covariance of the quantities: image share plus the preintegration share.
    Jq_eta = Jq_eta.reshape(14, -1)
    T = Jq_eta - Jq_g @ cov_g @ G_eta.reshape(N_GLOBAL, -1)
    cov_q = Jq_g @ cov_g @ Jq_g.T + T @ imu_cov @ T.T
    if not np.all(np.isfinite(cov_q)):
        return inf
    var = np.maximum(np.diag(cov_q), 0.0)
    length_sigma = float(np.sqrt(var[0])) / length if length > 0.0 else float("inf")
    speed_sigma = float(np.sqrt(var[1])) / speed if speed > 0.0 else float("inf")
    tangent = np.linalg.svd(np.eye(3) - np.outer(up_end, up_end))[0][:, :2]
    return {
        "scale_sigma": max(length_sigma, speed_sigma),
        "length_sigma": length_sigma,
        "length_m": length,
        "speed_sigma": speed_sigma,
        "tilt_sigma_rad": _tilt_sigma_rad(tangent.T @ cov_q[2:5, 2:5] @ tangent),
        "cov_v_B0": cov_q[5:8, 5:8],
        "cov_bg": cov_q[8:11, 8:11],
        "cov_ba": cov_q[11:14, 11:14],
    }
