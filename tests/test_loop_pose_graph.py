"""Tests of the 4-DOF pose graph: closed forms on tiny graphs, drift removal on a synthetic two-lap loop."""

from __future__ import annotations

import numpy as np
import pytest
from viotb.vio.lie import exp_so3, rotz
from viotb.vio.loop.frames import RigidTransform, drift_4dof, loop_4dof, relative_4dof, wrap_angle
from viotb.vio.loop.params import PoseGraphParams
from viotb.vio.loop.pose_graph import Edge4Dof, PoseGraph4Dof


def test_chain_with_loop_matches_weighted_least_squares_closed_form():
    # x0 = 0 fixed; odometry says +1 m twice, the loop 0 -> 2 says 1.8 m. With weights w_o = 1/s_o^2 and
    # w_l = 1/s_l^2 the normal equations give x2 = 2 x1 and x1 = (w_o + 1.8 w_l) / (w_o + 2 w_l).
    params = PoseGraphParams(robust_kernel="none")
    graph = PoseGraph4Dof(params)
    for k in range(3):
        graph.add_node(k, 0.0, np.array([float(k), 0.0, 0.0]), fixed=(k == 0))
    graph.add_edge(Edge4Dof(0, 1, 0.0, np.array([1.0, 0.0, 0.0])))
    graph.add_edge(Edge4Dof(1, 2, 0.0, np.array([1.0, 0.0, 0.0])))
    graph.add_edge(Edge4Dof(0, 2, 0.0, np.array([1.8, 0.0, 0.0]), is_loop=True))
    graph.optimize()
    w_o = 1.0 / params.odometry_sigma_translation_m**2
    w_l = 1.0 / params.loop_sigma_translation_m**2
    x1 = (w_o + 1.8 * w_l) / (w_o + 2.0 * w_l)
    np.testing.assert_allclose(graph.node(1)[1], [x1, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(graph.node(2)[1], [2.0 * x1, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(graph.node(0)[1], 0.0, atol=1e-7)


@pytest.mark.parametrize("to_map", [False, True])
def test_misclosure_spreads_in_proportion_to_length_grown_and_map_loop_variances(to_map):
    # x0 = 0 fixed; odometry edges of 1 m and 2 m, the loop 0 -> 2 says 2.7 m. Each edge absorbs the 0.3 m
    # misclosure in proportion to its variance, s_k = s0 + rate * length_k for odometry, the loop's own
    # (map-loop sigma for a loop to a loaded map's keyframe).
    params = PoseGraphParams(
        robust_kernel="none",
        odometry_sigma_translation_m=0.01,
        odometry_sigma_translation_per_m=0.02,
        loop_sigma_translation_m=0.05,
        map_loop_sigma_translation_m=0.015,
    )
    graph = PoseGraph4Dof(params)
    for k, x in enumerate((0.0, 1.0, 3.0)):
        graph.add_node(k, 0.0, np.array([x, 0.0, 0.0]), fixed=(k == 0))
    graph.add_edge(Edge4Dof(0, 1, 0.0, np.array([1.0, 0.0, 0.0])))
    graph.add_edge(Edge4Dof(1, 2, 0.0, np.array([2.0, 0.0, 0.0])))
    graph.add_edge(Edge4Dof(0, 2, 0.0, np.array([2.7, 0.0, 0.0]), is_loop=True, to_map=to_map))
    graph.optimize()
    var = np.array([0.01 + 0.02 * 1.0, 0.01 + 0.02 * 2.0, 0.015 if to_map else 0.05]) ** 2
    x1 = 1.0 - 0.3 * var[0] / var.sum()
    x2 = x1 + 2.0 - 0.3 * var[1] / var.sum()
    np.testing.assert_allclose(graph.node(1)[1], [x1, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(graph.node(2)[1], [x2, 0.0, 0.0], atol=1e-7)


def test_yaw_cycle_spreads_misclosure_in_proportion_to_variances():
    # Four nodes turning in place by pi/2 + delta per edge, the last edge a loop: the 4 delta misclosure is
    # absorbed by each edge in proportion to its variance: increment_k = m_k - 4 delta s_k^2 / sum(s^2).
    params = PoseGraphParams(robust_kernel="none")
    delta = 0.05
    graph = PoseGraph4Dof(params)
    for k in range(4):
        graph.add_node(k, k * (np.pi / 2 + delta), np.zeros(3), fixed=(k == 0))
    for k in range(3):
        graph.add_edge(Edge4Dof(k, k + 1, np.pi / 2 + delta, np.zeros(3)))
    graph.add_edge(Edge4Dof(3, 0, np.pi / 2 + delta, np.zeros(3), is_loop=True))
    graph.optimize()
    s_o, s_l = params.odometry_sigma_yaw_rad, params.loop_sigma_yaw_rad
    increment = np.pi / 2 + delta - 4 * delta * s_o**2 / (3 * s_o**2 + s_l**2)
    for k in range(4):
        assert wrap_angle(graph.node(k)[0] - k * increment) == pytest.approx(0.0, abs=1e-7)
        np.testing.assert_allclose(graph.node(k)[1], 0.0, atol=1e-9)


def test_four_dof_measurements_are_invariant_to_a_yaw_translation_drift():
    rng = np.random.default_rng(0)
    R_i, R_j = exp_so3(rng.normal(size=3) * 0.3), exp_so3(rng.normal(size=3) * 0.3)
    p_i, p_j = rng.normal(size=3), rng.normal(size=3)
    drift = RigidTransform.from_yaw(0.7, np.array([1.0, -2.0, 0.5]))
    a = relative_4dof(R_i, p_i, R_j, p_j)
    b = relative_4dof(*drift.apply_pose(R_i, p_i), *drift.apply_pose(R_j, p_j))
    assert a[0] == pytest.approx(b[0], abs=1e-12)
    np.testing.assert_allclose(a[1], b[1], atol=1e-12)
    # The loop measurement from a 6-DOF relative pose agrees with the one from the two poses.
    T_ij = RigidTransform(R_i, p_i).inverse() @ RigidTransform(R_j, p_j)
    c = loop_4dof(drift.R @ R_i, T_ij)
    assert c[0] == pytest.approx(a[0], abs=1e-12)
    np.testing.assert_allclose(c[1], a[1], atol=1e-12)
    # drift_4dof recovers the drift from one pose pair.
    T = drift_4dof(*drift.apply_pose(R_i, p_i), R_i, p_i)
    np.testing.assert_allclose(T.R, drift.R, atol=1e-12)
    np.testing.assert_allclose(T.p, drift.p, atol=1e-12)


def _circle_truth(n_per_lap: int, laps: int) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(n_per_lap * laps)
    angle = 2 * np.pi * k / n_per_lap
    p = np.stack([2.0 * np.cos(angle), 2.0 * np.sin(angle), 1.0 + 0.2 * np.sin(3 * angle)], axis=1)
    yaw = np.array([wrap_angle(a + np.pi / 2) for a in angle])
    return yaw, p


def _two_lap_problem(params: PoseGraphParams, wrong_loop: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Position errors of odometry and of the solved graph (m) on two laps, and the solve time (ms)."""
    rng = np.random.default_rng(0)
    n, laps = 60, 2
    yaw_true, p_true = _circle_truth(n, laps)
    # Odometry: true 4-DOF increments with a yaw drift of 0.004 rad per keyframe (13.8 deg per lap) plus white
    # noise (1 mrad, 3 mm). A scale error would not do: a scaled circle still closes, so no loop observes it.
    yaw_odom, p_odom = [yaw_true[0]], [p_true[0]]
    for k in range(1, n * laps):
        dyaw, dp = relative_4dof(rotz(yaw_true[k - 1]), p_true[k - 1], rotz(yaw_true[k]), p_true[k])
        yaw_odom.append(wrap_angle(yaw_odom[-1] + dyaw + 0.004 + rng.normal() * 0.001))
        p_odom.append(p_odom[-1] + rotz(yaw_odom[-2]) @ dp + rng.normal(size=3) * 0.003)
    graph = PoseGraph4Dof(params)
    for k in range(n * laps):
        graph.add_node(k, yaw_odom[k], p_odom[k], fixed=(k == 0))
    for k in range(1, n * laps):
        meas = relative_4dof(rotz(yaw_odom[k - 1]), p_odom[k - 1], rotz(yaw_odom[k]), p_odom[k])
        graph.add_edge(Edge4Dof(k - 1, k, *meas))
    for k in range(n, n * laps, 3):  # loops of lap 2 onto lap 1, measured with noise (5 mrad, 1 cm)
        dyaw, dp = relative_4dof(rotz(yaw_true[k - n]), p_true[k - n], rotz(yaw_true[k]), p_true[k])
        graph.add_edge(Edge4Dof(k - n, k, dyaw + rng.normal() * 0.005, dp + rng.normal(size=3) * 0.01, True))
    if wrong_loop:  # 1.5 m and 17 deg off
        graph.add_edge(Edge4Dof(10, n + 40, 0.3, np.array([1.5, 0.0, 0.0]), True))
    report = graph.optimize()
    assert report.error_after < report.error_before
    p_opt = np.array([graph.node(k)[1] for k in range(n * laps)])
    return (
        np.linalg.norm(np.array(p_odom) - p_true, axis=1),
        np.linalg.norm(p_opt - p_true, axis=1),
        report.solve_ms,
    )


def test_synthetic_two_lap_loop_with_injected_drift_is_restored():
    err_odom, err_opt, _ = _two_lap_problem(PoseGraphParams(), wrong_loop=True)
    _, err_ref, _ = _two_lap_problem(PoseGraphParams(robust_kernel="none"), wrong_loop=False)
    rms = float(np.sqrt(np.mean(err_opt**2)))
    rms_ref = float(np.sqrt(np.mean(err_ref**2)))
    # Measured: odometry max 0.875 m; graph RMS 6.0 cm (max 9.7) with the wrong loop and the Huber kernel,
    # 7.8 cm (max 12.4) for plain least squares without the wrong loop.
    assert err_odom.max() > 0.8
    assert rms < 0.09
    assert err_opt.max() < 0.15
    assert abs(rms - rms_ref) < 0.03  # the wrong loop does not bend the graph
    # The solve time is a benchmark (benchmarks/loop_closure_truth.py reports it), not a timed test.
