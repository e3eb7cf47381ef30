"""The online calibration's part of the window's Gauss-Newton system (:mod:`viotb.vio.window_calib`).

The C calibration variables follow the N keyframes' error states: the system is ``N NX + C`` wide, the
pose-landmark blocks ``E`` gain C rows after the 6 N pose rows (the calibration is coupled to every landmark
through its observations, so it stays with the poses in the Schur complement), and the linear prior spans
its keyframes' states and then the calibration (marginalizing the oldest keyframe keeps the calibration:
the prior on it accumulates the information of every marginalized landmark). :func:`viotb.vio.window_solver.
linearize` calls :meth:`CalibTerms.add_prior` and :meth:`CalibTerms.add_reprojection` instead of its own
prior and reprojection steps when it is given the calibration values (the latter only when the extrinsics
or the time offset are estimated), :meth:`CalibTerms.add_imu` when the IMU's correction matrices are, and
:meth:`CalibTerms.assemble` last.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.vio.marginalization import LinearPrior
from viotb.vio.window_calib import CalibLayout, CalibValues, calib_jacobian
from viotb.vio.window_factors import NX
from viotb.vio.window_reprojection import add_reprojection


@dataclass(frozen=True)
class CalibFactors:
    """What the factors of one solve need of the calibration, besides its current values.

    Attributes:
        layout: The estimated entries (C).
        x0: The linear prior's linearization point of the calibration.
        gyro_B_rad_s: Each keyframe's gyro reading at its time (bias not removed), shape (N, 3).
    """

    layout: CalibLayout
    x0: CalibValues
    gyro_B_rad_s: np.ndarray


@dataclass
class CalibTerms:
    """The calibration's blocks of one linearization.

    Attributes:
        H_xc: Keyframe states x calibration, shape (N NX, C).
        H_cc: Calibration information, shape (C, C).
        g_c: Calibration gradient, shape (C,).
        E_c: Calibration-landmark blocks, shape (L, C, 3).
    """

    H_xc: np.ndarray
    H_cc: np.ndarray
    g_c: np.ndarray
    E_c: np.ndarray

    @classmethod
    def zeros(cls, n_kf: int, n_lm: int, dim: int) -> CalibTerms:
        """Empty blocks for ``n_kf`` keyframes, ``n_lm`` landmarks and ``dim`` variables."""
        return cls(np.zeros((n_kf * NX, dim)), np.zeros((dim, dim)), np.zeros(dim), np.zeros((n_lm, dim, 3)))

    def add_prior(
        self,
        H: np.ndarray,
        g: np.ndarray,
        idx: np.ndarray,
        prior: LinearPrior,
        dx_kf: np.ndarray,
        dx_c: np.ndarray,
    ) -> tuple[np.ndarray, float]:
        """Add the linear prior over keyframe entries ``idx`` and the calibration; ``(gradient, cost)``.

        Args:
            H: Keyframe information (N NX, N NX), in place.
            g: Keyframe gradient (N NX,), in place.
            idx: The prior's keyframe entries in the system, shape (P NX,).
            prior: Its ``H`` and ``g`` span ``idx`` and then the C calibration entries.
            dx_kf: ``x [-] x0`` of its keyframes, shape (P NX,).
            dx_c: ``calib [-] x0`` of the calibration, shape (C,).
        """
        m = len(idx)
        dx = np.concatenate([dx_kf, dx_c])
        H[np.ix_(idx, idx)] += prior.H[:m, :m]
        g_pr = prior.H @ dx + prior.g
        g[idx] += g_pr[:m]
        self.H_xc[idx] += prior.H[:m, m:]
        self.H_cc += prior.H[m:, m:]
        self.g_c += g_pr[m:]
        return g_pr, float(0.5 * dx @ prior.H @ dx + prior.g @ dx)

    def add_reprojection(
        self,
        arrays: tuple[np.ndarray, ...],
        poses: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        rest: np.ndarray,
        pts: np.ndarray,
        cams: list[tuple[tuple[np.ndarray, np.ndarray, np.ndarray], float, float, object]],
        calib: CalibValues,
        cal_f: CalibFactors,
        blocks: list,
    ) -> tuple[float, int]:
        """Every camera's reprojection factors with the calibration ``calib``; ``(robust cost, residuals)``.

        Each observation ``xy`` becomes ``xy - td V`` with ``V`` the image velocity predicted from its
        keyframe's motion (:mod:`viotb.vio.window_calib`) and its Jacobian gains the calibration's columns
        (:func:`viotb.vio.window_calib.calib_jacobian`).

        Args:
            arrays: ``(H, g, H_ll, g_l, E (L, N, 6, 3), max_err)`` of
                :func:`viotb.vio.window_reprojection.add_reprojection`, in place.
            poses: Keyframe poses of the residuals, then of the Jacobians.
            rest: Keyframe ``[p, v, b_g, b_a]`` of the residuals, shape (N, 12).
            pts: Landmarks in W (m), shape (L, 3).
            cams: Per camera ``(observations, sigma in normalized coordinates, Huber threshold, sums)``.
            calib: Current calibration.
            cal_f: The solve's calibration factors.
            blocks: Each camera's blocks are appended (white noise).
        """
        cost, n_res = 0.0, 0
        C = cal_f.layout.dim
        for c, (obs, sigma, k_h, sums) in enumerate(cams):
            kf_i, lm_i, xy = obs
            if not len(kf_i):
                continue
            R_BC, p_BC = calib.R_BC[c], calib.p_BC[c]
            R_k, p_k = poses[0][kf_i], poses[1][kf_i]
            motion = (cal_f.gyro_B_rad_s[kf_i] - rest[kf_i, 6:9], rest[kf_i, 3:6])  # omega_B, v_W
            J_c, vel = calib_jacobian(R_k, p_k, pts[lm_i], R_BC, p_BC, *motion, c, cal_f.layout)
            obs_td = (kf_i, lm_i, xy - calib.td_s * vel)
            ci, ni = add_reprojection(
                *arrays, poses, pts, obs_td, (R_BC, p_BC, sigma, k_h), sums, blocks, J_extra=J_c
            )
            cost, n_res = cost + ci, n_res + ni
            A, M, sl = blocks[-1].A, len(kf_i), slice(9, 9 + C)
            sum_k, sum_l = sums  # the solve's 0/1 matrices summing per keyframe and per landmark
            H_pc = (sum_k @ A[:, :6, sl].reshape(M, 6 * C)).reshape(-1, 6, C)
            self.H_xc.reshape(-1, NX, C)[:, :6] += H_pc
            self.E_c += (sum_l @ A[:, sl, 6:9].reshape(M, 3 * C)).reshape(-1, C, 3)
            both = np.sum(A[:, sl, :], axis=0)
            self.H_cc += both[:, sl]
            self.g_c += both[:, -1]
        return cost, n_res

    def add_imu(self, k: np.ndarray, WJ_c: np.ndarray, WJ: np.ndarray, r_w: np.ndarray) -> None:
        """The IMU factors' calibration blocks (the correction matrices' columns); the cost is the caller's.

        Args:
            k: Each factor's first keyframe, shape (K,) (it joins ``k`` and ``k + 1``).
            WJ_c: Whitened Jacobians w.r.t. the estimated entries, shape (K, NX, C).
            WJ: Whitened Jacobians w.r.t. keyframes ``k`` and ``k + 1``, shape (K, NX, 2 NX).
            r_w: Whitened residuals, shape (K, NX).
        """
        pair = np.swapaxes(WJ, 1, 2) @ WJ_c
        H_kc = self.H_xc.reshape(-1, NX, WJ_c.shape[2])
        H_kc[k] += pair[:, :NX]  # the factors' first keyframes differ: fancy-indexed += adds each
        H_kc[k + 1] += pair[:, NX:]
        self.H_cc += np.einsum("kia,kib->ab", WJ_c, WJ_c)
        self.g_c += np.einsum("kia,ki->a", WJ_c, r_w)

    def assemble(
        self, H: np.ndarray, g: np.ndarray, E_flat: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The whole system: ``H (N NX + C, N NX + C)``, ``g (N NX + C,)``, ``E (L, 6 N + C, 3)``."""
        H_full = np.block([[H, self.H_xc], [self.H_xc.T, self.H_cc]])
        return H_full, np.concatenate([g, self.g_c]), np.concatenate([E_flat, self.E_c], axis=1)
