"""Run an estimator over any EuRoC-layout folder (recorded here or real) and measure it.

This is the engine of ``viotb eval``: it replays the IMU and camera streams in timestamp order on the IMU
clock, times the estimator per frame, writes TUM trajectories and returns the metrics of
:mod:`viotb.vio.metrics`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType

import numpy as np
from viotb.envs.data.euroc import EurocDataset, load_image, read_euroc
from viotb.envs.data.tum import write_tum
from viotb.envs.data.validate import IMU_GAP_POLICIES, bridge_imu_gaps, find_imu_gaps
from viotb.envs.run.replay import replay
from viotb.envs.tools.outdir import atomic_out_dir
from viotb.vio.factory import make_estimator
from viotb.vio.lie import quat_wxyz_to_rotmat, rotmat_to_quat_wxyz
from viotb.vio.metrics import evaluate_trajectory
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.types import CameraFrame, ImuSeries, StateEstimate, TrajectoryArrays
from viotb.vio.window import WindowParams

ProgressFn = Callable[[float, float], None]

NULL_REASONS = MappingProxyType(
    {
        "rpe_1m_pct": "no two evaluated poses 1 m apart along the ground-truth path",
        "scale_error_pct": "the evaluated path is too short to measure a scale",
        "drift_pct": "the evaluated path is too short to measure drift",
        "ms_per_frame_median": "no frame was processed",
        "ms_per_frame_p99": "no frame was processed",
    }
)
"""Why a metric of :func:`evaluate_dataset` can be NaN (``--json`` prints ``null`` with this reason)."""


@dataclass(frozen=True)
class EvalOptions:
    """Options of one evaluation run.

    Attributes:
        estimator: Estimator name (see ``viotb.vio.factory.ESTIMATOR_NAMES``).
        frontend: ``"klt"`` (OpenCV on the images, default) or ``"sim"`` (projections of the dataset's
            ``sim_landmarks0`` with ground-truth poses plus pixel noise; recorded datasets only).
        seed: Seed of the pixel noise in the ``sim`` front end.
        sim_pixel_sigma_px: Pixel noise (px) of the ``sim`` front end.
        max_frames: Stop after this many frames (None = all; >= 0).
        msckf: MSCKF settings (None: the defaults).
        window: Window-optimizer settings (None: the defaults).
        imu_gap_policy: What to do with a gap in ``imu0/data.csv`` longer than ``imu_gap_tolerance_periods``
            nominal periods: ``refuse`` (a ValueError naming file, lines and times) or ``bridge`` (linear
            interpolation at the nominal rate, reported in ``imu_gaps`` and ``notes``).
        imu_gap_tolerance_periods: Longest normal spacing of IMU samples, in nominal periods (> 1).
        cameras: 1 (``cam0`` only, the default, so results on stereo folders match earlier runs) or 2
            (``cam0`` and ``cam1``: ``calib_right`` to the estimator, ``image_right`` / ``features_right``
            in each frame).
    """

    estimator: str = "msckf"
    frontend: str = "klt"
    seed: int = 0
    sim_pixel_sigma_px: float = 0.5
    max_frames: int | None = None
    msckf: MsckfParams | None = None
    window: WindowParams | None = None
    cameras: int = 1
    imu_gap_policy: str = "refuse"
    imu_gap_tolerance_periods: float = 5.0

    def __post_init__(self) -> None:
        """Reject a negative ``max_frames``, an unknown gap policy and a tolerance <= 1 period."""
        if self.max_frames is not None and not (isinstance(self.max_frames, int) and self.max_frames >= 0):
            raise ValueError(f"max_frames must be an integer >= 0, got {self.max_frames!r}")
        if self.imu_gap_policy not in IMU_GAP_POLICIES:
            raise ValueError(
                f"unknown IMU gap policy {self.imu_gap_policy!r}; allowed: {', '.join(IMU_GAP_POLICIES)}"
            )
        if not self.imu_gap_tolerance_periods > 1.0:
            raise ValueError(f"imu_gap_tolerance_periods must be > 1, got {self.imu_gap_tolerance_periods!r}")
        if self.cameras not in (1, 2):
            raise ValueError(f"cameras must be 1 or 2, got {self.cameras!r}")


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
    R_WB, p_WB = _interpolate_pose(ds.groundtruth, t_s)
    v = ds.groundtruth.v_WB
    v_WB = (
        np.zeros(3) if v is None else v[int(np.clip(np.searchsorted(ds.groundtruth.t_s, t_s), 0, len(v) - 1))]
    )
    return StateEstimate(t_s=t_s, R_WB=R_WB, p_WB=p_WB, v_WB=v_WB)


def _frame(ds: EurocDataset, i: int, opts: EvalOptions, rng: np.random.Generator) -> CameraFrame:
    """Camera frame ``i``: the image(s), or simulated features from the dataset's landmarks."""
    t_cam = float(ds.cam_t_s[i])
    j = ds.right_index(i) if opts.cameras == 2 else None
    if opts.frontend != "sim":
        if opts.cameras == 2:
            right = None if j is None else load_image(ds, j, camera=1)
            return CameraFrame(t_s=t_cam, image=load_image(ds, i), image_right=right)
        return CameraFrame(t_s=t_cam, image=load_image(ds, i))
    from viotb.envs.sim.landmarks import project_landmarks

    if ds.landmarks_W is None or ds.groundtruth is None:
        raise ValueError(
            f"{ds.root}: the 'sim' front end needs mav0/sim_landmarks0/data.csv and ground truth; "
            "use --frontend klt on real data"
        )
    R_WB, p_WB = _interpolate_pose(ds.groundtruth, t_cam + ds.calib.time_offset_s)
    observations = []
    for calib in [ds.calib] + ([ds.calib_right] if opts.cameras == 2 else []):
        R_WC = R_WB @ calib.R_BC
        p_WC = p_WB + R_WB @ calib.p_BC
        observations.append(
            project_landmarks(ds.landmarks_W, R_WC, p_WC, calib.camera, rng, opts.sim_pixel_sigma_px)
        )
    if opts.cameras == 2:
        return CameraFrame(t_s=t_cam, features=observations[0], features_right=observations[1])
    return CameraFrame(t_s=t_cam, features=observations[0])


def usable_frames(ds: EurocDataset, opts: EvalOptions) -> tuple[int, int]:
    """Frames ``[first, stop)`` the replay feeds: within ``max_frames`` and inside the IMU's time span.

    A frame before the first IMU sample (or after the last) cannot be propagated to, so it is skipped;
    :func:`evaluate_dataset` reports how many.
    """
    n = len(ds.cam_t_s) if opts.max_frames is None else min(opts.max_frames, len(ds.cam_t_s))
    t_imu = ds.cam_t_s[:n] + ds.calib.time_offset_s
    first = int(np.searchsorted(t_imu, ds.imu.t_s[0], side="left"))
    stop = int(np.searchsorted(t_imu, ds.imu.t_s[-1], side="right"))
    return first, max(first, stop)


def run_estimator(
    ds: EurocDataset, opts: EvalOptions, progress: ProgressFn | None = None
) -> tuple[list[StateEstimate], list[float], list[dict]]:
    """Replay a dataset through an estimator (:func:`viotb.envs.run.replay.replay`).

    Returns:
        Estimates at each processed frame (after initialization, before any divergence), per-frame wall time
        (ms), and per-frame health records (dicts with t_s, tracked_features, updated_features,
        chi2_rejections, diverged, reason, conditions).
    """
    if opts.cameras not in (1, 2):
        raise ValueError(f"cameras must be 1 or 2, got {opts.cameras}")
    if opts.cameras == 2 and not ds.has_stereo:
        raise ValueError(f"{ds.root}: --cameras 2 needs a cam1 folder (this dataset is mono)")
    # The stereo keyword goes only to a stereo run, so mono runs do not depend on the stereo estimators.
    stereo = {"calib_right": ds.calib_right} if opts.cameras == 2 else {}
    est = make_estimator(
        opts.estimator,
        ds.calib,
        ds.imu_noise,
        frontend=opts.frontend,
        params=opts.msckf,
        window_params=opts.window,
        **stereo,
    )
    if opts.estimator == "ground-truth" and ds.groundtruth is None:
        raise ValueError(
            f"{ds.root}: the ground-truth estimator needs state_groundtruth_estimate0/data.csv, "
            "which this dataset does not have"
        )
    rng = np.random.default_rng(opts.seed)
    first, stop = usable_frames(ds, opts)
    n_frames = stop - first
    frame_t_imu = ds.cam_t_s[first:stop] + ds.calib.time_offset_s
    # Start the IMU one second before the first frame (static initialization needs a still window).
    imu_start = float(frame_t_imu[0]) - 1.0 if n_frames else None
    truth_at = (lambda t: _truth_estimate(ds, t)) if opts.estimator == "ground-truth" else None
    frames = (_frame(ds, k, opts, rng) for k in range(first, stop))
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


def apply_imu_gap_policy(ds: EurocDataset, opts: EvalOptions) -> tuple[EurocDataset, list[dict], list[str]]:
    """Find IMU gaps beyond the tolerance and refuse or bridge them (``opts.imu_gap_policy``).

    Returns:
        ``(dataset, gaps, notes)``: the dataset (with bridged samples under ``bridge``), one dict per gap
        (``line0``, ``line1``, ``t0_s``, ``t1_s``, ``samples_inserted``) and notes naming them.

    Raises:
        ValueError: Under ``refuse``, naming the file, the lines and the times of every gap.
    """
    path = ds.root / "imu0" / "data.csv"
    gaps = find_imu_gaps(path, ds.imu_t_ns, ds.imu_rate_hz, opts.imu_gap_tolerance_periods)
    if not gaps:
        return ds, [], []
    tolerance = f"{opts.imu_gap_tolerance_periods:g} periods at the nominal {ds.imu_rate_hz:g} Hz"
    if opts.imu_gap_policy == "refuse":
        named = "; ".join(g.describe(path) for g in gaps[:5]) + ("; ..." if len(gaps) > 5 else "")
        raise ValueError(
            f"{len(gaps)} IMU gap(s) longer than {tolerance}: {named}. "
            "Refused; --imu-gap-policy bridge interpolates across them (and reports it)"
        )
    imu = ds.imu
    values = np.hstack([imu.gyro_B_rad_s, imu.accel_B_m_s2])
    t_s, values, inserted = bridge_imu_gaps(imu.t_s, values, gaps, ds.imu_rate_hz)
    bridged = ImuSeries(t_s, values[:, :3].copy(), values[:, 3:].copy(), np.zeros(len(t_s), dtype=bool))
    report = [
        {"line0": g.line0, "line1": g.line1, "t0_s": g.t0_s, "t1_s": g.t1_s, "samples_inserted": n}
        for g, n in zip(gaps, inserted, strict=True)
    ]
    notes = [
        f"IMU gap bridged by linear interpolation ({n} samples): {g.describe(path)}"
        for g, n in zip(gaps, inserted, strict=True)
    ]
    return replace(ds, imu=bridged), report, notes


def _covariances_usable(covs: np.ndarray) -> bool:
    """True when every position covariance is symmetric positive definite (NEES is defined)."""
    return bool(covs.size) and bool(np.all(np.linalg.eigvalsh(0.5 * (covs + covs.transpose(0, 2, 1))) > 0.0))


def evaluate_dataset(
    dataset_dir: Path,
    out_dir: Path,
    opts: EvalOptions = EvalOptions(),
    progress: ProgressFn | None = None,
    overwrite: bool = False,
) -> dict:
    """Run ``opts.estimator`` on a EuRoC folder, write TUM files into ``out_dir`` and return metrics.

    Writes ``out_dir/estimate_tum.txt`` and ``out_dir/groundtruth_tum.txt`` (TUM ``t x y z qx qy qz qw``)
    atomically (:func:`viotb.envs.tools.outdir.atomic_out_dir`): ``out_dir`` is checked before any work, a
    non-empty one is refused unless ``overwrite``, and a run that fails or is interrupted leaves nothing.

    Returns:
        The metrics of :func:`viotb.vio.metrics.evaluate_trajectory` plus ``ms_per_frame_median``,
        ``ms_per_frame_p99``, ``frames``, ``estimator``, ``frontend``, ``diverged``, ``reason``,
        ``frames_skipped_before_imu``, ``frames_skipped_after_imu``, ``frames_without_estimate``,
        ``imu_gaps`` and ``notes`` (a list of strings; why a metric is missing or NaN, see
        :data:`NULL_REASONS`).

    Raises:
        ValueError: A bad dataset, an IMU gap under the ``refuse`` policy, or a bad ``out_dir``.
        FileNotFoundError: A missing dataset file.
    """
    with atomic_out_dir(out_dir, overwrite) as tmp_dir:
        ds = read_euroc(Path(dataset_dir))
        ds, gaps, notes = apply_imu_gap_policy(ds, opts)
        first, stop = usable_frames(ds, opts)
        n_wanted = len(ds.cam_t_s) if opts.max_frames is None else min(opts.max_frames, len(ds.cam_t_s))
        estimates, ms, health = run_estimator(ds, opts, progress)
        est_traj = estimates_to_trajectory(estimates)
        write_tum(tmp_dir / "estimate_tum.txt", est_traj)
        result: dict = {
            "dataset": str(dataset_dir),
            "estimator": opts.estimator,
            "frontend": opts.frontend,
            "cameras": opts.cameras,
            "frames": len(ms),
            "estimated_frames": len(estimates),
            "frames_skipped_before_imu": first,
            "frames_skipped_after_imu": n_wanted - stop,
            "frames_without_estimate": len(ms) - len(estimates),
            "imu_gaps": gaps,
            "ms_per_frame_median": float(np.median(ms)) if ms else float("nan"),
            "ms_per_frame_p99": float(np.percentile(ms, 99)) if ms else float("nan"),
            "diverged": any(h["diverged"] for h in health),
            "reason": next((h["reason"] for h in health if h["diverged"]), ""),
            "mean_tracked_features": float(np.mean([h["tracked_features"] for h in health]))
            if health
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
            notes.append("no ground truth (state_groundtruth_estimate0/data.csv): no accuracy metrics")
        elif len(estimates) < 2:
            notes.append(f"only {len(estimates)} estimate(s): no accuracy metrics")
        else:
            gt = ds.groundtruth
            mask = (gt.t_s >= est_traj.t_s[0]) & (gt.t_s <= est_traj.t_s[-1])
            gt_span = TrajectoryArrays(gt.t_s[mask], gt.p_WB[mask], gt.quat_wxyz_WB[mask])
            write_tum(tmp_dir / "groundtruth_tum.txt", gt_span)
            pos_covs = np.array([e.cov_position_W_m2 for e in estimates])
            usable = _covariances_usable(pos_covs)
            result.update(evaluate_trajectory(est_traj, gt, pos_covs=pos_covs if usable else None))
            if not usable:
                notes.append(
                    f"nees_pos_mean: null (the {opts.estimator} estimator reports no positive-definite "
                    "position covariance)"
                )
        result["frames"] = len(ms)
        result["notes"] = notes
    return result
