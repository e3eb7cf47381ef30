"""What ``viotb eval`` feeds and checks: frames (images or simulated features), truth, usable spans, IMU gaps.

Split from :mod:`viotb.envs.data.evaluate`, which runs the replay and measures it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from viotb.envs.data.euroc import EurocDataset, load_image
from viotb.envs.data.eval_options import EvalOptions
from viotb.envs.data.validate import bridge_imu_gaps, find_imu_gaps
from viotb.vio.camera import CameraCalibration
from viotb.vio.lie import quat_wxyz_to_rotmat
from viotb.vio.types import CameraFrame, ImuSeries, StateEstimate, TrajectoryArrays


def interpolate_pose(gt: TrajectoryArrays, t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth pose at ``t_s``: linear in position, normalized lerp of the quaternion."""
    i = int(np.clip(np.searchsorted(gt.t_s, t_s), 1, len(gt) - 1))
    t0, t1 = gt.t_s[i - 1], gt.t_s[i]
    a = float(np.clip((t_s - t0) / (t1 - t0), 0.0, 1.0))
    p = (1.0 - a) * gt.p_WB[i - 1] + a * gt.p_WB[i]
    q0, q1 = gt.quat_wxyz_WB[i - 1], gt.quat_wxyz_WB[i]
    q1 = q1 if np.dot(q0, q1) >= 0.0 else -q1
    q = (1.0 - a) * q0 + a * q1
    return quat_wxyz_to_rotmat(q / np.linalg.norm(q)), p


def truth_estimate(ds: EurocDataset, t_s: float) -> StateEstimate:
    """Ground truth at ``t_s`` as a :class:`StateEstimate` (for the ``ground-truth`` pass-through)."""
    R_WB, p_WB = interpolate_pose(ds.groundtruth, t_s)
    v = ds.groundtruth.v_WB
    v_WB = (
        np.zeros(3) if v is None else v[int(np.clip(np.searchsorted(ds.groundtruth.t_s, t_s), 0, len(v) - 1))]
    )
    return StateEstimate(t_s=t_s, R_WB=R_WB, p_WB=p_WB, v_WB=v_WB)


def camera_frame(
    ds: EurocDataset, i: int, opts: EvalOptions, rng: np.random.Generator, true_calib: CameraCalibration
) -> CameraFrame:
    """Camera frame ``i``: the image(s), or simulated features from the dataset's landmarks.

    The simulated features are projected with ``true_calib`` (a recording's true cam0 calibration, which a
    failure recording's ``sensor.yaml`` does not tell) and, for ``cameras == 2``, with ``cam1``'s file.
    """
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
    R_WB, p_WB = interpolate_pose(ds.groundtruth, t_cam + true_calib.time_offset_s)
    observations = []
    for calib in [true_calib] + ([ds.calib_right] if opts.cameras == 2 else []):
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


def covariances_usable(covs: np.ndarray) -> bool:
    """True when every position covariance is symmetric positive definite (NEES is defined)."""
    return bool(covs.size) and bool(np.all(np.linalg.eigvalsh(0.5 * (covs + covs.transpose(0, 2, 1))) > 0.0))
