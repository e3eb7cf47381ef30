"""Run an estimator over any EuRoC-layout folder (recorded here or real) and measure it.

This is the engine of ``viotb eval``: it replays the IMU and camera streams in timestamp order on the IMU
clock, times the estimator per frame, writes TUM trajectories and returns the metrics of
:mod:`viotb.vio.metrics`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from viotb.envs.data import diagnosis
from viotb.envs.data.euroc import EurocDataset, read_euroc
from viotb.envs.data.euroc_truth import GROUNDTRUTH_SOURCES
from viotb.envs.data.eval_frames import (
    apply_imu_gap_policy,
    camera_frame,
    covariances_usable,
    truth_estimate,
    usable_frames,
)
from viotb.envs.data.eval_options import NULL_REASONS, EvalOptions
from viotb.envs.data.tum import write_tum
from viotb.envs.run.loop_glue import apply_loop_closure
from viotb.envs.run.replay import MonitoredRun, replay
from viotb.envs.tools.outdir import atomic_out_dir
from viotb.vio.factory import CALIBRATING_ESTIMATORS, make_estimator
from viotb.vio.health import HealthMonitor, HealthParams
from viotb.vio.lie import rotmat_to_quat_wxyz
from viotb.vio.metrics import evaluate_trajectory
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.types import StateEstimate, TrajectoryArrays
from viotb.vio.window_params import WindowParams

ProgressFn = Callable[[float, float], None]

__all__ = ["NULL_REASONS", "EvalOptions", "evaluate_dataset", "run_monitored"]


def _monitor(ds: EurocDataset, opts: EvalOptions, filter_sigma_px: float) -> HealthMonitor | None:
    """The health monitor of a run (None when ``opts.monitor`` is off)."""
    if not opts.monitor:
        return None
    if opts.health is not None:
        return HealthMonitor(opts.health)
    expected = diagnosis.expected_nis_per_dof(
        opts.frontend, filter_sigma_px, opts.sim_pixel_sigma_px, ds.landmarks_W is not None, opts.estimator
    )
    return HealthMonitor(HealthParams(nis_per_dof_expected=expected))


def render_noise_hint(ds: EurocDataset, opts: EvalOptions) -> str:
    """A note for an MSCKF told 1 px on one of this project's KLT renders ('' otherwise).

    On the renders (datasets with ``sim_landmarks0``) the KLT tracks follow their points to ~0.03 px and the
    simulated IMU has scale and misalignment errors; the filter told 1 px is underconfident there, and its
    measured model is the render noise with the IMU intrinsics (README "Consistency per scenario").
    """
    if opts.estimator != "msckf" or opts.frontend != "klt" or ds.landmarks_W is None:
        return ""
    if opts.msckf is not None and opts.msckf.pixel_sigma_px != MsckfParams().pixel_sigma_px:
        return ""
    return (
        "one of this project's renders, told 1 px: its measured model is --sensor-model render "
        "(MsckfParams.with_render_sensor_model: consistent and 1.9-6.3x more accurate on the 40 s "
        "recordings of README 'Consistency per scenario')"
    )


def run_monitored(ds: EurocDataset, opts: EvalOptions, progress: ProgressFn | None = None) -> MonitoredRun:
    """Replay a dataset through an estimator, with the health monitor when ``opts.monitor``.

    Raises:
        ValueError: ``opts.calibrate`` with an estimator other than ``msckf`` or ``window``.
    """
    if opts.cameras == 2 and not ds.has_stereo:
        raise ValueError(f"{ds.root}: --cameras 2 needs a cam1 folder (this dataset is mono)")
    if opts.estimator == "ground-truth" and ds.groundtruth is None:
        raise ValueError(
            f"{ds.root}: the ground-truth estimator needs ground truth (one of "
            f"{', '.join(s + '/data.csv' for s in GROUNDTRUTH_SOURCES)}), which this dataset does not have"
        )
    # The stereo keyword goes only to a stereo run, so mono runs do not depend on the stereo estimators.
    stereo = {"calib_right": ds.calib_right} if opts.cameras == 2 else {}
    params, window = opts.msckf, opts.window
    if opts.calibrate:
        if opts.estimator not in CALIBRATING_ESTIMATORS:
            raise ValueError(
                f"--calibrate needs the msckf or window estimator (online time-offset and extrinsic "
                f"calibration); {opts.estimator!r} has none"
            )
        if opts.estimator == "msckf":
            params = (params if params is not None else MsckfParams()).with_online_calibration()
        else:
            window = (window if window is not None else WindowParams()).with_online_calibration()
    est = make_estimator(
        opts.estimator,
        ds.calib,
        ds.imu_noise,
        frontend=opts.frontend,
        params=params,
        window_params=window,
        **stereo,
    )
    if opts.estimator == "window":
        filter_sigma = (window if window is not None else WindowParams()).pixel_sigma_px
    else:
        filter_sigma = (params if params is not None else MsckfParams()).pixel_sigma_px
    true_calib = diagnosis.read_true_calibration(ds.root) or ds.calib
    rng = np.random.default_rng(opts.seed)
    first, stop = usable_frames(ds, opts)
    n_frames = stop - first
    frame_t_imu = ds.cam_t_s[first:stop] + ds.calib.time_offset_s
    # Start the IMU one second before the first frame (static initialization needs a still window).
    imu_start = float(frame_t_imu[0]) - 1.0 if n_frames else None
    truth_at = (lambda t: truth_estimate(ds, t)) if opts.estimator == "ground-truth" else None
    frames = (camera_frame(ds, k, opts, rng, true_calib) for k in range(first, stop))
    return replay(
        est,
        ds.imu,
        frames,
        ds.calib.time_offset_s,
        monitor=_monitor(ds, opts, filter_sigma),
        imu_start_s=imu_start,
        truth_at=truth_at,
        progress=progress,
        n_frames=n_frames,
    )


def estimates_to_trajectory(estimates: list[StateEstimate]) -> TrajectoryArrays:
    """Stack estimates into a :class:`TrajectoryArrays` (empty arrays when there are none)."""
    if not estimates:
        return TrajectoryArrays(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)))
    return TrajectoryArrays(
        t_s=np.array([e.t_s for e in estimates]),
        p_WB=np.array([e.p_WB for e in estimates]),
        quat_wxyz_WB=np.array([rotmat_to_quat_wxyz(e.R_WB) for e in estimates]),
        v_WB=np.array([e.v_WB for e in estimates]),
    )


def msckf_settings(params: MsckfParams | None) -> dict:
    """The MSCKF settings a result names: pixel noise, track walk, IMU intrinsics, clone spacing."""
    p = params if params is not None else MsckfParams()
    return {
        "pixel_sigma_px": p.pixel_sigma_px,
        "track_random_walk_px2_per_px": p.klt.track_random_walk_px2_per_px,
        "imu_intrinsics": p.imu_intrinsics,
        "rotation_compensated_keyframes": p.keyframing.rotation_compensated,
    }


def window_settings(params: WindowParams | None) -> dict:
    """The window settings a result names: pixel noise, track walk when modeled, intrinsics, track test."""
    p = params if params is not None else WindowParams()
    return {
        "pixel_sigma_px": p.pixel_sigma_px,
        "track_random_walk_px2_per_px": p.klt.track_random_walk_px2_per_px if p.track_noise else 0.0,
        "imu_intrinsics": p.imu_intrinsics,
        "outlier_chi2": p.outlier_chi2,
    }


def evaluate_dataset(
    dataset_dir: Path,
    out_dir: Path,
    opts: EvalOptions | None = None,
    progress: ProgressFn | None = None,
    overwrite: bool = False,
) -> dict:
    """Run ``opts.estimator`` on a EuRoC folder, write TUM files into ``out_dir`` and return metrics.

    Writes ``out_dir/estimate_tum.txt`` and ``out_dir/groundtruth_tum.txt`` (TUM ``t x y z qx qy qz qw``)
    atomically (:func:`viotb.envs.tools.outdir.atomic_out_dir`): ``out_dir`` is checked before any work, a
    non-empty one is refused unless ``overwrite``, and a run that fails or is interrupted leaves nothing.
    With ``opts.report`` the report (PNGs, ``report.json``) goes there too.

    Returns:
        The metrics of :func:`viotb.vio.metrics.evaluate_trajectory` plus ``ms_per_frame_median``,
        ``ms_per_frame_p99``, ``frames``, ``estimator``, ``frontend``, ``cameras``, ``diverged``, ``reason``,
        ``frames_skipped_before_imu``, ``frames_skipped_after_imu``, ``frames_without_estimate``,
        ``imu_gaps``, ``conditions`` (with the monitor), ``calibration`` (with ``calibrate``) and ``notes``
        (a list of strings; why a metric is missing or NaN, see :data:`NULL_REASONS`).

    Raises:
        ValueError: A bad dataset, an IMU gap under the ``refuse`` policy, or a bad ``out_dir``.
        FileNotFoundError: A missing dataset file.
    """
    opts = opts if opts is not None else EvalOptions()
    with atomic_out_dir(out_dir, overwrite) as tmp_dir:
        ds = read_euroc(Path(dataset_dir))
        ds, gaps, notes = apply_imu_gap_policy(ds, opts)
        first, stop = usable_frames(ds, opts)
        n_wanted = len(ds.cam_t_s) if opts.max_frames is None else min(opts.max_frames, len(ds.cam_t_s))
        first_run = run = run_monitored(ds, opts, progress)
        ds_run = ds
        for _ in range(1, opts.calibration_passes if opts.calibrate else 1):
            ds_run = replace(ds_run, calib=diagnosis.calibrated(ds_run.calib, run))
            run = run_monitored(ds_run, opts, progress)
        ms = run.ms_per_frame
        estimates = [
            e for e, h in zip(run.estimates, run.health, strict=True) if e is not None and not h.diverged
        ]
        loop_result: dict = {}
        if opts.loop is not None:  # the estimates become the loop-closed ones; odometry metrics come along
            records = [
                {"t_s": float(t), "tracked_features": h.tracked_features}
                for t, h in zip(run.frame_t_imu_s, run.health, strict=True)
            ]
            estimates, loop_result = apply_loop_closure(ds, estimates, records, opts.loop, tmp_dir)
        est_traj = estimates_to_trajectory(estimates)
        write_tum(tmp_dir / "estimate_tum.txt", est_traj)
        result: dict = {
            "dataset": str(dataset_dir),
            "estimator": opts.estimator,
            "frontend": opts.frontend,
            "cameras": opts.cameras,
            "msckf_settings": None if opts.estimator != "msckf" else msckf_settings(opts.msckf),
            "window_settings": None if opts.estimator != "window" else window_settings(opts.window),
            "frames": len(ms),
            "estimated_frames": len(estimates),
            "frames_skipped_before_imu": first,
            "frames_skipped_after_imu": n_wanted - stop,
            "frames_without_estimate": len(ms) - len(estimates),
            "imu_gaps": gaps,
            "ms_per_frame_median": float(np.median(ms)) if ms else float("nan"),
            "ms_per_frame_p99": float(np.percentile(ms, 99)) if ms else float("nan"),
            "diverged": any(h.diverged for h in run.health),
            "reason": next((h.reason for h in run.health if h.diverged), ""),
            "mean_tracked_features": float(np.mean([h.tracked_features for h in run.health]))
            if run.health
            else 0.0,
        }
        t_imu0 = float(ds.imu.t_s[0])
        if first:
            notes.append(f"{first} frame(s) before the first IMU sample (t {t_imu0:.4f} s) skipped")
        if n_wanted - stop:
            notes.append(f"{n_wanted - stop} frame(s) after the last IMU sample skipped")
        if len(ms) > len(estimates):
            notes.append(
                f"{len(ms) - len(estimates)} of {len(ms)} processed frame(s) gave no estimate "
                "(before initialization, or after a divergence)"
            )
        if ds.groundtruth is None:
            notes.append(
                f"no ground truth ({' / '.join(s + '/data.csv' for s in GROUNDTRUTH_SOURCES)}): "
                "no accuracy metrics"
            )
        elif len(estimates) < 2:
            notes.append(f"only {len(estimates)} estimate(s): no accuracy metrics")
        else:
            gt = ds.groundtruth
            if ds.groundtruth_source != GROUNDTRUTH_SOURCES[0]:
                notes.append(f"ground truth: {ds.groundtruth_source}/data.csv (pose only)")
            mask = (gt.t_s >= est_traj.t_s[0]) & (gt.t_s <= est_traj.t_s[-1])
            gt_span = TrajectoryArrays(gt.t_s[mask], gt.p_WB[mask], gt.quat_wxyz_WB[mask])
            write_tum(tmp_dir / "groundtruth_tum.txt", gt_span)
            pos_covs = np.array([e.cov_position_W_m2 for e in estimates])
            rot_covs = np.array([e.cov_orientation_rad2 for e in estimates])
            usable = covariances_usable(pos_covs)
            rot_usable = usable and covariances_usable(rot_covs)
            result.update(
                evaluate_trajectory(
                    est_traj,
                    gt,
                    pos_covs=pos_covs if usable else None,
                    rot_covs=rot_covs if rot_usable else None,
                )
            )
            if not usable:
                notes.append(
                    f"nees_pos_mean: null (the {opts.estimator} estimator reports no positive-definite "
                    "position covariance)"
                )
        result["frames"] = len(ms)
        result.update(loop_result)
        trace = diagnosis.trace_from_run(run, conditions_from=first_run)
        if first_run.monitor is not None:
            result["conditions"] = diagnosis.conditions_json(first_run.monitor.report(), trace)
            result["monitor_ms_per_frame"] = run.monitor_ms / max(len(ms), 1)
        if opts.calibrate:
            truth = diagnosis.read_true_calibration(ds.root)
            passes = max(opts.calibration_passes, 1)
            result["calibration"] = diagnosis.calibration_json(run, ds_run.calib, ds.calib, truth, passes)
        hint = render_noise_hint(ds, opts)
        if hint:
            notes.append(hint)
        result["notes"] = notes
        if opts.report:
            from viotb.envs.tools.eval_report import write_eval_report

            params = run.monitor.params if run.monitor is not None else None
            result["report"] = write_eval_report(
                tmp_dir, result, trace, ds, params, rerun=opts.rerun, final_dir=Path(out_dir)
            )
    return result
