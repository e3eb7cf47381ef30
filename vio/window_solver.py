"""Solver of the sliding-window optimizer: linearization, Schur elimination of landmarks, Levenberg-Marquardt.

The window's cost is the whitened sum of IMU factors, the linear prior left by marginalization (OKVIS eq. 9),
zero-velocity and no-motion factors on still keyframes, and Huber-robust reprojection factors
(:mod:`viotb.vio.window_factors`). :func:`linearize` builds its Gauss-Newton system with the landmarks kept
apart (sparse bundle-adjustment structure); :func:`schur_reduce` eliminates them from the damped system;
:func:`levenberg_marquardt` iterates on the manifold; :func:`newest_keyframe_covariance` inverts the
marginal information of the newest keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from viotb.vio.marginalization import LinearPrior
from viotb.vio.preintegration import ImuPreintegration
from viotb.vio.state import ImuValues
from viotb.vio.window_batch import ImuFactorStack, boxminus_batch, imu_factors, retract_batch, stack_values
from viotb.vio.window_calib import CalibValues
from viotb.vio.window_calib_system import CalibFactors, CalibTerms
from viotb.vio.window_factors import NX
from viotb.vio.window_linalg import block_index, coupled_index, schur_reduce, spd_solve
from viotb.vio.window_linalg import pose_index as pose_index  # re-exported: its home before
from viotb.vio.window_reprojection import (
    TrackBlocks,
    TrackPairs,
    WhiteBlocks,
    add_reprojection,
    summing_matrix,
    track_pairs,
)
from viotb.vio.window_weights import FactorWeights


@dataclass(frozen=True)
class Factors:
    """The factors of one linearization, by window index ``k`` of the keyframes they touch.

    Attributes:
        imu: ``(k, preintegration)`` of each IMU factor between keyframes ``k`` and ``k + 1``.
        prior: The linear prior, or None.
        prior_k: Window index of each of the prior's keyframes (``prior.keys`` order).
        still: Keyframes with a zero-velocity factor.
        no_motion: ``(k, dt_s)`` of each no-motion factor between keyframes ``k - 1`` and ``k``.
        obs: ``(kf index (M,), landmark index (M,), xy_norm (M, 2))`` of the cam0 reprojection factors.
        obs_right: The same for cam1 (stereo rigs; None or empty arrays for mono).
        calib: The online calibration's (:mod:`viotb.vio.window_calib_system`), or None (the extrinsics
            and time offset of :class:`FactorWeights` are fixed).
    """

    imu: list[tuple[int, ImuPreintegration]]
    prior: LinearPrior | None
    prior_k: list[int]
    still: list[int]
    no_motion: list[tuple[int, float]]
    obs: tuple[np.ndarray, np.ndarray, np.ndarray]
    obs_right: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    calib: CalibFactors | None = None


@dataclass
class LinearSystem:
    """Linearized window, landmarks not eliminated yet (``E[l] = H_{pose, l}`` over the 6N pose dims).

    Attributes:
        H: Information over the keyframe error states, shape (N NX, N NX).
        g: Gradient, shape (N NX,).
        H_ll: Landmark information blocks, shape (L, 3, 3).
        g_l: Landmark gradients, shape (L, 3).
        E: Pose-landmark blocks, shape (L, 6 N, 3).
        cost: Robust cost, prior included.
        n_res: Measurement residuals (prior excluded).
        max_err: Largest whitened reprojection error per landmark (sigmas), shape (L,).
        meas_cost: Cost without the prior.
        reprojection_blocks: Per camera, the reprojection factors' blocks
            (:mod:`viotb.vio.window_reprojection`), so the system of a subset of the landmarks needs no new
            linearization (:func:`viotb.vio.window_marginalize.landmark_subsystem`).
        imu_blocks: ``(k (K,), J^T J (K, 2 NX, 2 NX), J^T r (K, 2 NX))`` of the whitened IMU factors between
            keyframes ``k`` and ``k + 1``, or None.
        prior_terms: ``(indices (P NX,), H (P NX, P NX), gradient (P NX,))`` of the prior here, or None.
        n_calib: C online-calibration variables after the keyframes' states (``H`` and ``g`` are then
            ``N NX + C`` wide and ``E`` has ``6 N + C`` rows; :mod:`viotb.vio.window_calib_system`).
        compiled: Its Schur complements by the compiled kernel (``FactorWeights.kernels == "numba"``,
            :func:`schur_reduce`).
    """

    H: np.ndarray
    g: np.ndarray
    H_ll: np.ndarray
    g_l: np.ndarray
    E: np.ndarray
    cost: float
    n_res: int
    max_err: np.ndarray
    meas_cost: float
    reprojection_blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=list
    )
    imu_blocks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    prior_terms: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    n_calib: int = 0
    compiled: bool = False


@dataclass(frozen=True)
class PreparedFactors:
    """What :func:`linearize` needs of the factors that does not change with the values (one per solve).

    Attributes:
        imu: The IMU factors stacked, with their square-root information.
        prior_R0: Orientations of the prior's linearization points, shape (P, 3, 3).
        prior_rest0: Their ``[p, v, b_g, b_a]``, shape (P, 12).
        sums: Per camera (``obs``, then ``obs_right``), the sparse 0/1 matrices that sum the M observations'
            terms per keyframe (N, M) and per landmark (L, M), or with correlated track noise
            (``FactorWeights.track_q > 0``) the pairs of views of each landmark; None where the compiled
            blocks need neither (``FactorWeights.kernels == "numba"`` without online calibration).
    """

    imu: ImuFactorStack
    prior_R0: np.ndarray
    prior_rest0: np.ndarray
    sums: list[tuple[sparse.csr_matrix, sparse.csr_matrix] | TrackPairs | None]


def prepare(f: Factors, w8: FactorWeights, n_kf: int, n_lm: int) -> PreparedFactors:
    """What :func:`linearize` reuses for ``f`` over ``n_kf`` keyframes and ``n_lm`` landmarks."""
    R0, rest0 = (np.zeros((0, 3, 3)), np.zeros((0, 12))) if f.prior is None else stack_values(f.prior.x0)
    sums: list[tuple[sparse.csr_matrix, sparse.csr_matrix] | TrackPairs | None] = []
    for obs, focal_px in ((f.obs, w8.focal_px), (f.obs_right, w8.focal_px1)):
        if obs is not None and len(obs[0]) and w8.track_q > 0.0:
            sums.append(track_pairs(obs, n_kf, n_lm, focal_px, w8.track_q))
            continue
        # The compiled blocks sum themselves; the calibration's reprojection terms need the sums.
        if w8.kernels == "numba" and (f.calib is None or not f.calib.layout.camera_terms):
            sums.append(None)
            continue
        kf_i, lm_i = (np.zeros(0, dtype=np.int64),) * 2 if obs is None else obs[:2]
        sums.append((summing_matrix(kf_i, n_kf), summing_matrix(lm_i, n_lm)))
    return PreparedFactors(ImuFactorStack.build(f.imu, w8.noise), R0, rest0, sums)


def linearize(
    xs: list[ImuValues],
    pts: np.ndarray,
    f: Factors,
    w8: FactorWeights,
    prep: PreparedFactors | None = None,
    xs_lin: list[ImuValues] | None = None,
    calib: CalibValues | None = None,
) -> LinearSystem:
    """Whitened Gauss-Newton system at ``(xs, pts)`` (IRLS Huber weights) and its robust cost.

    With ``xs_lin`` the Jacobians of the IMU and reprojection factors are evaluated with the keyframes at
    those values (first-estimate Jacobians, Huang, Mourikis, Roumeliotis 2008; in a fixed-lag smoother
    Dong-Si and Mourikis, ICRA 2011: every factor on a keyframe that a marginalization prior holds uses
    the prior's linearization point, so the prior and the factors agree on the unobservable directions,
    global position and yaw, and the window gains no information along them); the residuals, the Huber
    weights and the cost stay at ``xs``.

    Args:
        xs: Keyframe values (N).
        pts: Landmarks in W (m), shape (L, 3).
        f: The factors.
        w8: Their noise models and the extrinsics.
        prep: ``prepare(f, w8)`` when the caller linearizes the same factors repeatedly (None: made here).
        xs_lin: Keyframe values of the Jacobians (N), or None (``xs``).
        calib: Current online calibration (``f.calib`` is then set), or None.
    """
    N, L = len(xs), len(pts)
    prep = prep if prep is not None else prepare(f, w8, N, L)
    D = N * NX
    H = np.zeros((D, D))
    g = np.zeros(D)
    cost = 0.0
    prior_cost = 0.0
    n_res = 0
    R, rest = stack_values(xs)
    R_lin, rest_lin = (R, rest) if xs_lin is None else stack_values(xs_lin)
    imu_blocks = prior_terms = None
    cal = None if calib is None else CalibTerms.zeros(N, L, f.calib.layout.dim)
    # a. IMU factors (Forster eq. 45), whitened by the Cholesky factor of their information.
    if len(prep.imu.k):
        intr = calib.imu_vector() if cal is not None and f.calib.layout.imu_terms else None
        r, J_i, J_j, J_T = imu_factors(prep.imu, R, rest, xs_lin is None, intr)
        if xs_lin is not None:
            _, J_i, J_j, J_T = imu_factors(prep.imu, R_lin, rest_lin, True, intr)
        W = prep.imu.sqrt_info
        r_w = np.einsum("kij,kj->ki", W, r)
        J = np.concatenate([W @ J_i, W @ J_j], axis=2)
        JT = np.swapaxes(J, 1, 2)
        JtJ, Jtr = JT @ J, np.einsum("kij,kj->ki", JT, r_w)
        # Blocks (k, k), (k, k+1), (k+1, k), (k+1, k+1) of H seen as (N, NX, N, NX); within each of the
        # four, the factors' keyframes differ, so fancy-indexed += adds every factor.
        k_i, H4, g2 = prep.imu.k, H.reshape(N, NX, N, NX), g.reshape(N, NX)
        for a in (0, 1):
            g2[k_i + a] += Jtr[:, a * NX : (a + 1) * NX]
            for b in (0, 1):
                H4[k_i + a, :, k_i + b, :] += JtJ[:, a * NX : (a + 1) * NX, b * NX : (b + 1) * NX]
        cost += 0.5 * float(np.sum(r_w * r_w))
        n_res += NX * len(prep.imu.k)
        imu_blocks = (k_i, JtJ, Jtr)
        if cal is not None and J_T is not None:  # the IMU's correction matrices (window_calib)
            cal.add_imu(k_i, W @ f.calib.layout.imu_columns(J_T), J, r_w)
    # b. Linear prior (OKVIS eq. 9): 0.5 dx^T H dx + g^T dx at dx = x [-] x0.
    pr = f.prior
    if pr is not None:
        k_pr = np.asarray(f.prior_k, dtype=np.int64)
        idx = (k_pr[:, None] * NX + np.arange(NX)[None, :]).ravel()
        dx = boxminus_batch(R[k_pr], rest[k_pr], prep.prior_R0, prep.prior_rest0).ravel()
        if cal is None:
            H[block_index(idx)] += pr.H
            g_pr = pr.H @ dx + pr.g
            g[idx] += g_pr
            prior_cost = float(0.5 * dx @ pr.H @ dx + pr.g @ dx)
        else:
            dc = calib.boxminus(f.calib.layout, f.calib.x0)
            g_pr, prior_cost = cal.add_prior(H, g, idx, pr, dx, dc)
        prior_terms = (idx, pr.H, g_pr)
        cost += prior_cost
    # b2. Zero-velocity factors ``v / sigma`` on still keyframes.
    for k in f.still:
        w_v = 1.0 / w8.zero_velocity_sigma_m_s
        sl = slice(k * NX + 6, k * NX + 9)
        r_v = w_v * xs[k].v_WB
        H[sl, sl] += w_v * w_v * np.eye(3)
        g[sl] += w_v * r_v
        cost += 0.5 * float(r_v @ r_v)
        n_res += 3
    # b3. No-motion factors ``(p_k - p_{k-1}) / (sigma dt)`` between consecutive still keyframes.
    for k, dt in f.no_motion:
        w_p = 1.0 / (w8.zero_velocity_sigma_m_s * dt)
        r_p = w_p * (xs[k].p_WB - xs[k - 1].p_WB)
        J = np.zeros((3, 2 * NX))
        J[:, 3:6], J[:, NX + 3 : NX + 6] = -w_p * np.eye(3), w_p * np.eye(3)
        sl = slice((k - 1) * NX, (k + 1) * NX)
        H[sl, sl] += J.T @ J
        g[sl] += J.T @ r_p
        cost += 0.5 * float(r_p @ r_p)
        n_res += 3
    # c. Reprojection factors of every camera, Huber-weighted (IRLS), landmarks kept apart for the Schur
    #    complement.
    H_ll = np.zeros((L, 3, 3))
    g_l = np.zeros((L, 3))
    E = np.zeros((L, N, 6, 3))
    max_err = np.zeros(L)
    blocks: list[WhiteBlocks | TrackBlocks] = []
    k_h = w8.huber_threshold
    cams = [(f.obs, (w8.R_BC, w8.p_BC, w8.sigma_norm, k_h), prep.sums[0])]
    if f.obs_right is not None and len(f.obs_right[0]) and w8.R_BC1 is not None:
        cams.append((f.obs_right, (w8.R_BC1, w8.p_BC1, w8.sigma_norm1, k_h), prep.sums[1]))
    poses = (R, rest[:, :3], R_lin, rest_lin[:, :3])
    if cal is not None and f.calib.layout.camera_terms:  # its values replace the extrinsics (window_calib)
        cams_c = [(obs, cam[2], k_h, sums) for obs, cam, sums in cams]
        arrays = (H, g, H_ll, g_l, E, max_err)
        c, n = cal.add_reprojection(arrays, poses, rest, pts, cams_c, calib, f.calib, blocks)
        cost, n_res, cams = cost + c, n_res + n, []
    for obs, cam, sums in cams:
        c, n = add_reprojection(
            H, g, H_ll, g_l, E, max_err, poses, pts, obs, cam, sums, blocks, compiled=w8.kernels == "numba"
        )
        cost += c
        n_res += n
    E_flat = E.reshape(L, N * 6, 3)
    if cal is not None:
        H, g, E_flat = cal.assemble(H, g, E_flat)
    meas, terms = cost - prior_cost, (blocks, imu_blocks, prior_terms, 0 if cal is None else len(cal.g_c))
    compiled = w8.kernels == "numba"
    return LinearSystem(H, g, H_ll, g_l, E_flat, cost, n_res, max_err, meas, *terms, compiled)


@dataclass(frozen=True)
class SolveResult:
    """Outcome of :func:`levenberg_marquardt`.

    Attributes:
        xs: Optimized keyframe values (N).
        pts: Optimized landmarks in W (m), shape (L, 3).
        system: The system linearized at ``(xs, pts)``.
        iterations: Trial steps taken (each linearized at its trial point; the budget's unit).
        converged: A stopping rule fired (small predicted or actual decrease) before the budget ran out.
        damping: The damping the next step would use: a solve continued later (a warm start) starts from it,
            so a rejected last step is not retried as it was.
    """

    xs: list[ImuValues]
    pts: np.ndarray
    system: LinearSystem
    iterations: int
    converged: bool
    damping: float


def predicted_decrease(sys: LinearSystem, lam: float, dx: np.ndarray, dl: np.ndarray) -> float:
    """Decrease of the Gauss-Newton model ``-g^T h - 1/2 h^T H h`` for the damped step ``h = (dx, dl)``.

    With ``(H + lam D) h = -g`` (``D`` the diagonal of H) it is ``1/2 (lam h^T D h - g^T h)`` (Madsen,
    Nielsen, Tingleff, "Methods for non-linear least squares problems", 2004, eq. 3.14), which needs no
    product with H.

    Args:
        sys: The system the step was solved from.
        lam: The damping of the step (relative to the diagonal).
        dx: Keyframe step, shape (N NX,).
        dl: Landmark step, shape (L, 3).
    """
    d_pose = np.diag(sys.H)
    d_lm = np.einsum("lii->li", sys.H_ll)
    damped = float(d_pose @ (dx * dx) + np.sum(d_lm * dl * dl))
    return 0.5 * (lam * damped - float(sys.g @ dx) - float(np.sum(sys.g_l * dl)))


@dataclass
class SolveState:
    """A Levenberg-Marquardt solve that can go on later (:func:`start_solve`, :func:`solve_steps`).

    Attributes:
        xs: Current keyframe values (N).
        pts: Current landmarks in W (m), shape (L, 3).
        system: The system linearized at ``(xs, pts)``.
        damping: The damping of the next step.
        iterations: Trial steps taken so far.
        converged: A stopping rule fired (small predicted or actual decrease).
        f: The factors.
        w8: Their noise models and the extrinsics.
        prep: ``prepare(f, w8, ...)``.
        fej: First-estimate values per keyframe (:func:`levenberg_marquardt`), or None.
        calib: Current online calibration (``f.calib`` set), or None.
    """

    xs: list[ImuValues]
    pts: np.ndarray
    system: LinearSystem
    damping: float
    iterations: int
    converged: bool
    f: Factors
    w8: FactorWeights
    prep: PreparedFactors
    fej: list[ImuValues | None] | None
    calib: CalibValues | None = None


def _jacobian_values(xs_at: list[ImuValues], fej: list[ImuValues | None] | None) -> list[ImuValues] | None:
    """The values of the Jacobians at ``xs_at``: the first estimates where there are (None: no FEJ)."""
    return None if fej is None else [x if x_fe is None else x_fe for x, x_fe in zip(xs_at, fej, strict=True)]


def start_solve(
    xs: list[ImuValues],
    pts: np.ndarray,
    f: Factors,
    w8: FactorWeights,
    initial_damping: float,
    fej: list[ImuValues | None] | None = None,
    calib: CalibValues | None = None,
) -> SolveState:
    """Linearize at the initial values: a solve of no steps yet (:func:`solve_steps` takes them)."""
    prep = prepare(f, w8, len(xs), len(pts))
    sys = linearize(xs, pts, f, w8, prep, _jacobian_values(xs, fej), calib)
    return SolveState(xs, pts, sys, initial_damping, 0, False, f, w8, prep, fej, calib)


def solve_steps(
    st: SolveState, max_steps: int, relative_tolerance: float = 1e-6, min_decrease: float = 0.0
) -> int:
    """Take at most ``max_steps`` more trial steps of ``st`` (in place); return the steps taken.

    One solve taken in several calls makes the same steps, in the same order and from the same values and
    damping, as one call with their sum: the rules are :func:`levenberg_marquardt`'s.
    """
    pidx = coupled_index(st.system)
    taken = 0
    while taken < max_steps and not st.converged:
        sys, lam = st.system, st.damping
        S, g_red, H_ll_inv = schur_reduce(sys, lam)
        dx = (spd_solve if sys.compiled else np.linalg.solve)(S, -g_red)
        rhs = sys.g_l + (np.swapaxes(sys.E, 1, 2) @ dx[pidx])
        dl = -(H_ll_inv @ rhs[:, :, None])[:, :, 0]
        if predicted_decrease(sys, lam, dx, dl) < min_decrease:
            st.converged = True
            break
        cal_new = None
        if st.calib is not None:
            n_x = len(st.xs) * NX
            dx, cal_new = dx[:n_x], st.calib.retract(st.f.calib.layout, dx[n_x:])
        xs_new = retract_batch(st.xs, dx)
        pts_new = st.pts + dl
        jac = _jacobian_values(xs_new, st.fej)
        sys_new = linearize(xs_new, pts_new, st.f, st.w8, st.prep, jac, cal_new)
        taken += 1
        st.iterations += 1
        if np.isfinite(sys_new.cost) and sys_new.cost <= sys.cost:
            small = sys.cost - sys_new.cost < relative_tolerance * sys.cost
            st.xs, st.pts, st.system, st.calib = xs_new, pts_new, sys_new, cal_new
            st.damping = max(lam / 10.0, 1e-8)
            st.converged = bool(small)
        else:
            st.damping = lam * 10.0
    return taken


def levenberg_marquardt(
    xs: list[ImuValues],
    pts: np.ndarray,
    f: Factors,
    w8: FactorWeights,
    max_iterations: int,
    initial_damping: float,
    relative_tolerance: float = 1e-6,
    min_decrease: float = 0.0,
    fej: list[ImuValues | None] | None = None,
) -> SolveResult:
    """Levenberg-Marquardt on the manifold, landmarks eliminated by the Schur complement in each solve.

    A step is kept when it does not raise the cost (damping / 10, at least 1e-8), else the damping grows
    10x. Each trial step costs one linearization at the trial point; ``max_iterations`` bounds them, a
    deterministic budget: the same problem always stops at the same step, and
    a solve cut short continues from its values at the next keyframe (they are the next solve's start).
    The iterations stop early when the model's predicted decrease of the next step is below
    ``min_decrease`` (before linearizing there: the step is not taken), or when a kept step lowered the cost
    by less than ``relative_tolerance`` of it. :func:`start_solve` and :func:`solve_steps` are the same solve
    taken in parts.

    Args:
        xs: Initial keyframe values (N).
        pts: Initial landmarks in W (m), shape (L, 3).
        f: The factors.
        w8: Their noise models and the extrinsics.
        max_iterations: Most trial steps (>= 0; 0 only linearizes at the initial values).
        initial_damping: Initial damping, relative to the diagonal.
        relative_tolerance: Convergence: a kept step that lowers the cost by less than this fraction.
        min_decrease: Convergence: a step whose predicted decrease of the cost (``0.5 chi^2`` units) is below
            this is not taken.
        fej: Per keyframe, the values of its first-estimate Jacobians (:func:`linearize`), or None where
            it has none (its Jacobians follow the iterations); None: no first estimates.

    Returns:
        The optimized values and the system linearized there (:class:`SolveResult`).
    """
    if max_iterations < 0:
        raise ValueError(f"levenberg_marquardt: max_iterations must be >= 0, got {max_iterations}")
    st = start_solve(xs, pts, f, w8, initial_damping, fej)
    solve_steps(st, max_iterations, relative_tolerance, min_decrease)
    return SolveResult(st.xs, st.pts, st.system, st.iterations, st.converged, st.damping)


def newest_keyframe_covariance(sys: LinearSystem) -> np.ndarray:
    """Covariance of the newest keyframe: the inverse of its marginal information, shape (NX, NX)."""
    S, _, _ = schur_reduce(sys, 0.0)
    n, k = S.shape[0], S.shape[0] - sys.n_calib - NX
    e_last = np.zeros((n, NX))
    e_last[k : k + NX] = np.eye(NX)
    return (spd_solve if sys.compiled else np.linalg.solve)(S, e_last)[k : k + NX]
