"""What ``viotb headset`` writes: TUM trajectories, metrics.json, PNG plots and a rerun recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from viotb.envs.data.tum import write_tum
from viotb.envs.run.headset import HeadsetRun
from viotb.envs.run.headset_report import prediction_relative_to_truth
from viotb.envs.run.loop_glue import write_loop_closures_csv
from viotb.envs.tools.cli_common import write_json
from viotb.vio.headset_metrics import highpass, position_errors_W, rotation_errors_W
from viotb.vio.lie import rotmat_to_quat_wxyz
from viotb.vio.types import TrajectoryArrays


def _traj(t_s: np.ndarray, R: np.ndarray, p: np.ndarray) -> TrajectoryArrays:
    quats = np.array([rotmat_to_quat_wxyz(r) for r in R]).reshape(-1, 4)
    return TrajectoryArrays(np.asarray(t_s, dtype=float), np.asarray(p).reshape(-1, 3), quats)


def write_headset_outputs(run: HeadsetRun, result: dict, out_dir: Path) -> list[Path]:
    """Write every output of a run into ``out_dir`` (created); returns the paths written.

    ``estimate_tum.txt`` (the estimator's pose at IMU rate), ``display_tum.txt`` (the display pose: the
    estimate with its corrections smoothed, what the metrics measure), ``predicted_tum.txt`` (stamped with
    the time each prediction is for), ``groundtruth_tum.txt`` (truth at the pose times), ``metrics.json``, the
    plots and ``headset.rrd``; with loop closure, ``loop_closures.csv``.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [
        write_tum(out_dir / "estimate_tum.txt", _traj(run.t_s, run.R_est, run.p_est)),
        write_tum(out_dir / "display_tum.txt", _traj(run.t_s, run.R_disp, run.p_disp)),
        write_tum(out_dir / "predicted_tum.txt", _traj(run.t_pred_s, run.R_pred, run.p_pred)),
        write_tum(out_dir / "groundtruth_tum.txt", _traj(run.t_s, run.R_true, run.p_true)),
    ]
    if run.loop:
        paths.append(write_loop_closures_csv(out_dir / "loop_closures.csv", run.closures))
    if len(run.t_s) >= 10:
        paths += save_headset_plots(run, out_dir)
    paths.append(write_headset_rrd(run, out_dir / "headset.rrd"))
    result = dict(result, plots=[str(p) for p in paths if p.suffix == ".png"], recording=str(paths[-1]))
    metrics = out_dir / "metrics.json"
    write_json(metrics, result)
    return [*paths, metrics]


def save_headset_plots(run: HeadsetRun, out_dir: Path) -> list[Path]:
    """Jitter trace, world-lock error over time, prediction error against head angular speed (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e_p = position_errors_W(run.p_disp, run.p_true)
    e_r = rotation_errors_W(run.R_disp, run.R_true)
    paths = []

    t_hp, hp = highpass(run.t_s, np.hstack([e_p, e_r]))
    _, hp_est = highpass(
        run.t_s,
        np.hstack([position_errors_W(run.p_est, run.p_true), rotation_errors_W(run.R_est, run.R_true)]),
    )
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    axes[0].plot(t_hp, 1e3 * np.linalg.norm(hp_est[:, :3], axis=1), "0.7", lw=0.6, label="|estimator|")
    axes[1].plot(t_hp, np.rad2deg(np.linalg.norm(hp_est[:, 3:], axis=1)), "0.7", lw=0.6, label="|estimator|")
    for k, name in enumerate("xyz"):
        axes[0].plot(t_hp, 1e3 * hp[:, k], lw=0.7, label=f"display {name}")
        axes[1].plot(t_hp, np.rad2deg(hp[:, 3 + k]), lw=0.7, label=f"display {name}")
    axes[0].set_ylabel("position jitter [mm]")
    axes[1].set_ylabel("rotation jitter [deg]")
    axes[1].set_xlabel("t [s]")
    axes[0].legend(ncol=4, loc="upper right", fontsize=7)
    fig.suptitle("Jitter: error high-passed at 1 Hz (display pose; grey: the estimator's own pose)")
    paths.append(_save(fig, out_dir / "jitter.png"))

    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    axes[0].plot(run.t_s, 1e3 * np.linalg.norm(e_p, axis=1), "C0", lw=0.8)
    axes[0].set_ylabel("|position error| [mm]")
    axes[1].plot(run.t_s, np.rad2deg(np.linalg.norm(e_r, axis=1)), "C1", lw=0.8)
    axes[1].set_ylabel("|rotation error| [deg]")
    axes[1].set_xlabel("t [s]")
    fig.suptitle("World lock: error of the pose in the boot-time world frame")
    paths.append(_save(fig, out_dir / "world_lock.png"))

    m = len(run.t_pred_s)
    if m:
        R_pc, p_pc = prediction_relative_to_truth(run)
        pos_mm = 1e3 * np.linalg.norm(p_pc - run.p_true_pred, axis=1)
        rot_deg = np.rad2deg(np.linalg.norm(rotation_errors_W(R_pc, run.R_true_pred), axis=1))
        speed = np.rad2deg(run.speed_true_rad_s[:m])
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        axes[0].scatter(speed, pos_mm, s=1, alpha=0.3)
        axes[0].set_ylabel("prediction position error [mm]")
        axes[1].scatter(speed, rot_deg, s=1, alpha=0.3, color="C1")
        axes[1].set_ylabel("prediction rotation error [deg]")
        for ax in axes:
            ax.set_xlabel("head angular speed [deg/s]")
            ax.axvline(150.0, color="k", lw=0.6, ls=":")
        fig.suptitle(f"Prediction to t + {1e3 * run.options.latency_s:.0f} ms against head speed")
        paths.append(_save(fig, out_dir / "prediction_error.png"))
    return paths


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_headset_rrd(run: HeadsetRun, path: Path, stride: int = 10) -> Path:
    """A rerun recording: truth, estimate and prediction paths, error scalars, and cam0 now and then."""
    import rerun as rr

    rec = rr.RecordingStream(application_id="viotb", recording_id=f"viotb-headset-{run.scenario}")
    rec.save(str(path))
    e_mm = 1e3 * np.linalg.norm(position_errors_W(run.p_disp, run.p_true), axis=1)
    e_est_mm = 1e3 * np.linalg.norm(position_errors_W(run.p_est, run.p_true), axis=1)
    for i in range(0, len(run.t_s), stride):
        rec.set_time("sim_time", duration=float(run.t_s[i]))
        rec.log("error/world_lock_mm", rr.Scalars(float(e_mm[i])))
        rec.log("error/estimator_mm", rr.Scalars(float(e_est_mm[i])))
        rec.log("head/speed_deg_s", rr.Scalars(float(np.rad2deg(run.speed_true_rad_s[i]))))
    for t_s, image in run.images:
        rec.set_time("sim_time", duration=float(t_s))
        rec.log("camera/cam0", rr.Image(image))
    if len(run.t_s):
        rec.set_time("sim_time", duration=float(run.t_s[-1]))
        rec.log("world/truth", rr.LineStrips3D([run.p_true[::stride]], colors=[[40, 40, 40]]))
        rec.log("world/estimate", rr.LineStrips3D([run.p_est[::stride]], colors=[[230, 120, 20]]))
        if len(run.p_pred):
            rec.log("world/predicted", rr.LineStrips3D([run.p_pred[::stride]], colors=[[30, 120, 220]]))
    rec.flush()
    rec.disconnect()
    return Path(path)
