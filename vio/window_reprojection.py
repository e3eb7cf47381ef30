"""The window's reprojection factors in its Gauss-Newton system, with white or correlated (KLT) track noise.

White noise: each observation ``m`` of landmark ``l`` in keyframe ``k`` adds its Huber-weighted
``J_m^T J_m`` (``J = [J_pose (6), J_point (3), r] / sigma``) to the pose block ``(k, k)``, the pose-landmark
block ``E[l, k]`` and the landmark block ``H_ll[l]``.

Correlated noise: a KLT track's error is white noise plus a random walk clocked by the feature's image motion
(``KltParams.track_random_walk_px2_per_px``; the MSCKF's model, :func:`viotb.vio.update_helpers.
random_walk_whitener`): per image axis the views of one landmark in one camera have the covariance
``sigma^2 (I + q min(n_u, n_v))`` with ``n`` the image path (px) since the landmark's first view in the
window and ``q = q_px / sigma_px^2``. The generalized-least-squares cost ``0.5 sum_uv Lambda_uv r_u . r_v``
(``Lambda = (I + q min(n_u, n_v))^-1``, whitening ``W^T W``) gives every pair of views ``(u, v)`` of a
landmark a block ``Lambda_uv J_u^T J_v``: pose-pose blocks between the two keyframes, the pose of ``u``
with the landmark, the landmark's own. The Huber weights enter as ``sqrt(w_u w_v) Lambda_uv`` (with
``Lambda = I`` both forms are the same system and cost). The pairs and their ``Lambda_uv`` depend on the
measurements only, so they are built once per solve (:func:`track_pairs`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import sparse
from viotb.vio.update_helpers import Chi2Table, random_walk_whitener, track_path_px
from viotb.vio.window_factors import NX, project, reprojection
from viotb.vio.window_kernels import white_reprojection


def summing_matrix(row: np.ndarray, n_rows: int) -> sparse.csr_matrix:
    """The 0/1 matrix (n_rows, M) with a one at ``(row[m], m)``: its product sums the M terms per row.

    Built from its CSR arrays directly (a stable sort of ``row``), which is several times faster than
    from coordinates.
    """
    row = np.asarray(row, dtype=np.int64)
    order = np.argsort(row, kind="stable")
    indptr = np.concatenate([[0], np.cumsum(np.bincount(row, minlength=n_rows))])
    return sparse.csr_matrix((np.ones(len(row)), order, indptr), shape=(n_rows, len(row)))


@dataclass(frozen=True)
class TrackPairs:
    """The track-noise information of each landmark's views in one camera, on a (landmark, keyframe) grid.

    Attributes:
        lam: ``Lambda`` of each landmark over the keyframes, zero where a keyframe does not see it, shape
            (L, N, N).
    """

    lam: np.ndarray


def track_pairs(
    obs: tuple[np.ndarray, np.ndarray, np.ndarray], n_kf: int, n_lm: int, focal_px: float, q: float
) -> TrackPairs:
    """``Lambda`` of every landmark's views (module docstring).

    Args:
        obs: ``(kf index (M,), landmark index (M,), xy_norm (M, 2))``, one observation per keyframe and
            landmark; keyframe indices in time order.
        n_kf: Keyframes N.
        n_lm: Landmarks L.
        focal_px: Focal length (px) that turns normalized distances into the clock's pixels.
        q: ``track_random_walk_px2_per_px / pixel_sigma_px^2`` (>= 0).
    """
    kf_i, lm_i, xy = obs
    mask = np.zeros((n_lm, n_kf), dtype=bool)
    grid = np.zeros((n_lm, n_kf, 2))
    mask[lm_i, kf_i] = True
    grid[lm_i, kf_i] = xy
    clock = track_path_px(grid, mask, np.full(n_kf, focal_px), n_kf)
    W = random_walk_whitener(clock, mask, np.zeros(n_kf, dtype=np.int64), q)
    both = mask[:, :, None] & mask[:, None, :]
    return TrackPairs(np.where(both, np.swapaxes(W, 1, 2) @ W, 0.0))


@dataclass(frozen=True)
class WhiteBlocks:
    """One camera's per-observation blocks ``A = w J^T J`` (M, 10, 10) of a linearization (white noise)."""

    kf_i: np.ndarray
    lm_i: np.ndarray
    A: np.ndarray

    def pose_terms(self, keep: np.ndarray, n_kf: int) -> tuple[np.ndarray, np.ndarray]:
        """Pose-pose blocks (N, N, 6, 6) and pose gradients (N, 6) of the landmarks ``keep`` (L,) bool."""
        sel = keep[self.lm_i]
        H_kk = np.zeros((n_kf, n_kf, 6, 6))
        g_k = np.zeros((n_kf, 6))
        np.add.at(H_kk, (self.kf_i[sel], self.kf_i[sel]), self.A[sel, :6, :6])
        np.add.at(g_k, self.kf_i[sel], self.A[sel, :6, -1])
        return H_kk, g_k


@dataclass(frozen=True)
class TrackBlocks:
    """One camera's blocks of a linearization with correlated track noise.

    Attributes:
        Jg: Huber-weighted ``[J_pose, J_point, r] / sigma`` on the (landmark, keyframe) grid, zero where
            unseen, shape (L, N, 2, 10).
        lam: ``Lambda`` per landmark (:class:`TrackPairs`), shape (L, N, N).
    """

    Jg: np.ndarray
    lam: np.ndarray

    def pose_terms(self, keep: np.ndarray, n_kf: int) -> tuple[np.ndarray, np.ndarray]:
        """Pose-pose blocks (N, N, 6, 6) and pose gradients (N, 6) of the landmarks ``keep`` (L,) bool."""
        H_pp, g_p = _track_pose_terms(self.Jg[keep], self.lam[keep])
        return np.swapaxes(H_pp, 1, 2), g_p


def _track_pose_terms(Jg: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sum_l sum_uv Lambda_uv J_pose,u^T [J_pose,v, r_v]`` as (N, 6, N, 6) pose blocks and (N, 6) gradients.

    Keyframe by keyframe ``u``, one matrix product over the landmarks it sees and the image axes:
    ``G_u (6, 2 L_u)`` with ``Z_u (2 L_u, 6 N)``, ``Z_u[(l, a), (v, j)] = Lambda_l[u, v] J_l[v, a, j]``
    (small temporaries: the whole (L, N, N, 2, 6) tensor at once was slower, out of cache).
    """
    N = Jg.shape[1]
    J6 = Jg[:, :, :, :6]
    H_pp = np.zeros((N, 6, N, 6))
    seen = np.any(lam != 0.0, axis=2)  # (L, N): the landmark has a view in keyframe u
    Y_r = lam @ Jg[:, :, :, 9]  # (L, u, 2): sum_v Lambda_uv r_v
    g_p = np.einsum("luai,lua->ui", J6, Y_r)
    for u in range(N):
        ls = np.nonzero(seen[:, u])[0]
        if not len(ls):
            continue
        Z = (lam[ls, u, :, None, None] * J6[ls]).transpose(0, 2, 1, 3).reshape(2 * len(ls), N * 6)
        G = J6[ls, u].transpose(2, 0, 1).reshape(6, 2 * len(ls))
        H_pp[u] = (G @ Z).reshape(6, N, 6)
    return H_pp, g_p


def add_reprojection(
    H: np.ndarray,
    g: np.ndarray,
    H_ll: np.ndarray,
    g_l: np.ndarray,
    E: np.ndarray,
    max_err: np.ndarray,
    poses: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    pts: np.ndarray,
    obs: tuple[np.ndarray, np.ndarray, np.ndarray],
    cam: tuple[np.ndarray, np.ndarray, float, float],
    sums: tuple[sparse.csr_matrix, sparse.csr_matrix] | TrackPairs | None,
    blocks: list[WhiteBlocks | TrackBlocks],
    J_extra: np.ndarray | None = None,
    compiled: bool = False,
) -> tuple[float, int]:
    """Add one camera's Huber-weighted reprojection factors to the system (in place).

    Args:
        H: Keyframe information (N NX, N NX).
        g: Keyframe gradient (N NX,).
        H_ll: Landmark information blocks (L, 3, 3).
        g_l: Landmark gradients (L, 3).
        E: Pose-landmark blocks (L, N, 6, 3).
        max_err: Largest whitened error per landmark (L,), raised in place (white-noise errors).
        poses: Keyframe ``(R_WB (N, 3, 3), p_WB (N, 3))`` of the residuals, then of the Jacobians.
        pts: Landmarks in W (m), shape (L, 3).
        obs: ``(kf index (M,), landmark index (M,), xy_norm (M, 2))`` in this camera (one observation per
            keyframe and landmark).
        cam: ``(R_BC (3, 3), p_BC (3,) m, sigma in normalized coordinates, Huber threshold in sigmas)``.
        sums: White noise: sparse 0/1 matrices summing the observations per keyframe (N, M) and landmark
            (L, M), or None (made here when needed); correlated track noise: the :class:`TrackPairs` of
            ``obs``.
        blocks: This camera's blocks are appended (:class:`WhiteBlocks` or :class:`TrackBlocks`): what
            the system of a subset of the landmarks needs.
        J_extra: Jacobians (M, 2, C) w.r.t. C more variables (online calibration,
            :mod:`viotb.vio.window_calib_system`), white noise only: their columns sit in the blocks ``A``
            between the landmark's and the residual (``A[:, 9 : 9 + C]``), or None.
        compiled: White noise without ``J_extra`` and without first-estimate Jacobians: the blocks by the
            compiled loop (:func:`viotb.vio.window_kernels.white_reprojection`; ``sums`` is then not used).

    Returns:
        ``(robust cost, residual count)``.
    """
    N = len(poses[0])
    kf_i, lm_i, xy = obs
    if not len(kf_i):
        return 0.0, 0
    R_BC, p_BC, sigma_norm, k_h = cam
    if compiled and J_extra is None and poses[2] is poses[0] and not isinstance(sums, TrackPairs):
        return _white_compiled(H, g, H_ll, g_l, E, max_err, poses, pts, obs, cam, blocks)
    if sums is None:  # prepared for the compiled blocks, which first-estimate Jacobians do not take
        sums = (summing_matrix(kf_i, N), summing_matrix(lm_i, len(H_ll)))
    if poses[2] is poses[0]:
        z, _, J_pose, J_pt = reprojection(poses[0][kf_i], poses[1][kf_i], pts[lm_i], R_BC, p_BC)
    else:  # first-estimate Jacobians, residuals at the current values
        _, _, J_pose, J_pt = reprojection(poses[2][kf_i], poses[3][kf_i], pts[lm_i], R_BC, p_BC)
        z = project(poses[0][kf_i], poses[1][kf_i], pts[lm_i], R_BC, p_BC)
    s = 1.0 / sigma_norm
    r = (z - xy) * s
    e = np.linalg.norm(r, axis=1)
    w = np.where(e <= k_h, 1.0, k_h / np.maximum(e, 1e-12))
    huber = np.where(e <= k_h, e * e, 2.0 * k_h * e - k_h * k_h)
    np.maximum.at(max_err, lm_i, e)
    # One product gives every block: with J = [J_pose, J_pt, r] / sigma (M, 2, 10), w J^T J holds the
    # pose-pose (6x6), pose-point (E), point-point and both gradients. Sums over the observations (pairs)
    # of each keyframe and each landmark are sparse products (faster than ``np.add.at``); the pose blocks
    # sit in H seen as (N, NX, N, NX).
    extra = [] if J_extra is None else [J_extra * s]
    J = np.concatenate([J_pose * s, J_pt * s, *extra, r[:, :, None]], axis=2)
    H4, nj = H.reshape(N, NX, N, NX), J.shape[2]
    if isinstance(sums, TrackPairs):
        if J_extra is not None:
            raise ValueError("add_reprojection: more variables (online calibration) need white track noise")
        # Views on the (landmark, keyframe) grid: Y_u = sum_v Lambda_uv J_v gives every block but the
        # pose-pose ones per observation (J_u^T Y_u); those pair different keyframes (_track_pose_terms).
        L = len(H_ll)
        Jg = np.zeros((L, N, 2, 10))
        Jg[lm_i, kf_i] = J * np.sqrt(w)[:, None, None]
        Y = (sums.lam @ Jg.reshape(L, N, 20)).reshape(L, N, 2, 10)
        A = np.swapaxes(Jg[lm_i, kf_i], 1, 2) @ Y[lm_i, kf_i]
        per_lm = (summing_matrix(lm_i, L) @ A.reshape(len(kf_i), 100)).reshape(-1, 10, 10)
        H_pp, g_p = _track_pose_terms(Jg, sums.lam)
        H4[:, :6, :, :6] += H_pp
        g.reshape(N, NX)[:, :6] += g_p
        E[lm_i, kf_i] += A[:, :6, 6:9]
        blocks.append(TrackBlocks(Jg, sums.lam))
        # GLS cost with the Huber weights; the Huber correction keeps it the robust cost at Lambda = I.
        cost = 0.5 * float(np.sum(A[:, 9, 9]) + np.sum(huber - w * e * e))
    else:
        A = (np.swapaxes(J, 1, 2) * w[:, None, None]) @ J
        M = len(kf_i)
        sum_k, sum_l = sums
        per_kf = (sum_k @ A.reshape(M, nj * nj)).reshape(N, nj, nj)
        per_lm = (sum_l @ A.reshape(M, nj * nj)).reshape(-1, nj, nj)
        k_all = np.arange(N)
        H4[k_all, :6, k_all, :6] += per_kf[:, :6, :6]
        g.reshape(N, NX)[:, :6] += per_kf[:, :6, -1]
        E[lm_i, kf_i] += A[:, :6, 6:9]
        blocks.append(WhiteBlocks(kf_i, lm_i, A))
        cost = 0.5 * float(np.sum(huber))
    H_ll += per_lm[:, 6:9, 6:9]
    g_l += per_lm[:, 6:9, -1]
    return cost, 2 * len(kf_i)


def _white_compiled(
    H: np.ndarray,
    g: np.ndarray,
    H_ll: np.ndarray,
    g_l: np.ndarray,
    E: np.ndarray,
    max_err: np.ndarray,
    poses: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    pts: np.ndarray,
    obs: tuple[np.ndarray, np.ndarray, np.ndarray],
    cam: tuple[np.ndarray, np.ndarray, float, float],
    blocks: list[WhiteBlocks | TrackBlocks],
) -> tuple[float, int]:
    """The white-noise branch of :func:`add_reprojection` by the compiled ``white_reprojection``."""
    kf_i, lm_i, xy = (np.ascontiguousarray(a) for a in obs)
    kf_i, lm_i = kf_i.astype(np.int64, copy=False), lm_i.astype(np.int64, copy=False)
    R_BC, p_BC, sigma_norm, k_h = cam
    N, L, M = len(poses[0]), len(H_ll), len(kf_i)
    per_kf, per_lm, A = np.zeros((N, 10, 10)), np.zeros((L, 10, 10)), np.empty((M, 10, 10))
    R_WB, p_WB = np.ascontiguousarray(poses[0]), np.ascontiguousarray(poses[1])
    args = (np.ascontiguousarray(pts), kf_i, lm_i, xy, np.ascontiguousarray(R_BC), np.ascontiguousarray(p_BC))
    rho = white_reprojection(R_WB, p_WB, *args, 1.0 / sigma_norm, k_h, per_kf, per_lm, A, E, max_err)
    k_all = np.arange(N)
    H4 = H.reshape(N, NX, N, NX)
    H4[k_all, :6, k_all, :6] += per_kf[:, :6, :6]
    g.reshape(N, NX)[:, :6] += per_kf[:, :6, -1]
    H_ll += per_lm[:, 6:9, 6:9]
    g_l += per_lm[:, 6:9, -1]
    blocks.append(WhiteBlocks(kf_i, lm_i, A))
    return 0.5 * rho, 2 * M


def landmark_chi2(blocks: list[WhiteBlocks | TrackBlocks], n_lm: int) -> tuple[np.ndarray, np.ndarray]:
    """Each landmark's whitened reprojection cost over all cameras and its degrees of freedom.

    White noise: ``sum_m w_m |r_m|^2`` over its observations; correlated track noise: the generalized
    least-squares ``sum_uv Lambda_uv r_u . r_v`` (both with the Huber weights of the linearization, the
    cost :func:`add_reprojection` adds). Degrees of freedom ``2 M - 3`` for M observations (a point in W).

    Args:
        blocks: ``LinearSystem.reprojection_blocks`` of one linearization over ``n_lm`` landmarks.
        n_lm: Landmarks L.

    Returns:
        ``(chi2 (L,), dof (L,))``.
    """
    chi2, views = np.zeros(n_lm), np.zeros(n_lm)
    for b in blocks:
        if isinstance(b, WhiteBlocks):
            chi2 += np.bincount(b.lm_i, b.A[:, -1, -1], minlength=n_lm)
            views += np.bincount(b.lm_i, minlength=n_lm)
        else:
            r = b.Jg[:, :, :, 9]  # (L, N, 2): sqrt(w) r / sigma, zero where unseen
            chi2 += np.einsum("lua,luv,lva->l", r, b.lam, r)
            views += np.count_nonzero(np.diagonal(b.lam, axis1=1, axis2=2), axis=1)
    return chi2, 2.0 * views - 3.0


@dataclass(frozen=True)
class LandmarkOutlierTest:
    """Which landmarks leave the window after a solve.

    A view whitened above ``threshold`` sigmas (``LinearSystem.max_err``), or, with a ``chi2_table``, the
    landmark's cost :func:`landmark_chi2` above the table's quantile for its degrees of freedom: the test of
    the whole track under the noise model, as the MSCKF gates each feature (Mourikis & Roumeliotis 2007,
    sec. IV), where a single view's error measured against the white part alone also rejects the slow drift
    of a correlated track.

    Attributes:
        threshold: Largest whitened error of a single view (sigmas).
        chi2_table: Chi-square quantiles of the track test (built once), or None (the per-view rule only).
    """

    threshold: float
    chi2_table: Chi2Table | None = None

    @classmethod
    def create(cls, threshold: float, quantile: float | None, window_size: int) -> LandmarkOutlierTest:
        """The test of ``WindowParams.outlier_threshold`` / ``outlier_chi2`` for ``window_size`` keyframes.

        The table covers a landmark seen by both cameras of every keyframe of a full window plus the newest.
        """
        table = None if quantile is None else Chi2Table(4 * (window_size + 1), confidence=quantile)
        return cls(threshold, table)

    def __call__(self, sys: Any) -> np.ndarray:
        """Landmarks of a :class:`~viotb.vio.window_solver.LinearSystem` to drop, shape (L,) bool."""
        bad = sys.max_err > self.threshold
        if self.chi2_table is not None and len(bad):
            cost, dof = landmark_chi2(sys.reprojection_blocks, len(bad))
            bad |= cost > self.chi2_table(np.maximum(dof, 1.0).astype(np.int64))
        return bad
