"""Normalized innovation squared of a new keyframe's observations, for the health monitor's time-sync test.

Before a new keyframe enters the optimization, its IMU-predicted pose and the window's landmarks predict
where the landmarks it sees should appear. The innovation of landmark ``l`` is ``r = xy - h(x_j, p_l)`` with
covariance (Bar-Shalom et al. 2001, sec. 5.4; the MSCKF's per-feature test, Mourikis & Roumeliotis 2007)::

    S = [J_x J_l] [[P_jj, P_jl], [P_lj, P_ll]] [J_x J_l]^T + sigma^2 I

where the joint covariance of the predicted keyframe ``j`` and the landmark comes from the previous solve:
its information, with landmarks eliminated (``S_p``, :func:`viotb.vio.window_solver.schur_reduce`), gives the
keyframe covariance ``Sigma = S_p^-1``; a landmark's is ``P_ll = H_ll^-1 + B^T Sigma_pp B`` and its
cross-covariance with keyframe ``n`` is ``P_nl = -Sigma_np B`` with ``B = E_l H_ll^-1`` (block inverse of the
bundle-adjustment system); the IMU factor carries them to ``j``: ``P_jj = F Sigma_nn F^T + Q``,
``P_jl = F P_nl`` with ``F = -J_j^-1 J_i`` and ``Q = J_j^-1 C J_j^-T`` (:func:`imu_factor`).
``r^T S^-1 r / 2`` has mean 1 when the models are right; a camera-IMU time offset or a wrong extrinsic
rotation moves the features against the prediction while the platform moves, and raises it
(:mod:`viotb.vio.health_conditions`, condition 4).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.state import ImuValues
from viotb.vio.types import ImuNoise
from viotb.vio.window_calib import image_velocity
from viotb.vio.window_factors import NX, imu_factor, reprojection
from viotb.vio.window_linalg import spd_inverse
from viotb.vio.window_solver import LinearSystem, pose_index, schur_reduce

CHI2_2DOF_99 = 9.21
"""99 % quantile of the chi-square distribution with 2 degrees of freedom (the per-feature gate)."""


@dataclass(frozen=True)
class WindowMarginals:
    """Covariances of the window after a solve, for the next keyframe's innovations.

    Attributes:
        Sigma: Covariance of every keyframe's error state, shape (N NX, N NX).
        H_ll_inv: Inverse landmark information blocks, shape (L, 3, 3).
        E: Pose-landmark information blocks, shape (L, 6 N, 3).
        index: Feature id -> landmark row.
        calib_cov: Covariance of the online calibration's C variables (after the keyframes' in the system,
            :mod:`viotb.vio.window_calib_system`), shape (C, C); (0, 0) without. The innovations leave
            its uncertainty out.
    """

    Sigma: np.ndarray
    H_ll_inv: np.ndarray
    E: np.ndarray
    index: dict[int, int]
    calib_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    @classmethod
    def from_system(cls, sys: LinearSystem, lm_ids: list[int]) -> WindowMarginals:
        """Invert the reduced system of a solve over landmarks ``lm_ids`` (its row order)."""
        S, _, H_ll_inv = schur_reduce(sys, 0.0)
        Sigma_all = spd_inverse(S) if sys.compiled else np.linalg.inv(S)
        n, n6 = len(S) - sys.n_calib, sys.E.shape[1] - sys.n_calib
        Sigma, E, index = Sigma_all[:n, :n], sys.E[:, :n6], {f: j for j, f in enumerate(lm_ids)}
        return cls(0.5 * (Sigma + Sigma.T), H_ll_inv, E, index, Sigma_all[n:, n:])

    @property
    def newest_covariance(self) -> np.ndarray:
        """Covariance of the newest keyframe, shape (NX, NX)."""
        return self.Sigma[-NX:, -NX:]


@dataclass(frozen=True)
class InnovationTest:
    """NIS of one keyframe's observations of existing landmarks.

    Attributes:
        nis_per_dof: Mean ``r^T S^-1 r / 2`` over the observations inside the 99 % gate (NaN if none).
        nis_per_dof_all: The same over every observation.
        passed: Observations inside the gate.
        rejected: Observations outside it.
    """

    nis_per_dof: float = float("nan")
    nis_per_dof_all: float = float("nan")
    passed: int = 0
    rejected: int = 0


def innovation_test(
    marg: WindowMarginals,
    pre: ImuPreintegration,
    x_n: ImuValues,
    x_j: ImuValues,
    noise: ImuNoise,
    obs: dict[int, np.ndarray],
    landmarks: dict[int, np.ndarray],
    camera: tuple[np.ndarray, np.ndarray, float, float],
    time_offset: tuple[float, np.ndarray] | None = None,
) -> InnovationTest:
    """NIS of the new keyframe ``j`` (predicted from the newest keyframe ``n`` by ``pre``) (module docstring).

    Args:
        marg: The window's covariances after the last solve (``n`` is its newest keyframe).
        pre: Preintegration from ``n`` to ``j``.
        x_n: Values of ``n``.
        x_j: Predicted values of ``j``.
        noise: IMU noise densities.
        obs: Feature id -> undistorted normalized xy (2,) seen by ``j``'s camera.
        landmarks: Feature id -> point in W (m), (3,).
        camera: ``(R_BC (3, 3), p_BC (3,), sigma_norm, min_depth_m)`` of that camera.
        time_offset: ``(td (s), gyro reading at j (3,) rad/s)`` of the online time-offset calibration: the
            predictions become ``z + td V`` (:mod:`viotb.vio.window_calib`), or None.
    """
    fids = [f for f in obs if f in landmarks and f in marg.index]
    if not fids:
        return InnovationTest()
    R_BC, p_BC, sigma_norm, min_depth_m = camera
    rows = np.array([marg.index[f] for f in fids])
    # 1. Landmark covariances and their cross-covariances with keyframe n.
    N6 = marg.E.shape[1]
    pidx = pose_index(N6 // 6)
    B = marg.E[rows] @ marg.H_ll_inv[rows]
    Sigma_pp = marg.Sigma[np.ix_(pidx, pidx)]
    P_ll = marg.H_ll_inv[rows] + np.swapaxes(B, 1, 2) @ Sigma_pp @ B
    P_nl = -marg.Sigma[-NX:, pidx] @ B
    # 2. Through the IMU factor to j.
    _, J_i, J_j, C = imu_factor(pre, x_n, x_j, noise)
    Jj_inv = np.linalg.inv(J_j)
    F = -Jj_inv @ J_i
    P_jj = F @ marg.newest_covariance @ F.T + Jj_inv @ C @ Jj_inv.T
    P_jl = F @ P_nl
    # 3. Predicted projections and innovation covariances.
    m = len(fids)
    p_W = np.array([landmarks[f] for f in fids])
    xy = np.array([obs[f] for f in fids])
    z, depth, J_x, J_l = reprojection(
        np.broadcast_to(x_j.R_WB, (m, 3, 3)), np.broadcast_to(x_j.p_WB, (m, 3)), p_W, R_BC, p_BC
    )
    if time_offset is not None:
        omega_B = np.broadcast_to(time_offset[1] - x_j.gyro_bias_rad_s, (m, 3))
        z = z + time_offset[0] * image_velocity(J_x, omega_B, np.broadcast_to(x_j.v_WB, (m, 3)))
    ok = depth > min_depth_m
    if not np.any(ok):
        return InnovationTest()
    J = np.concatenate([J_x, J_l], axis=2)
    P = np.zeros((m, 9, 9))
    P[:, :6, :6] = P_jj[:6, :6]
    P[:, :6, 6:] = P_jl[:, :6]
    P[:, 6:, :6] = np.swapaxes(P_jl[:, :6], 1, 2)
    P[:, 6:, 6:] = P_ll
    S = J @ P @ np.swapaxes(J, 1, 2) + sigma_norm**2 * np.eye(2)
    r = (xy - z)[ok]
    nis = np.einsum("mi,mi->m", r, np.linalg.solve(S[ok], r[:, :, None])[:, :, 0]) / 2.0
    gate = nis * 2.0 <= CHI2_2DOF_99
    return InnovationTest(
        float(np.mean(nis[gate])) if np.any(gate) else float("nan"),
        float(np.mean(nis)),
        int(np.sum(gate)),
        int(np.sum(~gate)),
    )
