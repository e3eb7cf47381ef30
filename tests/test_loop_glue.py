"""``viotb eval --loop-closure`` end to end on a short rendered recording with a revisit, and the CLI checks.

The recording is 13 s of the 2 m ``circle`` (one lap is 8.4 s), rendered at 320x240; the estimator runs with
the ``sim`` front end (fast) while the loop closer works on the rendered images.
"""

from __future__ import annotations

import csv

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from viotb.envs.data.euroc import read_euroc
from viotb.envs.data.eval_frames import interpolate_pose
from viotb.envs.data.evaluate import EvalOptions, evaluate_dataset
from viotb.envs.data.record import record_scenario
from viotb.envs.data.tum import read_tum
from viotb.envs.run.loop_glue import (
    CSV_COLUMNS,
    FlightLoopClosure,
    LoopOptions,
    loop_options,
    require_images,
    returns_to_start,
)
from viotb.vio.lie import log_so3
from viotb.vio.loop import RigidTransform
from viotb.vio.types import StateEstimate, TrajectoryArrays


@pytest.fixture(scope="module")
def circle(tmp_path_factory):
    root = tmp_path_factory.mktemp("circle")
    record_scenario("circle", root / "data", seed=0, seconds=13.0)
    opts = EvalOptions(estimator="msckf", frontend="sim", loop=LoopOptions(map_out=root / "map.npz"))
    result = evaluate_dataset(root / "data", root / "eval", opts)
    return root, result


def test_eval_with_loop_closure_writes_closures_and_keys(circle):
    root, result = circle
    for key in ("loop_closures", "ate_posyaw_m", "ate_posyaw_odometry_m", "ate_posyaw_online_m"):
        assert key in result, key
    assert result["loop_closures"] >= 2  # measured: 4
    with (root / "eval" / "loop_closures.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert len(rows) == result["loop_closures"]
    assert (root / "map.npz").is_file() and (root / "eval" / "estimate_odometry_tum.txt").is_file()
    # Every accepted closure is right: relative pose within 5 cm and 1 deg of the truth.
    gt = read_euroc(root / "data").groundtruth
    for r in rows:
        T_m = RigidTransform(*interpolate_pose(gt, float(r["t_match_s"])))
        T_q = RigidTransform(*interpolate_pose(gt, float(r["t_query_s"])))
        T_true = T_m.inverse() @ T_q
        R = Rotation.from_quat([float(r[k]) for k in ("qx", "qy", "qz", "qw")]).as_matrix()
        p = np.array([float(r[k]) for k in "xyz"])
        assert np.linalg.norm(p - T_true.p) < 0.05
        assert np.rad2deg(np.linalg.norm(log_so3(T_true.R.T @ R))) < 1.0
    # The loop-closed trajectory is no worse than the odometry (which drifts little here: 1.4 cm).
    assert result["ate_posyaw_m"] <= result["ate_posyaw_odometry_m"] + 0.002
    assert result["loop_ms_per_frame_median"] < 2.0
    # The odometry's metric scale error, against the ratio of the two paths' RMS spreads about their means
    # (Umeyama's scale up to terms of order (error / spread)^2: (1.4 cm / 1 m)^2, 0.02 %).
    odo = read_tum(root / "eval" / "estimate_odometry_tum.txt")
    p_gt = np.stack([np.interp(odo.t_s, gt.t_s, gt.p_WB[:, k]) for k in range(3)], axis=1)
    spread = [np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))) for p in (odo.p_WB, p_gt)]
    assert result["scale_error_odometry_pct"] == pytest.approx(100.0 * (spread[0] / spread[1] - 1.0), abs=0.1)


def test_cli_options_are_checked():
    assert loop_options(False) is None
    with pytest.raises(ValueError, match="need --loop-closure"):
        loop_options(False, map_out="m.npz")
    with pytest.raises(ValueError, match="no such file"):
        loop_options(True, map_in="/nonexistent/map.npz")
    with pytest.raises(ValueError, match="needs camera images"):
        require_images("sim")
    require_images("klt")


def test_returns_to_the_start_are_found():
    t = np.linspace(0.0, 30.0, 601)
    p = np.stack([np.cos(2 * np.pi * t / 10.0) - 1.0, np.sin(2 * np.pi * t / 10.0), 0 * t], axis=1)
    traj = TrajectoryArrays(t, p, np.tile([1.0, 0, 0, 0], (len(t), 1)))
    np.testing.assert_allclose(t[returns_to_start(traj)], [10.0, 20.0, 30.0])


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["long-loop", "fail-long-loop"])
def test_long_loop_is_closed(tmp_path, scenario):
    # Measured (seed 0, KLT): long-loop 60 s ATE 7.1 -> 3.0 cm, returns 3.2/18.6/15.9 -> 0.8/2.0/2.8 cm;
    # fail-long-loop 80 s 17.0 -> 5.1 cm, 15.3/37.3/50.2 -> 1.5/1.7/2.7 cm; closures within 4.6 cm / 0.81 deg.
    seconds = 60.0 if scenario == "long-loop" else 80.0
    record_scenario(scenario, tmp_path / "data", seed=0, seconds=seconds)
    result = evaluate_dataset(tmp_path / "data", tmp_path / "eval", EvalOptions(loop=LoopOptions()))
    assert result["loop_closures"] >= 20
    if scenario == "fail-long-loop":  # drift dominates: the loops take most of it out
        assert result["ate_posyaw_m"] < 0.5 * result["ate_posyaw_odometry_m"]
    else:
        # Here the ratio measures the odometry more than the loops: what remains is the odometry's shape
        # within a lap, which loops between laps cannot observe (README "Loop closure against its targets").
        # When the odometry improved (7.1 -> 4.6 cm, session 7's KLT noise model), the loop-closed ATE went
        # 3.0 -> 2.4 cm and the ratio 0.42 -> 0.52. So the loop-closed ATE itself is bounded, at what this
        # test first measured, and it must still beat the odometry clearly.
        assert result["ate_posyaw_m"] < 0.030
        assert result["ate_posyaw_m"] < 0.6 * result["ate_posyaw_odometry_m"]
    returns = result["return_to_start_err_m"]
    assert max(returns[:-1]) < 0.025  # the last return is the recording's last frame: not yet confirmed


def test_flight_glue_blends_the_correction_and_leaves_the_filter_alone():
    lc = FlightLoopClosure(LoopOptions(), calib=None, frontend="klt")
    lc.closer.blender.set_target(0.0, RigidTransform.from_yaw(0.1, np.array([1.0, 0.0, 0.0])))
    est = StateEstimate(t_s=0.5, R_WB=np.eye(3), p_WB=np.zeros(3), v_WB=np.array([1.0, 0.0, 0.0]))
    half = lc.correct(0.5, est)
    np.testing.assert_allclose(half.p_WB, [0.5, 0.0, 0.0], atol=1e-12)  # halfway through the 1 s blend
    np.testing.assert_allclose(half.v_WB, [np.cos(0.05), np.sin(0.05), 0.0], atol=1e-12)
    np.testing.assert_allclose(est.p_WB, 0.0)  # the filter's estimate is not touched
    np.testing.assert_allclose(lc.correct(2.0, est).p_WB, [1.0, 0.0, 0.0], atol=1e-12)


def test_loop_closure_without_images_is_refused():
    # A sim flight with loop closure renders the camera for the closer (fly); without rendered images the
    # closer is refused.
    with pytest.raises(ValueError, match="needs camera images"):
        FlightLoopClosure(LoopOptions(), calib=None, frontend="sim")
    FlightLoopClosure(LoopOptions(), calib=None, frontend="sim", render_images=True)
