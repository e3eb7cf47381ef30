"""The report of one ``viotb eval``: error plots with the filter's 3-sigma band, health plots, JSON, rerun.

Files written into the eval's output folder:

* ``error.png``: position error per world axis and yaw error against time (after the yaw + translation
  alignment of the ATE) with the filter's own +-3 sigma band;
* ``health.png``: tracked features and the windowed NIS per dof (relative to the expected value, with the
  monitor's threshold) against time;
* on both, the monitor's conditions shaded over the intervals in which they were active;
* ``report.json``: the eval's JSON (as ``viotb failures`` writes its ``report.json``: conditions with their
  first time and evidence), strict JSON (NaN and infinities written as ``null``);
* ``eval.rrd`` with ``rerun=True``: a rerun recording (trajectories, images, errors, features, NIS, the
  conditions as a text log).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp
from viotb.envs.data.diagnosis import EvalTrace, condition_intervals
from viotb.envs.data.euroc import EurocDataset, load_image
from viotb.envs.tools.jsonout import plain_json
from viotb.vio.health import HealthParams
from viotb.vio.metrics import align_umeyama, positions_at

_COLORS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:gray", "gold")


def trace_errors(trace: EvalTrace, ds: EurocDataset) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Errors against ground truth after the ATE's yaw + translation alignment.

    Returns:
        ``(t_s (N,), position error per world axis (m, (N, 3)), yaw error (rad, (N,)))`` over the estimates
        inside the ground truth's time span, or None without ground truth or with fewer than 2 estimates.
    """
    gt = ds.groundtruth
    if gt is None or len(trace.est_t_s) < 2:
        return None
    keep = (trace.est_t_s >= gt.t_s[0]) & (trace.est_t_s <= gt.t_s[-1])
    if np.count_nonzero(keep) < 2:
        return None
    t = trace.est_t_s[keep]
    p_gt = positions_at(gt, t)
    q = gt.quat_wxyz_WB
    R_gt = Slerp(gt.t_s, Rotation.from_quat(q[:, [1, 2, 3, 0]]))(t).as_matrix()
    al = align_umeyama(trace.p_WB[keep], p_gt, "posyaw")
    err_p = al.apply(trace.p_WB[keep]) - p_gt
    R_err = al.apply_rotation(trace.R_WB[keep]) @ np.transpose(R_gt, (0, 2, 1))  # world-frame error
    yaw = np.arctan2(R_err[:, 1, 0], R_err[:, 0, 0])
    return t, err_p, yaw


def _shade_conditions(axes: list, trace: EvalTrace) -> None:
    """Shade each condition's active intervals on every axis, labelled once in the first axis' legend."""
    spans = condition_intervals(trace)
    dt = float(np.median(np.diff(trace.frame_t_s))) if len(trace.frame_t_s) > 1 else 0.05
    for k, (name, ivs) in enumerate(sorted(spans.items())):
        color = _COLORS[k % len(_COLORS)]
        for ax in axes:
            for j, (t0, t1) in enumerate(ivs):
                label = name if (ax is axes[0] and j == 0) else None
                ax.axvspan(t0, t1 + dt, color=color, alpha=0.18, lw=0, label=label)


def _windowed_nis(trace: EvalTrace, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean NIS per dof over the last ``window`` updates (the monitor's statistic), at each update's time."""
    ok = np.isfinite(trace.nis_per_dof)
    t, nis = trace.frame_t_s[ok], trace.nis_per_dof[ok]
    if len(nis) == 0:
        return t, nis
    c = np.concatenate([[0.0], np.cumsum(nis)])
    n = np.minimum(np.arange(1, len(nis) + 1), window)
    idx = np.arange(1, len(nis) + 1)
    return t, (c[idx] - c[idx - n]) / n


def _plot_errors(path: Path, trace: EvalTrace, ds: EurocDataset, title: str) -> bool:
    errs = trace_errors(trace, ds)
    if errs is None:
        return False
    import matplotlib.pyplot as plt

    t, err_p, yaw = errs
    keep = (trace.est_t_s >= t[0]) & (trace.est_t_s <= t[-1])
    sig_p, sig_y = trace.position_sigma_W_m[keep], trace.yaw_sigma_rad[keep]
    fig, axes = plt.subplots(4, 1, figsize=(8, 8), sharex=True)
    for j, name in enumerate("xyz"):
        ax = axes[j]
        ax.fill_between(t, -3 * sig_p[:, j] * 100, 3 * sig_p[:, j] * 100, color="tab:blue", alpha=0.15)
        ax.plot(t, err_p[:, j] * 100, color="tab:blue", lw=1.0, label=f"error {name}")
        ax.set_ylabel(f"{name} error (cm)")
    axes[3].fill_between(t, -3 * np.rad2deg(sig_y), 3 * np.rad2deg(sig_y), color="tab:green", alpha=0.15)
    axes[3].plot(t, np.rad2deg(yaw), color="tab:green", lw=1.0)
    axes[3].set_ylabel("yaw error (deg)")
    axes[3].set_xlabel("t (s, IMU clock)")
    _shade_conditions(list(axes), trace)
    axes[0].set_title(f"{title}: error after yaw+translation alignment, band = filter +-3 sigma")
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def _plot_health(path: Path, trace: EvalTrace, params: HealthParams, title: str) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    axes[0].plot(trace.frame_t_s, trace.tracked_features, color="tab:blue", lw=1.0)
    axes[0].axhline(params.min_tracked_features, ls=":", color="gray", label="feature-poverty threshold")
    axes[0].set_ylabel("tracked features")
    t, win = _windowed_nis(trace, params.speed_window_frames)
    axes[1].plot(t, win / params.nis_per_dof_expected, color="tab:orange", lw=1.0)
    axes[1].axhline(params.max_nis_per_dof, ls=":", color="gray", label="time-sync threshold")
    axes[1].set_ylabel(
        f"NIS/dof, {params.speed_window_frames}-update mean\n/ {params.nis_per_dof_expected:.3g}"
    )
    axes[1].set_xlabel("t (s, IMU clock)")
    _shade_conditions(list(axes), trace)
    axes[0].set_title(f"{title}: front end and filter health")
    for ax in axes:
        ax.legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _write_rerun(path: Path, trace: EvalTrace, ds: EurocDataset, params: HealthParams, report: list) -> None:
    """A rerun recording of the run (entities in the module docstring)."""
    import rerun as rr

    rec = rr.RecordingStream(application_id="viotb", recording_id="viotb-eval")
    rec.save(str(path))
    try:
        if ds.groundtruth is not None:
            rec.log("world/truth", rr.LineStrips3D([ds.groundtruth.p_WB], colors=[[40, 40, 40]]), static=True)
        errs = trace_errors(trace, ds)
        t_nis, win = _windowed_nis(trace, params.speed_window_frames)
        nis_at = dict(zip(t_nis.tolist(), (win / params.nis_per_dof_expected).tolist(), strict=True))
        est_k = {float(t): k for k, t in enumerate(trace.est_t_s)}
        err_k = {} if errs is None else {float(t): k for k, t in enumerate(errs[0])}
        offset = ds.calib.time_offset_s
        for i, t in enumerate(trace.frame_t_s.tolist()):
            rec.set_time("time", duration=t)
            rec.log("health/tracked_features", rr.Scalars(float(trace.tracked_features[i])))
            if t in nis_at:
                rec.log("health/nis_window", rr.Scalars(nis_at[t]))
            k = est_k.get(t)
            if k is not None:
                rec.log("world/estimate", rr.LineStrips3D([trace.p_WB[: k + 1]], colors=[[230, 120, 20]]))
                rec.log(
                    "world/estimate/cov",
                    rr.Ellipsoids3D(
                        centers=[trace.p_WB[k]],
                        half_sizes=[3.0 * trace.position_sigma_W_m[k] + 1e-4],
                        colors=[[230, 120, 20]],
                    ),
                )
            j = err_k.get(t)
            if j is not None:
                rec.log("error/position_cm", rr.Scalars(float(np.linalg.norm(errs[1][j]) * 100)))
                rec.log("error/yaw_deg", rr.Scalars(float(np.rad2deg(errs[2][j]))))
            idx = int(np.argmin(np.abs(ds.cam_t_s + offset - t)))
            rec.log("camera/image", rr.Image(load_image(ds, idx)))
        for c in report:
            rec.set_time("time", duration=float(c["t_s_first"]))
            rec.log("health/conditions", rr.TextLog(f"{c['name']}: {c['evidence']}", level="WARN"))
    finally:
        rec.flush()
        rec.disconnect()


def write_eval_report(
    out_dir: Path,
    result: dict,
    trace: EvalTrace,
    ds: EurocDataset,
    params: HealthParams | None = None,
    rerun: bool = False,
    final_dir: Path | None = None,
) -> dict:
    """Write the report of one eval into ``out_dir`` (module docstring) and return its file paths.

    Args:
        out_dir: The eval's output folder.
        result: The eval's JSON result; ``report.json`` is it plus ``"report"`` (the paths returned here).
        trace: Per-frame series of the run.
        ds: The dataset (ground truth, images for the rerun recording).
        params: The monitor's thresholds (the defaults when None).
        rerun: Also write ``eval.rrd``.
        final_dir: Where ``out_dir`` will be renamed to (an atomic write); the paths name it (None:
            ``out_dir``).

    Returns:
        ``{"error_plot", "health_plot", "json", "rerun"}`` (paths as strings; ``error_plot`` and ``rerun``
        None when not written).
    """
    import matplotlib

    matplotlib.use("Agg")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    prm = params if params is not None else HealthParams()
    title = f"{result.get('estimator', '?')} on {Path(str(result.get('dataset', ''))).name}"
    error_png, health_png = out / "error.png", out / "health.png"
    has_err = len(trace.frame_t_s) > 0 and _plot_errors(error_png, trace, ds, title)
    if len(trace.frame_t_s):
        _plot_health(health_png, trace, prm, title)
    rrd = out / "eval.rrd"
    if rerun:
        _write_rerun(rrd, trace, ds, prm, result.get("conditions", []))
    final = Path(final_dir) if final_dir is not None else out
    paths = {
        "error_plot": str(final / error_png.name) if has_err else None,
        "health_plot": str(final / health_png.name) if len(trace.frame_t_s) else None,
        "json": str(final / "report.json"),
        "rerun": str(final / rrd.name) if rerun else None,
    }
    text = json.dumps(plain_json({**result, "report": paths}), indent=2, allow_nan=False)
    tmp = out / "report.json.tmp"
    tmp.write_text(text + "\n")
    tmp.replace(out / "report.json")
    return paths


def print_diagnosis(console: object, result: dict) -> None:
    """Print the monitor's conditions and the online calibration of an eval result (rich console)."""
    from rich.markup import escape

    conds = result.get("conditions")
    if conds is not None:
        if not conds:
            console.print("[green]monitor: no condition raised[/green]")
        for c in conds:
            console.print(
                f"[bold yellow]{c['name']}[/bold yellow] first at {c['t_s_first']:.2f} s "
                f"({c['t_since_start_s']:.2f} s after the first frame): {escape(c['evidence'])}"
            )
    cal = result.get("calibration")
    if cal:
        rot = ", ".join(f"{v:+.2f}" for v in cal["extrinsic_rotation_vector_deg"])
        rsig = ", ".join(f"{v:.2f}" for v in cal["extrinsic_rotation_sigma_deg"])
        tr = ", ".join(f"{v:+.2f}" for v in cal["extrinsic_translation_vector_cm"])
        tsig = ", ".join(f"{v:.2f}" for v in cal["extrinsic_translation_sigma_cm"])
        offset = (
            f"time offset {cal['time_offset_ms']:.2f} ms (given {cal['time_offset_given_ms']:.2f}, "
            f"sigma {cal['time_offset_sigma_ms']:.2f})"
        )
        console.print(
            f"calibration: {offset}; rotation vs the file's T_BS {cal['extrinsic_rotation_deg']:.2f} deg "
            f"({rot}) +- ({rsig}); translation {cal['extrinsic_translation_cm']:.2f} cm ({tr}) +- ({tsig})"
        )
    rep = result.get("report")
    if rep:
        console.print("report: " + ", ".join(str(v) for v in rep.values() if v))
