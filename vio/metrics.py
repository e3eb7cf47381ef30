"""Trajectory metrics in the style of evo (Grupp, github.com/MichaelGrupp/evo).

* Alignment (Umeyama, "Least-squares estimation of transformation parameters between two point patterns",
  TPAMI 1991): ``p_gt ~= s R p_est + t`` with ``mode`` ``"se3"`` (6 DOF), ``"sim3"`` (7 DOF) or ``"posyaw"``
  (4 DOF: yaw about world z + translation, the VIO gauge of Chapter 6 of the lesson).
* ATE: RMSE of aligned positions (Sturm et al., "A benchmark for the evaluation of RGB-D SLAM", IROS 2012).
* RPE over travelled distance (KITTI odometry protocol, Geiger et al. CVPR 2012): relative translation error
  of pose pairs whose ground-truth path length apart is ``d``, in % of ``d``.
* NEES (Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking and Navigation", 2001,
  sec. 5.4.2) and its two-sided chi-square acceptance interval for the mean of ``n`` runs/samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp
from scipy.stats import chi2
from viotb.vio.lie import log_so3, quat_wxyz_to_rotmat, rotz, yaw_from_rotmat
from viotb.vio.types import TrajectoryArrays

ALIGN_MODES = ("posyaw", "se3", "sim3")


@dataclass(frozen=True)
class Alignment:
    """A similarity transform ``p_gt = s R p_est + t`` (the estimate's frame into the ground-truth frame).

    Attributes:
        R: Rotation, shape (3, 3).
        t: Translation (m), shape (3,).
        s: Scale (1.0 unless ``mode == "sim3"``).
    """

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    def apply(self, p: np.ndarray) -> np.ndarray:
        """Map points (m), shape (N, 3), from the estimate frame into the ground-truth frame."""
        return self.s * np.asarray(p, dtype=float) @ self.R.T + self.t

    def apply_rotation(self, R_WB: np.ndarray) -> np.ndarray:
        """Map orientations ``R_WB``, shape (N, 3, 3), into the ground-truth frame."""
        return np.einsum("ij,njk->nik", self.R, R_WB)


def _check_points(p: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(p, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def posyaw_alignment(mu_est: np.ndarray, mu_gt: np.ndarray, num: float, den: float) -> Alignment:
    """The 4-DOF (yaw + translation) alignment from the centred sums of :func:`align_umeyama`.

    The yaw maximizing ``sum y_i . Rz x_i`` over the centred points ``x = p_est - mu_est``,
    ``y = p_gt - mu_gt`` has ``tan(yaw) = num / den``; streamed metrics accumulate the sums in chunks.

    Args:
        mu_est: Mean estimated position (m), shape (3,).
        mu_gt: Mean ground-truth position (m), shape (3,).
        num: ``sum(x_x y_y - x_y y_x)`` (m^2).
        den: ``sum(x_x y_x + x_y y_y)`` (m^2).

    Returns:
        The :class:`Alignment` ``p_gt ~= Rz p_est + t`` (scale 1).
    """
    R = rotz(np.arctan2(num, den))
    return Alignment(R, mu_gt - R @ mu_est, 1.0)


def align_umeyama(p_est: np.ndarray, p_gt: np.ndarray, mode: str = "posyaw") -> Alignment:
    """Least-squares alignment of estimated positions onto ground truth.

    Args:
        p_est: Estimated positions (m), shape (N, 3).
        p_gt: Ground-truth positions at the same times (m), shape (N, 3).
        mode: ``"posyaw"`` (yaw + translation), ``"se3"`` (rotation + translation) or ``"sim3"`` (+ scale).

    Returns:
        The :class:`Alignment` minimizing ``sum |p_gt - (s R p_est + t)|^2``.
    """
    p_est = _check_points(p_est, "p_est")
    p_gt = _check_points(p_gt, "p_gt")
    if p_est.shape != p_gt.shape:
        raise ValueError(f"p_est {p_est.shape} and p_gt {p_gt.shape} must have the same shape")
    if mode not in ALIGN_MODES:
        raise ValueError(f"mode must be one of {ALIGN_MODES}, got {mode!r}")
    if p_est.shape[0] < 2:
        raise ValueError(f"alignment needs at least 2 positions, got {p_est.shape[0]}")
    # 1. Centre both point sets (Umeyama 1991, eqs. 34-35).
    mu_est, mu_gt = p_est.mean(axis=0), p_gt.mean(axis=0)
    x, y = p_est - mu_est, p_gt - mu_gt
    if mode == "posyaw":
        # 2a. Yaw maximizing sum y_i . Rz x_i (posyaw_alignment).
        num = float(np.sum(x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0]))
        den = float(np.sum(x[:, 0] * y[:, 0] + x[:, 1] * y[:, 1]))
        return posyaw_alignment(mu_est, mu_gt, num, den)
    # 2b. Cross-covariance and its SVD with the reflection guard (eqs. 38-43).
    n = p_est.shape[0]
    cov = y.T @ x / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = 1.0
    if mode == "sim3":
        var_est = float(np.mean(np.sum(x * x, axis=1)))
        if var_est <= 0.0:
            raise ValueError("sim3 alignment needs p_est with non-zero spread")
        s = float(np.trace(np.diag(D) @ S) / var_est)
    return Alignment(R, mu_gt - s * R @ mu_est, s)


def associate(t_est: np.ndarray, t_gt: np.ndarray, max_dt_s: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-timestamp association (TUM benchmark ``associate.py``), one ground-truth pose per estimate.

    Args:
        t_est: Estimate times (s), shape (N,), increasing.
        t_gt: Ground-truth times (s), shape (M,), increasing.
        max_dt_s: Largest accepted time difference (s).

    Returns:
        ``(idx_est, idx_gt)`` integer index arrays of the matched pairs, same length.
    """
    t_est = np.asarray(t_est, dtype=float)
    t_gt = np.asarray(t_gt, dtype=float)
    if t_gt.size == 0 or t_est.size == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    if np.any(np.diff(t_gt) <= 0.0):
        raise ValueError("t_gt must be strictly increasing")
    right = np.clip(np.searchsorted(t_gt, t_est), 1, t_gt.size - 1) if t_gt.size > 1 else np.zeros_like(t_est)
    right = right.astype(int)
    left = np.maximum(right - 1, 0)
    pick = np.where(np.abs(t_gt[left] - t_est) <= np.abs(t_gt[right] - t_est), left, right)
    ok = np.abs(t_gt[pick] - t_est) <= max_dt_s
    return np.flatnonzero(ok), pick[ok]


def ground_truth_gaps(t_ref_s: np.ndarray, max_gap_s: float | None = None) -> np.ndarray:
    """Indices ``i`` where ground truth has a gap ``t_ref_s[i] .. t_ref_s[i + 1]`` too long to interpolate.

    Motion capture drops out (occlusions) or covers only part of a run (TUM-VI's corridors: the start and
    the end); a straight line across a gap would be scored as if it were truth.

    Args:
        t_ref_s: Ground-truth stamps (s), shape (M,), strictly increasing.
        max_gap_s: Longest interval (s) interpolated across; default ``max(0.25 s, 10 x the median
            interval)``, so a 200 Hz mocap bridges a 50 ms dropout and a 1 Hz truth still interpolates.

    Returns:
        Integer indices (K,) of the gaps' first samples.
    """
    dt = np.diff(np.asarray(t_ref_s, dtype=float))
    if dt.size == 0:
        return np.zeros(0, dtype=int)
    limit = max(0.25, 10.0 * float(np.median(dt))) if max_gap_s is None else float(max_gap_s)
    return np.flatnonzero(dt > limit)


def positions_at(traj: TrajectoryArrays, t_s: np.ndarray) -> np.ndarray:
    """Positions (m, world frame) of ``traj`` linearly interpolated at ``t_s`` (s, shape (N,)): shape (N, 3).

    ``np.interp`` per axis: no gap or span check (:func:`interpolate_trajectory` has them); query times
    outside the span take the end positions.
    """
    return np.column_stack([np.interp(t_s, traj.t_s, traj.p_WB[:, k]) for k in range(3)])


def interpolate_trajectory(
    traj: TrajectoryArrays, t_s: np.ndarray, max_gap_s: float | None = None
) -> tuple[TrajectoryArrays, np.ndarray]:
    """Ground truth at arbitrary times: linear positions/velocities, slerp orientations.

    Args:
        traj: Trajectory with strictly increasing ``t_s``.
        t_s: Query times (s), shape (N,).
        max_gap_s: Query times inside a ground-truth gap longer than this are outside
            (:func:`ground_truth_gaps`, whose default this shares).

    Returns:
        ``(interpolated, inside)``: the trajectory at the query times inside ``traj``'s time span and not
        in one of its gaps, and the boolean mask (N,) of which query times were inside.
    """
    t_ref = np.asarray(traj.t_s, dtype=float)
    if t_ref.size < 2 or np.any(np.diff(t_ref) <= 0.0):
        raise ValueError("interpolation needs a trajectory with >= 2 strictly increasing timestamps")
    t_q = np.asarray(t_s, dtype=float)
    inside = (t_q >= t_ref[0]) & (t_q <= t_ref[-1])
    for i in ground_truth_gaps(t_ref, max_gap_s):
        inside &= ~((t_q > t_ref[i]) & (t_q < t_ref[i + 1]))
    tq = t_q[inside]
    p = positions_at(traj, tq)
    rots = Rotation.from_quat(np.roll(np.asarray(traj.quat_wxyz_WB, dtype=float), -1, axis=1))
    quat_xyzw = Slerp(t_ref, rots)(tq).as_quat() if tq.size else np.zeros((0, 4))
    v = None
    if traj.v_WB is not None:
        v = np.column_stack([np.interp(tq, t_ref, traj.v_WB[:, k]) for k in range(3)])
    return TrajectoryArrays(tq, p, np.roll(quat_xyzw, 1, axis=1), v), inside


def ate_rmse(p_est_aligned: np.ndarray, p_gt: np.ndarray) -> float:
    """Absolute trajectory error: RMSE (m) of already-aligned positions, shapes (N, 3)."""
    d = _check_points(p_est_aligned, "p_est_aligned") - _check_points(p_gt, "p_gt")
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def path_length_m(p: np.ndarray) -> float:
    """Length (m) of the polyline through positions, shape (N, 3)."""
    p = _check_points(p, "p")
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def _rotmats(traj: TrajectoryArrays) -> np.ndarray:
    return np.stack([quat_wxyz_to_rotmat(q) for q in np.asarray(traj.quat_wxyz_WB, dtype=float)])


def rpe(est: TrajectoryArrays, gt: TrajectoryArrays, distances_m: tuple[float, ...] = (1.0,)) -> dict:
    """Relative pose (translation) error over fixed travelled distances, in % of the distance.

    For every start pose i, j is the first pose whose ground-truth path length from i reaches ``d``. The error
    of the pair is ``|t(E)|`` with ``E = (T_gt_i^-1 T_gt_j)^-1 (T_est_i^-1 T_est_j)`` (KITTI protocol); the
    result is the mean over pairs of ``100 |t(E)| / L_ij`` with ``L_ij >= d`` the pair's ground-truth path
    length (the first pose at or past ``d``, so sampling does not bias the ratio). Invariant to any global
    SE(3) of the estimate.

    Args:
        est: Estimate, associated one-to-one with ``gt`` (same length and times).
        gt: Ground truth.
        distances_m: Segment lengths (m).

    Returns:
        ``{d: mean error (%)}``; NaN for a distance no pair of poses spans.
    """
    if len(est) != len(gt):
        raise ValueError(f"est ({len(est)}) and gt ({len(gt)}) must be associated one-to-one")
    p_gt = _check_points(gt.p_WB, "gt.p_WB")
    p_est = _check_points(est.p_WB, "est.p_WB")
    R_gt, R_est = _rotmats(gt), _rotmats(est)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p_gt, axis=0), axis=1))])
    out = {}
    for d in distances_m:
        if d <= 0.0:
            raise ValueError(f"distances_m must be positive, got {d}")
        j_all = np.searchsorted(cum, cum + d)
        errs = []
        for i, j in enumerate(j_all):
            if j >= len(cum):
                break
            dp_gt = R_gt[i].T @ (p_gt[j] - p_gt[i])
            dp_est = R_est[i].T @ (p_est[j] - p_est[i])
            dR_gt = R_gt[i].T @ R_gt[j]
            # Translation of E = rel_gt^-1 rel_est is dR_gt^T (dp_est - dp_gt).
            errs.append(np.linalg.norm(dR_gt.T @ (dp_est - dp_gt)) / (cum[j] - cum[i]) * 100.0)
        out[float(d)] = float(np.mean(errs)) if errs else float("nan")
    return out


def drift_pct(est: TrajectoryArrays, gt: TrajectoryArrays) -> float:
    """Final position error in % of the ground-truth path length, after aligning on the FIRST pose.

    The estimate is moved by the 4-DOF gauge (yaw + translation) that makes its first pose coincide with the
    first ground-truth pose (yaw from the orientations), so the error at the end is the drift accumulated
    over the whole run. NaN when the path is shorter than 1 mm.
    """
    if len(est) != len(gt) or len(est) < 2:
        raise ValueError("drift_pct needs >= 2 associated poses in est and gt")
    R_est0 = quat_wxyz_to_rotmat(est.quat_wxyz_WB[0])
    R_gt0 = quat_wxyz_to_rotmat(gt.quat_wxyz_WB[0])
    R_delta = R_gt0 @ R_est0.T
    R = rotz(np.arctan2(R_delta[1, 0], R_delta[0, 0]))
    t = gt.p_WB[0] - R @ est.p_WB[0]
    length = path_length_m(gt.p_WB)
    if length < 1e-3:
        return float("nan")
    return float(np.linalg.norm(R @ est.p_WB[-1] + t - gt.p_WB[-1]) / length * 100.0)


def scale_error_pct(p_est: np.ndarray, p_gt: np.ndarray) -> float:
    """Scale error (%) of the estimate from a Sim(3) alignment: ``100 (1 / s - 1)``.

    Positive when the estimated trajectory is too large (``p_est ~= (1 + e/100) p_gt`` gives ``e``).
    NaN when either trajectory spans less than 1 mm RMS about its mean (scale is then meaningless).
    """
    for p in (_check_points(p_est, "p_est"), _check_points(p_gt, "p_gt")):
        if np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))) < 1e-3:
            return float("nan")
    s = align_umeyama(p_est, p_gt, "sim3").s
    return float(100.0 * (1.0 / s - 1.0))


def nees(errors: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """Normalized estimation error squared ``e^T P^-1 e`` per sample.

    Args:
        errors: Errors, shape (N, k).
        covs: Covariances, shape (N, k, k), symmetric positive definite.

    Returns:
        NEES values, shape (N,).
    """
    e = np.asarray(errors, dtype=float)
    P = np.asarray(covs, dtype=float)
    if e.ndim != 2 or P.shape != (e.shape[0], e.shape[1], e.shape[1]):
        raise ValueError(f"errors (N, k) and covs (N, k, k) do not match: {e.shape} vs {P.shape}")
    return np.einsum("ni,ni->n", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])


def chi2_bounds(dof: int, n: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval of the mean of ``n`` independent NEES values with ``dof`` each.

    ``n * mean`` is chi-square with ``n * dof`` degrees of freedom (Bar-Shalom et al. 2001, eq. 5.4.2-9).
    """
    if dof < 1 or n < 1 or not 0.0 < prob < 1.0:
        raise ValueError(f"need dof >= 1, n >= 1, 0 < prob < 1; got dof={dof}, n={n}, prob={prob}")
    lo = chi2.ppf(0.5 * (1.0 - prob), n * dof) / n
    hi = chi2.ppf(0.5 * (1.0 + prob), n * dof) / n
    return float(lo), float(hi)


def anchor_first_pose(est: TrajectoryArrays, gt: TrajectoryArrays) -> Alignment:
    """The yaw-and-translation transform that puts the first estimate on the first ground-truth pose.

    A VIO filter fixes the four unobservable directions (position, yaw) at its initialization and reports
    covariances relative to that frame, so this is the transform under which its NEES is defined; a
    least-squares alignment over the whole run (posyaw) instead moves the early poses, whose covariance is
    near zero, by the mean drift.
    """
    R_e0, R_g0 = _rotmats(est)[0], _rotmats(gt)[0]
    Rz = rotz(yaw_from_rotmat(R_g0) - yaw_from_rotmat(R_e0))
    return Alignment(Rz, np.asarray(gt.p_WB[0], dtype=float) - Rz @ np.asarray(est.p_WB[0], dtype=float))


def _nees_means(
    align: Alignment,
    est: TrajectoryArrays,
    gt: TrajectoryArrays,
    pos_covs: np.ndarray | None,
    rot_covs: np.ndarray | None,
) -> tuple[float, float]:
    """Mean position and orientation NEES of ``est`` (matched to ``gt``) under ``align`` (NaN when no covs).

    Position: ``e = A p_est - p_gt`` with the covariance rotated by ``A``. Orientation: the body-frame
    error ``Log(R_est^T A^T R_gt)`` (``R = R_hat Exp(dtheta)``), whose covariance does not depend on the
    world frame.
    """
    pos = rot = float("nan")
    if pos_covs is not None:
        covs_W = np.einsum("ij,njk,lk->nil", align.R, pos_covs, align.R)
        pos = float(np.mean(nees(align.apply(est.p_WB) - gt.p_WB, covs_W)))
    if rot_covs is not None:
        R_err = np.einsum("nji,njk->nik", align.apply_rotation(_rotmats(est)), _rotmats(gt))
        rot = float(np.mean(nees(np.array([log_so3(R) for R in R_err]), rot_covs)))
    return pos, rot


def evaluate_trajectory(
    est: TrajectoryArrays,
    gt: TrajectoryArrays,
    pos_covs: np.ndarray | None = None,
    rot_covs: np.ndarray | None = None,
) -> dict[str, float | int]:
    """The ``viotb eval`` metrics of an estimate against ground truth.

    Ground truth is interpolated at the estimate times; estimates outside its span are dropped.

    Args:
        est: Estimated trajectory.
        gt: Ground truth (any rate).
        pos_covs: Optional position covariances of the estimate (m^2), shape (len(est), 3, 3), in the
            estimate's world frame; rotated by the alignment before computing NEES.
        rot_covs: Optional orientation covariances (rad^2), shape (len(est), 3, 3), of the body-frame error
            ``dtheta`` in ``R_WB = R_hat Exp(dtheta)``; the error is ``Log(R_hat^T A^T R_gt)`` with ``A`` the
            alignment (a body-frame error does not depend on the world frame).

    Returns:
        Dict with ``ate_posyaw_m``, ``ate_se3_m``, ``rpe_1m_pct``, ``drift_pct``, ``scale_error_pct``,
        ``frames`` (poses evaluated), ``path_length_m`` (ground truth over the evaluated span) and the NEES:

        - ``nees_pos_mean`` (NaN without covariances) and ``nees_rot_mean`` (only with ``rot_covs``): under
          :func:`anchor_first_pose`, the frame a VIO estimator's covariance refers to (it fixes position
          and yaw at its initialization, so its error and covariance grow from zero there);
        - ``nees_pos_aligned_mean`` / ``nees_rot_aligned_mean``: under the run-wide posyaw alignment of
          ``ate_posyaw_m``, which moves the early poses (covariance near zero) by the mean drift and so
          overstates a drifting estimator's NEES (``tests/test_metrics.py`` shows both on a consistent
          random-walk drift); right only for an estimator whose errors are white in a fixed frame;
        - ``nees_pos_anchored_mean`` / ``nees_rot_anchored_mean``: the same values as ``nees_pos_mean`` /
          ``nees_rot_mean``, under the names of earlier versions.
    """
    gt_at, inside = interpolate_trajectory(gt, est.t_s)
    if int(inside.sum()) < 3:
        raise ValueError(
            f"only {int(inside.sum())} estimate times fall inside the ground-truth span "
            f"[{gt.t_s[0]:.3f}, {gt.t_s[-1]:.3f}] s; need >= 3"
        )
    est_in = TrajectoryArrays(
        np.asarray(est.t_s)[inside],
        np.asarray(est.p_WB, dtype=float)[inside],
        np.asarray(est.quat_wxyz_WB, dtype=float)[inside],
        None if est.v_WB is None else np.asarray(est.v_WB)[inside],
    )
    posyaw = align_umeyama(est_in.p_WB, gt_at.p_WB, "posyaw")
    se3 = align_umeyama(est_in.p_WB, gt_at.p_WB, "se3")
    anchor = anchor_first_pose(est_in, gt_at)
    nees_mean = nees_aligned = float("nan")
    if pos_covs is not None:
        pos_covs = np.asarray(pos_covs, dtype=float)
        if pos_covs.shape != (len(est), 3, 3):
            raise ValueError(f"pos_covs must have shape ({len(est)}, 3, 3), got {pos_covs.shape}")
        pos_covs = pos_covs[inside]
        nees_mean = _nees_means(anchor, est_in, gt_at, pos_covs, None)[0]
        nees_aligned = _nees_means(posyaw, est_in, gt_at, pos_covs, None)[0]
    out: dict[str, float | int] = {
        "ate_posyaw_m": ate_rmse(posyaw.apply(est_in.p_WB), gt_at.p_WB),
        "ate_se3_m": ate_rmse(se3.apply(est_in.p_WB), gt_at.p_WB),
        "rpe_1m_pct": rpe(est_in, gt_at, (1.0,))[1.0],
        "drift_pct": drift_pct(est_in, gt_at),
        "scale_error_pct": scale_error_pct(est_in.p_WB, gt_at.p_WB),
        "nees_pos_mean": nees_mean,
        "nees_pos_aligned_mean": nees_aligned,
        "nees_pos_anchored_mean": nees_mean,
        "frames": len(est_in),
        "path_length_m": path_length_m(gt_at.p_WB),
    }
    if rot_covs is not None:
        rot_covs = np.asarray(rot_covs, dtype=float)
        if rot_covs.shape != (len(est), 3, 3):
            raise ValueError(f"rot_covs must have shape ({len(est)}, 3, 3), got {rot_covs.shape}")
        rot_covs = rot_covs[inside]
        out["nees_rot_mean"] = out["nees_rot_anchored_mean"] = _nees_means(
            anchor, est_in, gt_at, None, rot_covs
        )[1]
        out["nees_rot_aligned_mean"] = _nees_means(posyaw, est_in, gt_at, None, rot_covs)[1]
    return out
