"""Marginalization of the window's oldest keyframe into a linear prior (OKVIS sec. IV-E, VINS-Mono sec. VI-D).

When the window is full, the oldest keyframe leaves it together with every landmark it observed (with all
their observations); what those factors said about the remaining keyframes stays as a linear prior
(:mod:`viotb.vio.marginalization`, OKVIS eq. 9):

1. The factors touching the marginalized variables: the prior, the oldest IMU link, its zero-velocity and
   no-motion factors, and the observations of its landmarks, linearized at the keyframes' current values.
   When the window's solve has just linearized every factor there, its per-observation blocks
   (``LinearSystem.reprojection_blocks``) give the landmarks' part without a new linearization
   (:func:`landmark_subsystem`); only the few IMU, prior and zero-velocity factors are linearized again.
2. Eliminate those landmarks, then the oldest keyframe (Schur complement).

Those landmarks' later observations start fresh tracks, so no measurement is used twice.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from viotb.vio.marginalization import LinearPrior, schur_complement
from viotb.vio.state import ImuValues
from viotb.vio.window_calib_state import OnlineCalibration
from viotb.vio.window_calib_system import CalibFactors
from viotb.vio.window_factors import NX
from viotb.vio.window_map import (
    ImuLink,
    Keyframe,
    drop_landmark,
    fix_first_estimates,
    observations,
)
from viotb.vio.window_solver import (
    Factors,
    FactorWeights,
    LinearSystem,
    block_index,
    linearize,
    schur_reduce,
)


def window_factors(
    keyframes: list[Keyframe],
    links: list[ImuLink],
    prior: LinearPrior | None,
    link_idx: Iterable[int],
    still: list[int],
    no_motion: list[int],
    obs: tuple[np.ndarray, np.ndarray, np.ndarray],
    obs1: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    calib: CalibFactors | None = None,
) -> Factors:
    """The window's factors: IMU ``link_idx``, the prior, ``still``/``no_motion`` keyframes, observations.

    Args:
        keyframes: The window's keyframes (N).
        links: Their IMU links (N - 1).
        prior: The marginalization prior, or None.
        link_idx: Indices of the IMU links to include (link ``k`` joins keyframes ``k`` and ``k + 1``).
        still: Window indices of keyframes with a zero-velocity factor.
        no_motion: Window indices ``k`` of no-motion factors between keyframes ``k - 1`` and ``k``.
        obs: Cam0 observations (:func:`observations`).
        obs1: Cam1 observations, or None.
        calib: The online calibration's factors, or None.
    """
    key_to_k = {kf.key: k for k, kf in enumerate(keyframes)}
    prior_k = [] if prior is None else [key_to_k[key] for key in prior.keys]
    return Factors(
        imu=[(k, links[k].pre) for k in link_idx],
        prior=prior,
        prior_k=prior_k,
        still=still,
        no_motion=[(k, keyframes[k].t_s - keyframes[k - 1].t_s) for k in no_motion],
        obs=obs,
        obs_right=obs1,
        calib=calib,
    )


def solve_factors(
    keyframes: list[Keyframe],
    links: list[ImuLink],
    prior: LinearPrior | None,
    landmarks: dict[int, np.ndarray],
) -> tuple[list[int], np.ndarray, Factors]:
    """Every factor of the window's solve: ``(landmark ids (L,), their points in W (L, 3) m, factors)``.

    The IMU links, the prior, the zero-velocity factors of still keyframes, the no-motion factors between
    consecutive still ones and the observations of every landmark (ids in increasing order) in each camera.
    """
    lm_ids = sorted(landmarks)
    pts = np.array([landmarks[f] for f in lm_ids]).reshape(-1, 3)
    obs = observations(keyframes, lm_ids)
    obs1 = observations(keyframes, lm_ids, cam=1)
    still = [k for k, kf in enumerate(keyframes) if kf.still]
    no_motion = [k for k in still if k >= 1 and keyframes[k - 1].still]
    f = window_factors(keyframes, links, prior, range(len(links)), still, no_motion, obs, obs1)
    return lm_ids, pts, f


def landmark_subsystem(solved: LinearSystem, rows: np.ndarray, base: LinearSystem) -> LinearSystem:
    """``base`` plus the reprojection factors of landmarks ``rows`` of ``solved`` (no new linearization).

    Args:
        solved: A system linearized over N keyframes and L landmarks, with its ``reprojection_blocks``.
        rows: The landmarks to keep (rows of ``solved``), shape (L',).
        base: The other factors' system over the same N keyframes at the same values (no landmarks).

    Returns:
        The system of ``base``'s factors and every observation of the landmarks ``rows`` (their rows of
        ``H_ll``, ``g_l``, ``E``, ``max_err`` in ``rows`` order); the cost is ``base``'s.
    """
    rows = np.asarray(rows, dtype=np.int64)
    n_kf = len(base.g) // NX
    keep = np.zeros(len(solved.H_ll), dtype=bool)
    keep[rows] = True
    H, g = base.H.copy(), base.g.copy()
    H_kk = np.zeros((n_kf, n_kf, 6, 6))
    g_k = np.zeros((n_kf, 6))
    for blocks in solved.reprojection_blocks:
        H_b, g_b = blocks.pose_terms(keep, n_kf)
        H_kk += H_b
        g_k += g_b
    H.reshape(n_kf, NX, n_kf, NX)[:, :6, :, :6] += np.swapaxes(H_kk, 1, 2)
    g.reshape(n_kf, NX)[:, :6] += g_k
    return LinearSystem(
        H,
        g,
        solved.H_ll[rows],
        solved.g_l[rows],
        solved.E[rows],
        base.cost,
        base.n_res,
        solved.max_err[rows],
        base.meas_cost,
        compiled=solved.compiled,
    )


def _solved_base(
    solved: LinearSystem,
    xs: list[ImuValues],
    w8: FactorWeights,
    still: list[int],
    no_motion: list[int],
    keyframes: list[Keyframe],
) -> LinearSystem:
    """The oldest keyframe's prior, IMU link and zero-velocity factors, from a solve's stored terms.

    The prior's and the first IMU link's blocks are the solve's own (``solved.prior_terms``,
    ``solved.imu_blocks``); the zero-velocity and no-motion factors are linearized (a few 3x3 blocks).
    """
    n_kf = len(xs)
    H, g = np.zeros((n_kf * NX, n_kf * NX)), np.zeros(n_kf * NX)
    if still or no_motion:
        empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
        f = window_factors(keyframes, [], None, [], still, no_motion, empty, None)
        base = linearize(xs, np.zeros((0, 3)), f, w8)
        H, g = base.H, base.g
    if solved.prior_terms is not None:
        idx, H_pr, g_pr = solved.prior_terms
        H[block_index(idx)] += H_pr
        g[idx] += g_pr
    if solved.imu_blocks is not None:
        k_imu, JtJ, Jtr = solved.imu_blocks
        first = np.nonzero(k_imu == 0)[0]
        if len(first):
            H[: 2 * NX, : 2 * NX] += JtJ[first[0]]
            g[: 2 * NX] += Jtr[first[0]]
    return LinearSystem(
        H, g, np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 6 * n_kf, 3)), 0.0, 0, np.zeros(0), 0.0
    )


def marginalize_oldest(
    keyframes: list[Keyframe],
    links: list[ImuLink],
    landmarks: dict[int, np.ndarray],
    prior: LinearPrior | None,
    w8: FactorWeights,
    first_estimates: bool,
    solved: tuple[LinearSystem, list[int]] | None = None,
    calib: OnlineCalibration | None = None,
) -> tuple[LinearPrior, list[Keyframe], list[ImuLink]]:
    """Fold the oldest keyframe and the landmarks it saw into a new linear prior (Schur complement).

    Args:
        keyframes: The window (N >= 2); the marginalized landmarks' observations are removed from it.
        links: Its IMU links (N - 1).
        landmarks: Feature id -> point in W (m); the marginalized landmarks are removed.
        prior: The current prior, or None.
        w8: The factors' noise models and extrinsics.
        first_estimates: Linearize at the keyframes' first estimates (``Keyframe.x_fej``, set here for
            those without one).
        solved: ``(system, landmark ids)`` of a solve linearized at the keyframes' current values (and
            first estimates) over those landmarks (its rows), or None (linearize the factors here).
        calib: The online calibration, or None. Its variables stay, after the kept keyframes' in the new
            prior, linearized at its current values (its ``x0`` becomes them); the factors are linearized
            here (the solve's blocks do not hold the calibration's columns).

    Returns:
        ``(new prior over keyframes 1..N-1, keyframes[1:], links[1:])``.
    """
    old = keyframes[0]
    lm_ids = sorted(f for f in old.obs.keys() | old.obs_right.keys() if f in landmarks)
    xs = [kf.x for kf in keyframes]
    still = [0] if old.still else []
    no_motion = [1] if old.still and keyframes[1].still else []
    xs_lin = fix_first_estimates(keyframes) if first_estimates else None
    # 1. The factors touching the marginalized variables.
    if solved is not None and calib is None:
        sys_all, solved_ids = solved
        row_of = {f: j for j, f in enumerate(solved_ids)}
        base = _solved_base(sys_all, xs, w8, still, no_motion, keyframes)
        sys = landmark_subsystem(sys_all, np.array([row_of[f] for f in lm_ids], dtype=np.int64), base)
    else:
        pts = np.array([landmarks[f] for f in lm_ids]).reshape(-1, 3)
        obs = observations(keyframes, lm_ids)
        obs1 = observations(keyframes, lm_ids, cam=1)
        f = window_factors(keyframes, links, prior, [0], still, no_motion, obs, obs1)
        f = f if calib is None else calib.factors(keyframes, f)
        sys = linearize(xs, pts, f, w8, xs_lin=xs_lin, calib=None if calib is None else calib.values)
    # 2. Eliminate those landmarks, then the oldest keyframe.
    S, g_red, _ = schur_reduce(sys, 0.0)
    H_p, g_p, _ = schur_complement(S, g_red, np.arange(NX))
    rest = keyframes[1:]
    new_prior = LinearPrior(H_p, g_p, [kf.key for kf in rest], [kf.x.copy() for kf in rest])
    if calib is not None:
        calib.x0 = calib.values
    for fid in lm_ids:
        drop_landmark(keyframes, landmarks, fid)
    return new_prior, rest, links[1:]
