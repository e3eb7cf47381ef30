"""Tracking and estimation metrics of a flight log, computed chunk by chunk (``viotb fly``'s metrics).

The log streams its ticks to disk (:mod:`viotb.envs.run.flight_log`), so the metrics read it one chunk at a
time and never hold a whole column or its temporaries: sums, counts and maxima are accumulated per chunk,
and the ATE's 4-DOF alignment (Umeyama 1991, posyaw mode of :func:`viotb.vio.metrics.align_umeyama`) takes
three passes (means; centred sums; aligned residuals). Row-wise values (errors, masks) are computed exactly
as on whole arrays, so maxima are bit-identical and sums and RMS agree with the whole-array formulas to
round-off (chunk sums against numpy's pairwise sum, ~1e-16 relative).
"""

from __future__ import annotations

import numpy as np
from viotb.envs.run.flight_log import FlightLog
from viotb.vio.metrics import posyaw_alignment


def _max_or_nan(maxima: list[float]) -> float:
    """Largest of per-chunk maxima, NaN when there are none (like ``np.nanmax`` of an all-NaN span)."""
    return float(np.max(maxima)) if maxima else float("nan")


def _nonnan_max(x: np.ndarray, maxima: list[float]) -> None:
    """Append ``nanmax(x)`` to ``maxima`` when ``x`` has a non-NaN value."""
    x = x[~np.isnan(x)]
    if x.size:
        maxima.append(float(np.max(x)))


def flight_metrics(log: FlightLog, mission_t0: float | None, init_time: float | None) -> dict:
    """Tracking and estimation metrics of a flight log.

    Args:
        log: The flight's log.
        mission_t0: Mission start (s); None if the mission never started.
        init_time: Estimator initialization time (s); None if it never initialized.

    Returns:
        ``hover_rms_m`` and ``max_err_m`` (truth-to-setpoint distance from the mission start, RMS and max),
        ``est_rms_m`` (RMS estimate error over the ticks with a finite estimate) and ``ate_posyaw_m`` (RMS
        error after the 4-DOF alignment of estimate onto truth); None where undefined.

    Raises:
        ValueError: A non-finite truth position at a tick with a finite estimate.
    """
    out: dict = {"hover_rms_m": None, "max_err_m": None, "ate_posyaw_m": None, "est_rms_m": None}
    # 1. One pass: setpoint error from the mission start; estimate error, counts and sums for the means.
    hover_sq, hover_n, hover_max = 0.0, 0, []
    est_sq, n_ok = 0.0, 0
    sum_est, sum_true = np.zeros(3), np.zeros(3)
    for t, p_true, p_est, p_set in log.tick_chunks("t_s", "p_true_W", "p_est_W", "p_set_W"):
        if mission_t0 is not None:
            m = t >= mission_t0
            err = np.linalg.norm(p_true[m] - p_set[m], axis=1)
            if err.size:
                hover_sq += float(np.sum(err**2))
                hover_n += err.size
                hover_max.append(float(np.max(err)))
        ok = np.all(np.isfinite(p_est), axis=1)
        if ok.any():
            if not np.all(np.isfinite(p_true[ok])):
                raise ValueError("p_gt contains non-finite values")
            est_err = np.linalg.norm(p_est[ok] - p_true[ok], axis=1)
            est_sq += float(np.sum(est_err**2))
            n_ok += est_err.size
            sum_est += np.sum(p_est[ok], axis=0)
            sum_true += np.sum(p_true[ok], axis=0)
    if hover_n:
        out["hover_rms_m"] = float(np.sqrt(hover_sq / hover_n))
        out["max_err_m"] = float(np.max(hover_max))
    if init_time is None or n_ok < 3:
        return out
    out["est_rms_m"] = float(np.sqrt(est_sq / n_ok))
    # 2. Centred sums of the yaw alignment (align_umeyama's posyaw step 2a).
    mu_est, mu_true = sum_est / n_ok, sum_true / n_ok
    num = den = 0.0
    for p_true, p_est in log.tick_chunks("p_true_W", "p_est_W"):
        ok = np.all(np.isfinite(p_est), axis=1)
        x, y = p_est[ok] - mu_est, p_true[ok] - mu_true
        num += float(np.sum(x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0]))
        den += float(np.sum(x[:, 0] * y[:, 0] + x[:, 1] * y[:, 1]))
    al = posyaw_alignment(mu_est, mu_true, num, den)
    # 3. Aligned residuals.
    res_sq = 0.0
    for p_true, p_est in log.tick_chunks("p_true_W", "p_est_W"):
        ok = np.all(np.isfinite(p_est), axis=1)
        aligned = (al.s * (al.R @ p_est[ok].T)).T + al.t
        res_sq += float(np.sum(np.sum((aligned - p_true[ok]) ** 2, axis=1)))
    out["ate_posyaw_m"] = float(np.sqrt(res_sq / n_ok))
    return out


def blackout_metrics(log: FlightLog, blackouts: tuple) -> dict:
    """Excursion during each camera blackout (+1 s) and whether tracking came back after it.

    Args:
        log: The flight's log.
        blackouts: ``(start_s, end_s)`` camera blackout intervals.

    Returns:
        ``{}`` without blackouts, else ``blackout_excursion_m`` (largest truth-to-setpoint distance from the
        start of a blackout to 1 s after its end), ``blackout_est_err_m`` (largest estimate error in that
        span) and ``blackout_recovered`` (every blackout is followed, within 1 s, by a frame with >= 20
        tracked features).
    """
    if not blackouts:
        return {}
    seen = [False] * len(blackouts)
    set_max: list[list[float]] = [[] for _ in blackouts]
    est_max: list[list[float]] = [[] for _ in blackouts]
    for t, p_true, p_est, p_set in log.tick_chunks("t_s", "p_true_W", "p_est_W", "p_set_W"):
        err_set = np.linalg.norm(p_true - p_set, axis=1)
        err_est = np.linalg.norm(p_est - p_true, axis=1)
        for i, (a, b) in enumerate(blackouts):
            m = (t >= a) & (t <= b + 1.0)
            if np.any(m):
                seen[i] = True
                _nonnan_max(err_set[m], set_max[i])
                _nonnan_max(err_est[m], est_max[i])
    ft, nf = np.asarray(log.frame_t_s), np.asarray(log.frame_features)
    excursion, est_err, recovered = 0.0, 0.0, True
    for i, (_, b) in enumerate(blackouts):
        if not seen[i]:
            recovered = False
            continue
        excursion = max(excursion, _max_or_nan(set_max[i]))
        est_err = max(est_err, _max_or_nan(est_max[i]))
        after = (ft > b) & (ft <= b + 1.0)
        recovered = recovered and bool(np.any(nf[after] >= 20))
    return {"blackout_excursion_m": excursion, "blackout_est_err_m": est_err, "blackout_recovered": recovered}


def lights_out_metrics(log: FlightLog, intervals: tuple, back_m: float = 0.10) -> dict:
    """How far the drone strays while the lights are out and how fast it is back at the hold point.

    Args:
        log: The flight's log.
        intervals: ``(off_s, on_s)`` lights-out intervals, in time order.
        back_m: Distance to the setpoint (m) that counts as back.

    Returns:
        ``{}`` without intervals, else ``lights_out_excursion_m`` (largest truth-to-setpoint distance from the
        first light-off to the end of the flight) and ``lights_out_back_s``: for the last interval, the time
        (s) after the light returns from which that distance stays below ``back_m`` until the end of the
        flight (0 if it never left; None if it is not back by the end).
    """
    if not intervals:
        return {}
    end = intervals[-1][1]
    any_after, excursion = False, []
    n_m, far_seen = 0, False
    t_back = None  # the tick after the last one that was not back, once seen
    for t, p_true, p_set in log.tick_chunks("t_s", "p_true_W", "p_set_W"):
        err = np.linalg.norm(p_true - p_set, axis=1)
        after = t >= intervals[0][0]
        if np.any(after):
            any_after = True
            _nonnan_max(err[after], excursion)
        m = t >= end
        t_m, far = t[m], np.flatnonzero(~(err[m] < back_m))  # NaN (no setpoint) counts as not back
        n_m += t_m.size
        if far.size:
            far_seen = True
            t_back = float(t_m[far[-1] + 1]) if far[-1] + 1 < t_m.size else None
        elif far_seen and t_back is None and t_m.size:
            t_back = float(t_m[0])
    out: dict = {"lights_out_excursion_m": _max_or_nan(excursion) if any_after else None}
    if n_m == 0:
        out["lights_out_back_s"] = None
    elif not far_seen:
        out["lights_out_back_s"] = 0.0
    else:
        out["lights_out_back_s"] = None if t_back is None else float(t_back - end)
    return out
