"""Tests of vio/metrics.py: known transforms recovered, closed-form errors, NEES statistics."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.vio.lie import rotmat_to_quat_wxyz, rotz
from viotb.vio.metrics import (
    align_umeyama,
    associate,
    ate_rmse,
    chi2_bounds,
    drift_pct,
    evaluate_trajectory,
    interpolate_trajectory,
    nees,
    path_length_m,
    rpe,
    scale_error_pct,
)
from viotb.vio.types import TrajectoryArrays


def _lissajous(n: int = 400, duration_s: float = 20.0) -> TrajectoryArrays:
    """A 3-D figure-eight trajectory with the body yawing along the path."""
    t = np.linspace(0.0, duration_s, n)
    w = 2 * np.pi / duration_s
    p = np.column_stack([3 * np.sin(w * t), 2 * np.sin(2 * w * t), 1.0 + 0.5 * np.sin(3 * w * t)])
    rots = Rotation.from_euler("ZYX", np.column_stack([0.5 * t, 0.1 * np.sin(t), 0.05 * np.cos(t)]))
    return TrajectoryArrays(t, p, np.roll(rots.as_quat(), 1, axis=1))


def _transform(traj: TrajectoryArrays, R: np.ndarray, t: np.ndarray, s: float = 1.0) -> TrajectoryArrays:
    rots = Rotation.from_matrix(R) * Rotation.from_quat(np.roll(traj.quat_wxyz_WB, -1, axis=1))
    return TrajectoryArrays(traj.t_s, s * traj.p_WB @ R.T + t, np.roll(rots.as_quat(), 1, axis=1))


@pytest.mark.parametrize("mode", ["posyaw", "se3", "sim3"])
def test_alignment_recovers_known_transform(mode):
    gt = _lissajous()
    R_true = rotz(0.7) if mode == "posyaw" else Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix()
    t_true = np.array([4.0, -2.0, 0.5])
    s_true = 1.3 if mode == "sim3" else 1.0
    # est = inverse transform of gt, so that aligning est onto gt recovers (R_true, t_true, s_true).
    p_est = (gt.p_WB - t_true) @ R_true / s_true
    al = align_umeyama(p_est, gt.p_WB, mode)
    np.testing.assert_allclose(al.R, R_true, atol=1e-9)
    np.testing.assert_allclose(al.t, t_true, atol=1e-9)
    assert al.s == pytest.approx(s_true, abs=1e-9)
    np.testing.assert_allclose(al.apply(p_est), gt.p_WB, atol=1e-9)


def test_posyaw_does_not_absorb_tilt_and_se3_does():
    gt = _lissajous()
    R_tilt = Rotation.from_rotvec([0.05, 0.0, 0.0]).as_matrix()
    p_est = gt.p_WB @ R_tilt.T
    assert ate_rmse(align_umeyama(p_est, gt.p_WB, "se3").apply(p_est), gt.p_WB) < 1e-9
    assert ate_rmse(align_umeyama(p_est, gt.p_WB, "posyaw").apply(p_est), gt.p_WB) > 1e-2


def test_ate_identical_is_zero_and_known_offset():
    gt = _lissajous()
    assert ate_rmse(gt.p_WB, gt.p_WB) == 0.0
    assert ate_rmse(gt.p_WB + np.array([0.0, 0.3, 0.4]), gt.p_WB) == pytest.approx(0.5, abs=1e-12)
    metrics = evaluate_trajectory(gt, gt)
    for key in ("ate_posyaw_m", "ate_se3_m", "rpe_1m_pct", "drift_pct", "scale_error_pct"):
        assert abs(metrics[key]) < 1e-9, key
    assert metrics["frames"] == len(gt)
    assert metrics["path_length_m"] == pytest.approx(path_length_m(gt.p_WB), rel=1e-12)


def test_evaluate_invariant_to_gauge_and_reports_scale():
    gt = _lissajous()
    est = _transform(gt, rotz(-1.1), np.array([3.0, 1.0, -2.0]))
    m = evaluate_trajectory(est, gt)
    assert m["ate_posyaw_m"] < 1e-9 and m["drift_pct"] < 1e-9 and m["rpe_1m_pct"] < 1e-9
    # A 5 % too large trajectory (about its start) reads +5 % scale error.
    big = TrajectoryArrays(gt.t_s, gt.p_WB[0] + 1.05 * (gt.p_WB - gt.p_WB[0]), gt.quat_wxyz_WB)
    assert evaluate_trajectory(big, gt)["scale_error_pct"] == pytest.approx(5.0, abs=1e-9)
    assert scale_error_pct(big.p_WB, gt.p_WB) == pytest.approx(5.0, abs=1e-9)


def test_path_length_closed_form():
    theta = np.linspace(0.0, 2 * np.pi, 100001)
    circle = np.column_stack([2.0 * np.cos(theta), 2.0 * np.sin(theta), np.zeros_like(theta)])
    assert path_length_m(circle) == pytest.approx(4 * np.pi, rel=1e-9)


def test_rpe_and_drift_with_known_constant_drift():
    """Straight line at 1 m/s with a velocity error of 0.02 m/s sideways: 2 % per metre, 2 % drift."""
    t = np.linspace(0.0, 30.0, 3001)
    p_gt = np.column_stack([t, np.zeros_like(t), np.ones_like(t)])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (t.size, 1))
    gt = TrajectoryArrays(t, p_gt, q)
    est = TrajectoryArrays(t, p_gt + np.column_stack([np.zeros_like(t), 0.02 * t, np.zeros_like(t)]), q)
    out = rpe(est, gt, (1.0, 5.0))
    assert out[1.0] == pytest.approx(2.0, rel=1e-9)
    assert out[5.0] == pytest.approx(2.0, rel=1e-9)
    assert drift_pct(est, gt) == pytest.approx(2.0, rel=1e-9)
    assert np.isnan(rpe(est, gt, (100.0,))[100.0])


def test_rpe_invariant_to_global_se3():
    gt = _lissajous()
    rng = np.random.default_rng(0)
    noisy = TrajectoryArrays(gt.t_s, gt.p_WB + 0.01 * rng.normal(size=gt.p_WB.shape), gt.quat_wxyz_WB)
    moved = _transform(noisy, Rotation.from_rotvec([0.2, 0.4, -1.0]).as_matrix(), np.array([5.0, 0.0, 1.0]))
    assert rpe(moved, gt)[1.0] == pytest.approx(rpe(noisy, gt)[1.0], rel=1e-9)
    assert rpe(noisy, gt)[1.0] > 0.5  # 1 cm noise on both ends over 1 m ~ 2 %


def test_associate_and_interpolate():
    t_gt = np.arange(0.0, 1.0, 0.1)
    t_est = np.array([-0.5, 0.001, 0.148, 0.152, 0.55, 0.9, 2.0])
    idx_est, idx_gt = associate(t_est, t_gt, max_dt_s=0.01)
    np.testing.assert_array_equal(idx_est, [1, 5])
    np.testing.assert_array_equal(idx_gt, [0, 9])
    # Interpolation: linear positions, slerped orientation about a fixed axis is linear in angle.
    n = t_gt.size
    gt = TrajectoryArrays(
        t_gt,
        np.column_stack([2.0 * t_gt, np.zeros(n), np.zeros(n)]),
        np.array([rotmat_to_quat_wxyz(rotz(3.0 * tk)) for tk in t_gt]),
        np.tile([2.0, 0.0, 0.0], (n, 1)),
    )
    at, inside = interpolate_trajectory(gt, t_est)
    np.testing.assert_array_equal(inside, [False, True, True, True, True, True, False])
    np.testing.assert_allclose(at.p_WB[:, 0], 2.0 * t_est[inside], atol=1e-12)
    np.testing.assert_allclose(at.v_WB[:, 0], 2.0, atol=1e-12)
    expected = np.array([rotmat_to_quat_wxyz(rotz(3.0 * tk)) for tk in t_est[inside]])
    np.testing.assert_allclose(at.quat_wxyz_WB, expected, atol=1e-12)


def test_nees_averages_dof_and_chi2_bounds():
    rng = np.random.default_rng(0)
    n, k = 4000, 3
    A = rng.normal(size=(n, k, k))
    covs = A @ np.transpose(A, (0, 2, 1)) + 0.1 * np.eye(k)
    errors = np.einsum("nij,nj->ni", np.linalg.cholesky(covs), rng.normal(size=(n, k)))
    values = nees(errors, covs)
    lo, hi = chi2_bounds(k, n, 0.95)
    assert lo < values.mean() < hi
    assert values.mean() == pytest.approx(k, abs=5 * np.sqrt(2 * k / n))
    # Over-confident covariances (half the truth) give NEES ~ 2 dof, outside the bounds.
    assert nees(errors, 0.5 * covs).mean() > hi
    # Closed-form bounds: one sample with 1 dof at 95 % is [chi2(0.025), chi2(0.975)] = [0.000982, 5.0239].
    lo1, hi1 = chi2_bounds(1, 1)
    assert lo1 == pytest.approx(0.0009820691, rel=1e-6) and hi1 == pytest.approx(5.0238862, rel=1e-6)


def test_evaluate_nees_with_consistent_position_covariances():
    gt = _lissajous(n=2000)
    rng = np.random.default_rng(0)
    sigma_m = np.array([0.05, 0.02, 0.03])
    covs = np.tile(np.diag(sigma_m**2), (len(gt), 1, 1))
    est = TrajectoryArrays(gt.t_s, gt.p_WB + sigma_m * rng.normal(size=gt.p_WB.shape), gt.quat_wxyz_WB)
    m = evaluate_trajectory(est, gt, covs)
    # White errors in a fixed frame: the run-wide alignment is the right one. It absorbs 4 of the 3 N dof:
    # the mean is (3 N - 4) / N, within the chi-square bounds of 3 dof.
    lo, hi = chi2_bounds(3, len(gt))
    assert lo < m["nees_pos_aligned_mean"] < hi


def test_nees_of_a_consistent_drifting_estimate_is_chi2_only_when_anchored():
    """A VIO-like estimate: its error is a random walk from zero at the first pose, covariance ``k Q``.

    Over 40 such runs the anchored NEES (``nees_pos_mean``) lies in the chi-square band of 3 dof; the
    run-wide posyaw alignment moves the first poses (covariance near zero) by the mean drift, and its NEES
    is several times too high for the same, consistent, estimate.
    """
    gt = _lissajous(n=300)
    rng = np.random.default_rng(4)
    q_m = np.array([0.004, 0.002, 0.003])  # per-step random-walk sigma (m), per axis
    k = np.arange(len(gt))
    covs = np.einsum("n,ij->nij", np.maximum(k, 1e-6), np.diag(q_m**2))  # k Q (tiny at the anchor)
    anchored, aligned = [], []
    for _ in range(40):
        steps = q_m * rng.normal(size=gt.p_WB.shape)
        steps[0] = 0.0
        est = TrajectoryArrays(gt.t_s, gt.p_WB + np.cumsum(steps, axis=0), gt.quat_wxyz_WB)
        m = evaluate_trajectory(est, gt, covs)
        anchored.append(m["nees_pos_mean"])
        aligned.append(m["nees_pos_aligned_mean"])
        assert m["nees_pos_anchored_mean"] == m["nees_pos_mean"]
    # 40 runs x 299 poses of 3 dof, but the poses of one run are correlated (a random walk), so the band
    # is that of 40 independent runs' means of chi-square(3) variables scaled to one dof each: use the
    # spread over runs instead of the per-pose band.
    mean, sem = float(np.mean(anchored)), float(np.std(anchored) / np.sqrt(len(anchored)))
    assert abs(mean - 3.0 * (len(gt) - 1) / len(gt)) < 3.0 * sem
    assert np.mean(aligned) > 2.0 * mean


def test_bad_input_errors():
    gt = _lissajous()
    with pytest.raises(ValueError, match="mode"):
        align_umeyama(gt.p_WB, gt.p_WB, "affine")
    with pytest.raises(ValueError, match="p_est"):
        align_umeyama(gt.p_WB[:, :2], gt.p_WB)
    late = TrajectoryArrays(gt.t_s + 100.0, gt.p_WB, gt.quat_wxyz_WB)
    with pytest.raises(ValueError, match="ground-truth span"):
        evaluate_trajectory(late, gt)
    with pytest.raises(ValueError, match="covs"):
        nees(np.zeros((3, 2)), np.zeros((3, 3, 3)))
