"""Run an estimator over any EuRoC-layout folder (recorded here or real) and measure it.

This is the engine of ``viotb eval``: it replays the IMU and camera streams in timestamp order on the IMU
clock, times the estimator per frame, writes TUM trajectories and returns the metrics of
:mod:`viotb.vio.metrics`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc import EurocDataset, load_image, read_euroc
from viotb.envs.data.tum import write_tum
from viotb.envs.run.loop_glue import LoopOptions, apply_loop_closure
from viotb.envs.run.replay import replay
from viotb.vio.factory import make_estimator
from viotb.vio.lie import quat_wxyz_to_rotmat, rotmat_to_quat_wxyz
from viotb.vio.metrics import evaluate_trajectory
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.types import CameraFrame, StateEstimate, TrajectoryArrays
from viotb.vio.window import WindowParams

ProgressFn = Callable[[float, float], None]


@dataclass(frozen=True)
class EvalOptions:
    """Options of one evaluation run.

    Attributes:
        estimator: Estimator name (see ``viotb.vio.factory.ESTIMATOR_NAMES``).
        frontend: ``"klt"`` (OpenCV on the images, default) or ``"sim"`` (projections of the dataset's
            ``sim_landmarks0`` with ground-truth poses plus pixel noise; recorded datasets only).
        seed: Seed of the pixel noise in the ``sim`` front end.
        sim_pixel_sigma_px: Pixel noise (px) of the ``sim`` front end.
        max_frames: Stop after this many frames (None = all).
        msckf: MSCKF settings (None: the defaults).
        window: Window-optimizer settings (None: the defaults).
        loop: Loop closure beside the estimator (``viotb.envs.run.loop_glue.LoopOptions``); None = off.
    """

    estimator: str = "msckf"
    frontend: str = "klt"
    seed: int = 0
    sim_pixel_sigma_px: float = 0.5
    max_frames: int | None = None
    msckf: MsckfParams | None = None
    window: WindowParams | None = None
    loop: LoopOptions | None = None


def _interpolate_pose(gt: TrajectoryArrays, t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth pose at ``t_s``: linear in position, normalized lerp of the quaternion."""
    i = int(np.clip(np.searchsorted(gt.t_s, t_s), 1, len(gt) - 1))
    t0, t1 = gt.t_s[i - 1], gt.t_s[i]
    a = float(np.clip((t_s - t0) / (t1 - t0), 0.0, 1.0))
    p = (1.0 - a) * gt.p_WB[i - 1] + a * gt.p_WB[i]
    q0, q1 = gt.quat_wxyz_WB[i - 1], gt.quat_wxyz_WB[i]
    q1 = q1 if np.dot(q0, q1) >= 0.0 else -q1
    q = (1.0 - a) * q0 + a * q1
    return quat_wxyz_to_rotmat(q / np.linalg.norm(q)), p


def _truth_estimate(ds: EurocDataset, t_s: float) -> StateEstimate:
    """Ground truth at ``t_s`` as a :class:`StateEstimate` (for the ``ground-truth`` pass-through)."""
    assert ds.groundtruth is not None
    R_WB, p_WB = _interpolate_pose(ds.groundtruth, t_s)
    v = ds.groundtruth.v_WB
    v_WB = (
        np.zeros(3) if v is None else v[int(np.clip(np.searchsorted(ds.groundtruth.t_s, t_s), 0, len(v) - 1))]
    )
    return StateEstimate(t_s=t_s, R_WB=R_WB, p_WB=p_WB, v_WB=v_WB)


def _frame(ds: EurocDataset, i: int, opts: EvalOptions, rng: np.random.Generator) -> CameraFrame:
    """Camera frame ``i``: the image, or simulated features from the dataset's landmarks."""
    t_cam = float(ds.cam_t_s[i])
    if opts.frontend != "sim":
        return CameraFrame(t_s=t_cam, image=load_image(ds, i))
    from viotb.envs.sim.landmarks import project_landmarks

    if ds.landmarks_W is None or ds.groundtruth is None:
        raise ValueError(
            f"{ds.root}: the 'sim' front end needs mav0/sim_landmarks0/data.csv and ground truth; "
            "use --frontend klt on real data"
        )
    R_WB, p_WB = _interpolate_pose(ds.groundtruth, t_cam + ds.calib.time_offset_s)
    R_WC = R_WB @ ds.calib.R_BC
    p_WC = p_WB + R_WB @ ds.calib.p_BC
    obs = project_landmarks(ds.landmarks_W, R_WC, p_WC, ds.calib.camera, rng, opts.sim_pixel_sigma_px)
    return CameraFrame(t_s=t_cam, features=obs)


def run_estimator(
    ds: EurocDataset, opts: EvalOptions, progress: ProgressFn | None = None
) -> tuple[list[StateEstimate], list[float], list[dict]]:
    """Replay a dataset through an estimator (:func:`viotb.envs.run.replay.replay`).

    Returns:
        Estimates at each processed frame (after initialization, before any divergence), per-frame wall time
        (ms), and per-frame health records (dicts with t_s, tracked_features, updated_features,
        chi2_rejections, diverged, reason, conditions).
    """
    est = make_estimator(
        opts.estimator,
        ds.calib,
        ds.imu_noise,
        frontend=opts.frontend,
        params=opts.msckf,
        window_params=opts.window,
    )
    rng = np.random.default_rng(opts.seed)
    n_frames = len(ds.cam_t_s) if opts.max_frames is None else min(opts.max_frames, len(ds.cam_t_s))
    frame_t_imu = ds.cam_t_s[:n_frames] + ds.calib.time_offset_s
    # Start the IMU one second before the first frame (static initialization needs a still window).
    imu_start = float(frame_t_imu[0]) - 1.0 if n_frames else None
    truth_at = (lambda t: _truth_estimate(ds, t)) if opts.estimator == "ground-truth" else None
    frames = (_frame(ds, k, opts, rng) for k in range(n_frames))
    run = replay(
        est,
        ds.imu,
        frames,
        ds.calib.time_offset_s,
        imu_start_s=imu_start,
        truth_at=truth_at,
        progress=progress,
        n_frames=n_frames,
    )
    health = [
        {
            "t_s": float(t),
            "tracked_features": h.tracked_features,
            "updated_features": h.updated_features,
            "chi2_rejections": h.chi2_rejections,
            "diverged": h.diverged,
            "reason": h.reason,
            "conditions": list(h.conditions),
        }
        for t, h in zip(run.frame_t_imu_s, run.health, strict=True)
    ]
    estimates = [
        e for e, h in zip(run.estimates, run.health, strict=True) if e is not None and not h.diverged
    ]
    return estimates, run.ms_per_frame, health


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


def evaluate_dataset(
    dataset_dir: Path,
    out_dir: Path,
    opts: EvalOptions = EvalOptions(),
    progress: ProgressFn | None = None,
) -> dict:
    """Run ``opts.estimator`` on a EuRoC folder, write TUM files into ``out_dir`` and return metrics.

    Writes ``out_dir/estimate_tum.txt`` and ``out_dir/groundtruth_tum.txt`` (TUM ``t x y z qx qy qz qw``).

    Returns:
        The metrics of :func:`viotb.vio.metrics.evaluate_trajectory` plus ``ms_per_frame_median``,
        ``ms_per_frame_p99``, ``frames``, ``estimator``, ``frontend``, ``diverged``, ``reason``.
    """
    ds = read_euroc(Path(dataset_dir))
    estimates, ms, health = run_estimator(ds, opts, progress)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    loop_result: dict = {}
    if opts.loop is not None:  # the estimates become the loop-closed ones; odometry metrics come along
        estimates, loop_result = apply_loop_closure(ds, estimates, health, opts.loop, out_dir)
    est_traj = estimates_to_trajectory(estimates)
    write_tum(out_dir / "estimate_tum.txt", est_traj)
    result: dict = {
        "dataset": str(dataset_dir),
        "estimator": opts.estimator,
        "frontend": opts.frontend,
        "frames": len(ms),
        "estimated_frames": len(estimates),
        "ms_per_frame_median": float(np.median(ms)) if ms else float("nan"),
        "ms_per_frame_p99": float(np.percentile(ms, 99)) if ms else float("nan"),
        "diverged": any(h["diverged"] for h in health),
        "reason": next((h["reason"] for h in health if h["diverged"]), ""),
        "mean_tracked_features": float(np.mean([h["tracked_features"] for h in health])) if health else 0.0,
    }
    if ds.groundtruth is not None and len(estimates) >= 2:
        gt = ds.groundtruth
        mask = (gt.t_s >= est_traj.t_s[0]) & (gt.t_s <= est_traj.t_s[-1])
        gt_span = TrajectoryArrays(gt.t_s[mask], gt.p_WB[mask], gt.quat_wxyz_WB[mask])
        write_tum(out_dir / "groundtruth_tum.txt", gt_span)
        pos_covs = np.array([e.cov_position_W_m2 for e in estimates])
        result.update(evaluate_trajectory(est_traj, gt, pos_covs=pos_covs))
    result["frames"] = len(ms)
    result.update(loop_result)
    return result
