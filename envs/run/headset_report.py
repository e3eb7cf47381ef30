"""The JSON result of a headset run (``viotb headset``): DESIGN.md's keys, from a :class:`HeadsetRun`.

The metrics measure the display pose (the estimate with its corrections smoothed,
:mod:`viotb.vio.display_pose`), what the user sees; the ``estimator_*`` keys measure the estimator's own
pose at IMU rate.
"""

from __future__ import annotations

import numpy as np
from viotb.envs.data.diagnosis import condition_rows
from viotb.envs.run.headset import HeadsetRun
from viotb.vio.headset_metrics import HeadsetMetricParams, headset_metrics, prediction_errors


def prediction_relative_to_truth(run: HeadsetRun) -> tuple[np.ndarray, np.ndarray]:
    """Predictions carried onto the truth: the predicted motion over the latency, started from the true pose.

    ``R = R_true(t) R_disp(t)^T R_pred``, ``p = p_pred - (p_disp(t) - p_true(t))`` (predictions start from
    the display pose): the display pose's error at ``t`` (world lock, counted by ``world_lock_ate_mm``) is
    taken out, so that what is left is the error of the prediction itself (wrong velocity, angular rate or
    acceleration, and the motion model), which is what ``pred_err_*`` report; ``pred_err_abs_*`` compare the
    raw predictions with the truth.

    Returns:
        ``(R (M, 3, 3), p (M, 3))`` for the M predictions of ``run``.
    """
    m = len(run.t_pred_s)
    R_fix = run.R_true[:m] @ np.swapaxes(run.R_disp[:m], -1, -2)
    return R_fix @ run.R_pred, run.p_pred - (run.p_disp[:m] - run.p_true[:m])


METRIC_KEYS = (
    "jitter_pos_mm",
    "jitter_rot_deg",
    "world_lock_ate_mm",
    "max_err_mm",
    "pred_err_pos_mm_p95",
    "pred_err_rot_deg_p95",
    "pose_rate_hz",
    "drift_pct",
)
"""Display-pose metrics (:func:`viotb.vio.headset_metrics.headset_metrics`) the result carries."""

ESTIMATOR_KEYS = ("jitter_pos_mm", "jitter_rot_deg", "world_lock_ate_mm", "max_err_mm")
"""Metrics also reported (prefixed ``estimator_``) for the estimator's own pose, before the display filter."""


def _finite_or_none(value: float | None, key: str, notes: dict[str, str], why: str) -> float | None:
    if value is None or not np.isfinite(value):
        notes.setdefault(key, why)
        return None
    return float(value)


def headset_result(run: HeadsetRun, params: HeadsetMetricParams | None = None) -> dict:
    """The JSON result of a run: DESIGN.md's ``viotb headset`` keys plus context (strict JSON, no NaN)."""
    o = run.options
    result: dict = {
        "scenario": run.scenario,
        "estimator": o.estimator,
        "frontend": o.frontend,
        "cameras": o.cameras,
        "latency_ms": 1e3 * o.latency_s,
        "seed": o.seed,
        "time_offset_error_ms": 1e3 * o.time_offset_error_s,
        "online_calibration": o.online_calibration,
        "frames": int(len(run.ms_per_frame)),
        "poses": int(len(run.t_s)),
        "diverged": bool(run.failure),
        "reason": run.failure,
        "path_length_m": float(np.sum(np.linalg.norm(np.diff(run.p_true, axis=0), axis=1)))
        if len(run.t_s)
        else 0.0,
        "realtime_factor": float((run.t_s[-1] - run.t_s[0]) / run.wall_s) if len(run.t_s) > 1 else 0.0,
    }
    notes: dict[str, str] = {}
    keys = METRIC_KEYS
    if len(run.t_s) >= 10:
        m = len(run.t_pred_s)
        R_pc, p_pc = prediction_relative_to_truth(run)
        pred = prediction_errors(
            R_pc, p_pc, run.R_true_pred, run.p_true_pred, run.speed_true_rad_s[:m], params
        )
        absolute = prediction_errors(
            run.R_pred, run.p_pred, run.R_true_pred, run.p_true_pred, run.speed_true_rad_s[:m], params
        )
        result["pred_err_abs_pos_mm_p95"] = absolute.pos_mm
        result["pred_err_abs_rot_deg_p95"] = absolute.rot_deg
        hm = headset_metrics(run.t_s, run.R_disp, run.p_disp, run.R_true, run.p_true, pred, params).to_dict()
        notes.update(hm.pop("notes"))
        for key in keys:
            result[key] = _finite_or_none(hm[key], key, notes, "not finite")
        raw = headset_metrics(run.t_s, run.R_est, run.p_est, run.R_true, run.p_true, None, params).to_dict()
        for key in ESTIMATOR_KEYS:
            result[f"estimator_{key}"] = _finite_or_none(raw[key], f"estimator_{key}", notes, "not finite")
        result["pred_fast_samples"] = pred.n_fast
        for key in ("pred_err_abs_pos_mm_p95", "pred_err_abs_rot_deg_p95"):
            result[key] = _finite_or_none(result[key], key, notes, notes.get("pred_err_pos_mm_p95", "none"))
    else:
        for key in keys + tuple(f"estimator_{k}" for k in ESTIMATOR_KEYS):
            result[key] = None
            notes[key] = "fewer than 10 poses (the estimator did not initialize)"
    ms = run.ms_per_frame
    why_ms = "no frame processed"
    result["ms_per_frame_median"] = _finite_or_none(
        float(np.median(ms)) if len(ms) else None, "ms_per_frame_median", notes, why_ms
    )
    result["ms_per_frame_p99"] = _finite_or_none(
        float(np.percentile(ms, 99)) if len(ms) else None, "ms_per_frame_p99", notes, why_ms
    )
    nees = run.nees_pos
    result["nees_pos_mean"] = _finite_or_none(
        float(np.mean(nees)) if len(nees) else None, "nees_pos_mean", notes, "no covariance (or no frame)"
    )
    result["mean_tracked_features"] = float(np.mean(run.tracked)) if len(run.tracked) else 0.0
    result["conditions"] = condition_rows(run.conditions, run.frame_t_s, run.active)
    result.update({k: v for k, v in run.loop.items() if k != "loop_closure_rows"})
    result["notes"] = notes
    return result
