"""Loop closure beside an estimator on a recorded dataset: the glue of ``viotb eval --loop-closure``.

The :class:`~viotb.vio.loop.LoopCloser` never feeds back into the estimator (it publishes a drift correction
on the odometry), so on a replay it runs beside it frame by frame in the same order: one ``add_frame`` per
estimated frame, with that frame's image and the estimate, and the corrected pose is read at once (causal,
blended: what a controller would have received). A frame whose health reports no tracked feature after
frames that had some (a blackout) tells the closer that tracking was lost, so the next keyframes start a new
sequence that must relocalize against the map.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc import EurocDataset, load_image
from viotb.vio.camera import CameraCalibration
from viotb.vio.lie import rotmat_to_quat_wxyz, rotz
from viotb.vio.loop import LoopCloser, LoopClosure, LoopClosureParams
from viotb.vio.loop.frames import heading_rad
from viotb.vio.metrics import evaluate_trajectory
from viotb.vio.types import StateEstimate, TrajectoryArrays

CSV_COLUMNS = ("t_query_s", "t_match_s", "x", "y", "z", "qx", "qy", "qz", "qw", "inliers")
"""Columns of ``loop_closures.csv`` (relative pose of the query body in the match body frame, m)."""


@dataclass(frozen=True)
class LoopOptions:
    """Loop closure settings of one run.

    Attributes:
        params: Loop closer parameters.
        map_in: Start in the frame of this saved map (``LoopCloser.load_map``), or None.
        map_out: Save the map here at the end, or None.
        from_excitation: In flight, keyframes from the excitation manoeuvre after the takeoff on, not only
            from the mission on. A hover makes no baseline: the keyframes at the hold point get their
            landmarks only by triangulation against the manoeuvre's, and without landmarks no place can be
            verified (``fly-lights-out`` from the mission on: 7 keyframes, 0 closures). The climb is left
            out: its poses carry the filter's not yet converged scale (measured: two of its keyframes put
            the same place 10 cm apart, and relocalizations against them missed the hold point by 8-18 cm).
        velocity_fix_wait_s: In flight, how long after the features return a re-initialization
            (``vio.recovery``) waits for the relocalized drift rate (``FlightLoopClosure.drift_velocity``)
            to correct the coasted velocity (s); 0: it does not wait.
    """

    params: LoopClosureParams = field(default_factory=LoopClosureParams)
    map_in: Path | None = None
    map_out: Path | None = None
    from_excitation: bool = False
    velocity_fix_wait_s: float = 1.0


@dataclass
class LoopRun:
    """What the closer did over a run.

    Attributes:
        online: The estimates with the pose corrected as known at each frame (causal, blended).
        final: The estimates with the final loop-closed correction (the pose graph at the end, interpolated
            between keyframes: the whole run's trajectory in the map frame).
        closer: The closer (closures, timings, graph).
    """

    online: list[StateEstimate]
    final: list[StateEstimate]
    closer: LoopCloser


def run_loop_closure(
    ds: EurocDataset, estimates: list[StateEstimate], health: list[dict], opts: LoopOptions
) -> LoopRun:
    """Feed every estimated frame with its image to a closer; returns the corrected estimates.

    Args:
        ds: The dataset (images and calibration).
        estimates: The estimator's output, one per processed frame (IMU-clock times).
        health: Per-frame records (``t_s``, ``tracked_features``) of the replay (``evaluate_dataset``).
        opts: Loop settings.
    """
    closer = LoopCloser(opts.params)
    if opts.map_in is not None:
        closer.load_map(opts.map_in)
    cam_t_imu = ds.cam_t_s + ds.calib.time_offset_s
    health_t = np.array([h["t_s"] for h in health]) if health else np.zeros(0)
    tracked = np.array([h["tracked_features"] for h in health]) if health else np.zeros(0)
    corrected: list[StateEstimate] = []
    had_tracks = False
    for i, e in enumerate(estimates):
        k = int(np.argmin(np.abs(cam_t_imu - e.t_s)))
        h = int(np.argmin(np.abs(health_t - e.t_s))) if len(health_t) else -1
        if h >= 0 and tracked[h] == 0 and had_tracks:
            closer.notify_tracking_lost()
        had_tracks = h < 0 or tracked[h] > 0
        last = i == len(estimates) - 1  # the end of the final trajectory is tied to the graph
        closer.add_frame(e.t_s, load_image(ds, k), e.R_WB, e.p_WB, ds.calib, force_keyframe=last)
        R, p = closer.corrected_pose(e.t_s, e.R_WB, e.p_WB)
        corrected.append(replace(e, R_WB=R, p_WB=p))
    if opts.map_out is not None:
        closer.save_map(opts.map_out)
    final = [
        replace(e, R_WB=T.R @ e.R_WB, p_WB=T.R @ e.p_WB + T.p)
        for e, T in zip(
            estimates, closer.smoothed_corrections(np.array([e.t_s for e in estimates])), strict=True
        )
    ]
    return LoopRun(corrected, final, closer)


def estimates_to_trajectory(estimates: list[StateEstimate]) -> TrajectoryArrays:
    """Stack estimates' times, positions and attitudes."""
    return TrajectoryArrays(
        t_s=np.array([e.t_s for e in estimates]),
        p_WB=np.array([e.p_WB for e in estimates]).reshape(-1, 3),
        quat_wxyz_WB=np.array([rotmat_to_quat_wxyz(e.R_WB) for e in estimates]).reshape(-1, 4),
    )


def write_loop_closures_csv(path: Path | str, closures: list[LoopClosure]) -> Path:
    """Write ``loop_closures.csv`` (columns :data:`CSV_COLUMNS`, one row per accepted closure)."""
    path = Path(path)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for c in closures:
            w.writerow(
                [f"{c.t_query_s:.9f}", f"{c.t_match_s:.9f}"]
                + [f"{v:.6f}" for v in (*c.p_xyz, *c.quat_xyzw)]
                + [c.inliers]
            )
    return path


def returns_to_start(gt: TrajectoryArrays, radius_m: float = 0.3, leave_m: float = 1.0) -> np.ndarray:
    """Indices of ground-truth poses closest to the start on each return (after leaving ``leave_m``)."""
    d = np.linalg.norm(gt.p_WB - gt.p_WB[0], axis=1)
    out, away, best = [], False, None
    for i, di in enumerate(d):
        if di > leave_m:
            if best is not None:
                out.append(best)
            away, best = True, None
        elif away and di < radius_m and (best is None or di < d[best]):
            best = i
    if best is not None:
        out.append(best)
    return np.array(out, dtype=np.int64)


def return_errors_m(est: TrajectoryArrays, gt: TrajectoryArrays) -> list[float]:
    """Error of the estimate's displacement from its first pose at each return of the truth to its start (m).

    The estimate's displacement is rotated by the yaw between estimated and true attitude at the first pose.
    """
    from viotb.vio.lie import quat_wxyz_to_rotmat, rotz, yaw_from_rotmat
    from viotb.vio.metrics import interpolate_trajectory

    gt_at, inside = interpolate_trajectory(gt, est.t_s)
    t = np.asarray(est.t_s)[inside]
    p_e = np.asarray(est.p_WB)[inside]
    q_e = np.asarray(est.quat_wxyz_WB)[inside]
    if len(t) < 2:
        return []
    dyaw = yaw_from_rotmat(quat_wxyz_to_rotmat(gt_at.quat_wxyz_WB[0])) - yaw_from_rotmat(
        quat_wxyz_to_rotmat(q_e[0])
    )
    gt_span = TrajectoryArrays(gt_at.t_s, gt_at.p_WB, gt_at.quat_wxyz_WB)
    errs = []
    for i in returns_to_start(gt_span):
        d_est = rotz(dyaw) @ (p_e[i] - p_e[0])
        errs.append(float(np.linalg.norm(d_est - (gt_span.p_WB[i] - gt_span.p_WB[0]))))
    return errs


def loop_metrics(run: LoopRun, odometry: TrajectoryArrays, gt: TrajectoryArrays | None) -> dict:
    """JSON keys of a loop-closure run: counts, per-frame cost, odometry vs online vs final errors.

    ``ate_posyaw_m`` of the final trajectory is the caller's (it evaluates what it writes); here
    ``ate_posyaw_odometry_m``, ``scale_error_odometry_pct`` (the odometry's metric scale error, which a
    closure between laps cannot observe), ``ate_posyaw_online_m``, and the error at each return to the start
    (``return_to_start_err{_odometry,_online,}_m``, see :func:`return_errors_m`).
    """
    closer = run.closer
    ms = np.array([ft.total_ms for ft in closer.timings]) if closer.timings else np.zeros(1)
    kf_ms = [ft.total_ms for ft in closer.timings if ft.keyframe]
    solve = [ft.optimize_ms for ft in closer.timings if ft.optimize_ms > 0]
    out: dict = {
        "loop_closures": len(closer.run_closures),
        "relocalizations": sum(c.relocalization for c in closer.run_closures),
        "loop_keyframes": len(closer.db),
        "loop_ms_per_frame_median": float(np.median(ms)),
        "loop_ms_per_frame_mean": float(np.mean(ms)),
        "loop_ms_per_frame_p99": float(np.percentile(ms, 99)),
        "loop_ms_per_keyframe_median": float(np.median(kf_ms)) if kf_ms else None,
        "loop_solve_ms_max": float(max(solve)) if solve else None,
        "loop_rejected_drift": closer.gate.rejected_drift,
        "loop_unconfirmed": closer.gate.unconfirmed,
    }
    if gt is not None and len(odometry.t_s) >= 3:
        online = estimates_to_trajectory(run.online)
        final = estimates_to_trajectory(run.final)
        odo = evaluate_trajectory(odometry, gt)
        out["ate_posyaw_odometry_m"] = odo["ate_posyaw_m"]
        out["scale_error_odometry_pct"] = odo["scale_error_pct"]  # loops keep it (README, issue #14)
        out["ate_posyaw_online_m"] = evaluate_trajectory(online, gt)["ate_posyaw_m"]
        out["return_to_start_err_odometry_m"] = return_errors_m(odometry, gt)
        out["return_to_start_err_online_m"] = return_errors_m(online, gt)
        out["return_to_start_err_m"] = return_errors_m(final, gt)
    return out


def apply_loop_closure(
    ds: EurocDataset, estimates: list[StateEstimate], health: list[dict], opts: LoopOptions, out_dir: Path
) -> tuple[list[StateEstimate], dict]:
    """``viotb eval --loop-closure``: run the closer, write its files, return the final estimates and keys.

    Writes ``out_dir/loop_closures.csv``, ``estimate_odometry_tum.txt`` (the estimator's own poses) and
    ``estimate_online_tum.txt`` (corrected as known at each frame); the caller writes the returned final
    loop-closed estimates as ``estimate_tum.txt`` and evaluates them (``ate_posyaw_m``).
    """
    from viotb.envs.data.tum import write_tum

    run = run_loop_closure(ds, estimates, health, opts)
    out_dir = Path(out_dir)
    write_loop_closures_csv(out_dir / "loop_closures.csv", run.closer.run_closures)
    odometry = estimates_to_trajectory(estimates)
    if estimates:
        write_tum(out_dir / "estimate_odometry_tum.txt", odometry)
        write_tum(out_dir / "estimate_online_tum.txt", estimates_to_trajectory(run.online))
    return run.final, loop_metrics(run, odometry, ds.groundtruth if len(estimates) >= 3 else None)


def loop_options(
    enabled: bool, map_in: Path | None = None, map_out: Path | None = None
) -> LoopOptions | None:
    """The CLI's ``--loop-closure [--map-in FILE] [--map-out FILE]`` as options (None when off).

    Raises:
        ValueError: A map flag without ``--loop-closure``, or ``--map-in`` that is not a file.
    """
    if not enabled:
        if map_in is not None or map_out is not None:
            raise ValueError("--map-in/--map-out need --loop-closure")
        return None
    if map_in is not None and not Path(map_in).is_file():
        raise ValueError(f"--map-in {map_in}: no such file")
    return LoopOptions(map_in=map_in, map_out=map_out)


def require_images(frontend: str, render_images: bool = False) -> None:
    """Loop closure works on camera images (ORB features).

    Args:
        frontend: The estimator's front end.
        render_images: Whether the run renders images anyway (a ``sim`` flight with loop closure does: the
            estimator on the simulated features, the closer on the rendered images).

    Raises:
        ValueError: ``frontend`` is not ``"klt"`` and no image is rendered.
    """
    if frontend != "klt" and not render_images:
        raise ValueError(
            f"loop closure needs camera images: the {frontend!r} front end has none; use --frontend klt"
        )


class FlightLoopClosure:
    """Loop closure in flight: the closer beside the filter, the controller on the blended corrected pose.

    The filter's own state is never touched: each delivered frame goes to the closer with the filter's
    estimate, and ``correct`` maps the estimate the controller is about to use into the map frame with the
    correction in force (blended over ``blend_duration_s``, so no jump reaches the controller). A frame
    with no tracked feature after frames with some tells the closer that tracking was lost and is not
    added (a dark or blank frame has nothing to recognize): the first frame with features again is the new
    sequence's first keyframe, the query of the relocalization.

    Args:
        opts: Loop settings.
        calib: The camera calibration the estimator is told.
        frontend: The run's front end; loop closure needs images.
        render_images: Whether images are rendered whatever the front end (``RigConfig.render_images``).

    Raises:
        ValueError: ``frontend == "sim"`` without rendered images.
    """

    def __init__(
        self, opts: LoopOptions, calib: CameraCalibration, frontend: str, render_images: bool = False
    ) -> None:
        """A closer, loaded from ``opts.map_in`` when given."""
        require_images(frontend, render_images)
        self.opts, self.calib = opts, calib
        self.closer = LoopCloser(opts.params)
        if opts.map_in is not None:
            self.closer.load_map(opts.map_in)
        self.odometry: list[StateEstimate] = []
        self.online: list[StateEstimate] = []
        self.truth: list[StateEstimate] = []
        self._had_tracks = False
        self._sequence_lost: int | None = None  # the sequence in which tracking was last lost
        self._resets: list | None = None  # the estimator's odometry resets (follow_odometry_resets)
        self._resets_seen = 0

    def follow_odometry_resets(self, resets: list) -> None:
        """Follow an estimator's odometry jumps (``RecoveringEstimator.odometry_resets``, a growing list).

        Before each frame and each correction, a jump not yet seen is handed to the closer
        (``LoopCloser.notify_odometry_reset``): the correction in force is carried over to the odometry
        after the jump, so the corrected pose does not move with it, and the next frame starts a new
        segment that relocalizes afresh. Without it a velocity fix that moved the coasted position by
        21 cm moved the corrected pose by as much, and the later loops, which put it back, were refused
        as too large a drift (``fly-lights-out`` KLT seed 5, README "Recovery in flight").
        """
        self._resets, self._resets_seen = resets, 0
        self._sync_resets()

    def _sync_resets(self) -> None:
        if self._resets is None:
            return
        while self._resets_seen < len(self._resets):
            r = self._resets[self._resets_seen]
            self._resets_seen += 1
            self.closer.notify_odometry_reset(r.R_WB_before, r.p_WB_before, r.R_WB_after, r.p_WB_after)

    def on_frame(
        self,
        t_s: float,
        image_u8: np.ndarray | None,
        est: StateEstimate | None,
        tracked: int,
        truth: StateEstimate | None = None,
    ) -> None:
        """A delivered frame with the filter's estimate after it (skipped before initialization).

        ``truth`` (the simulator's pose then, optional) feeds the odometry-vs-corrected metrics.
        """
        self._sync_resets()
        if est is None or image_u8 is None:
            return
        if tracked == 0 and self._had_tracks:
            self.closer.notify_tracking_lost()
            self._sequence_lost = self.closer.sequence
        self._had_tracks = tracked > 0
        if tracked == 0:
            return
        self.closer.add_frame(t_s, image_u8, est.R_WB, est.p_WB, self.calib)
        self.odometry.append(replace(est, t_s=t_s))
        self.online.append(self.correct(t_s, self.odometry[-1]))
        if truth is not None:
            self.truth.append(replace(truth, t_s=t_s))

    def drift_velocity(
        self, min_loops: int = 6, min_span_s: float = 0.6, sigma_m: float = 0.01
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The odometry's velocity error, from how its drift changes between loops of the current sequence.

        Each verified loop of the current sequence (``LoopCloser.verified_corrections``, accepted or not:
        a coasted pose drifts too fast for the drift bound) implies a correction ``T_map_odom`` (yaw
        ``psi_k``, translation ``t_k``) that puts the query's odometry position ``o_k`` where PnP puts it in
        the map, ``q_k = R(psi_k) o_k + t_k``. With the mean yaw ``psi``, ``d_k = q_k - R(psi) o_k`` is the
        drift at time ``t_k``. Its rate is fitted by least squares as one slope with an offset per matched
        keyframe (two map keyframes may disagree by centimetres: measured 10 cm between two of the climb,
        which a common line would read as velocity), once more without the loops more than 3 sigma off;
        it is the odometry's velocity error in the map frame, and the true velocity in the odometry frame
        is ``v_odom + R(psi)^T d'``.

        Args:
            min_loops: Fewest loops of the sequence (after the outliers are dropped).
            min_span_s: Shortest time they must span (s).
            sigma_m: Position noise of one loop (m) (closures against the truth: median 1 cm); the larger of
                it and the fit's residual sigma sets the covariance.

        Returns:
            ``(dv_odom (3,) m/s, cov (3, 3) m^2/s^2)`` to add to the odometry velocity, or None (too few
            loops, too short a span, or tracking lost and its next sequence not started).
        """
        closer = self.closer
        if closer.sequence == self._sequence_lost:
            return None  # lost, and no frame since: the sequence that follows has not started
        rows = [r for r in closer.verified_corrections if r[1] == closer.sequence]
        if len(rows) < min_loops:
            return None
        psi = [heading_rad(r[4].R) for r in rows]  # a 4-DOF correction: a rotation about the vertical
        R = rotz(float(np.arctan2(np.mean(np.sin(psi)), np.mean(np.cos(psi)))))
        t = np.array([r[0] for r in rows])
        match = np.array([r[2] for r in rows])
        d = np.array([r[4].R @ r[3] + r[4].p - R @ r[3] for r in rows])
        keep = np.ones(len(t), dtype=bool)
        for _ in range(2):
            groups = np.unique(match[keep])
            # The slope needs loops at two times or more against the same keyframe.
            if keep.sum() < min_loops or keep.sum() - len(groups) < 2 or np.ptp(t[keep]) < min_span_s:
                return None
            t0 = float(t[keep].mean())
            A = np.column_stack([match == g for g in groups] + [t - t0]).astype(float)
            coef, *_ = np.linalg.lstsq(A[keep], d[keep], rcond=None)
            resid = np.linalg.norm(d - A @ coef, axis=1)
            resid[~np.isin(match, groups)] = np.inf
            dof = max(int(keep.sum()) - len(groups) - 1, 1)
            sigma = max(sigma_m, float(np.sqrt(np.sum(resid[keep] ** 2) / (3 * dof))))
            cov_slope = sigma**2 * np.linalg.inv(A[keep].T @ A[keep])[-1, -1]
            keep = resid <= 3.0 * sigma * np.sqrt(3.0)
        return R.T @ coef[-1], np.eye(3) * cov_slope

    def correct(self, t_s: float, est: StateEstimate | None) -> StateEstimate | None:
        """The estimate in the map frame (attitude, position and velocity) with the correction in force."""
        self._sync_resets()
        if est is None:
            return None
        T = self.closer.correction(t_s)
        return replace(est, R_WB=T.R @ est.R_WB, p_WB=T.R @ est.p_WB + T.p, v_WB=T.R @ est.v_WB)

    def finish(self) -> dict:
        """Save the map when asked; the JSON keys of the closer (closures, cost)."""
        if self.opts.map_out is not None:
            self.closer.save_map(self.opts.map_out)
        run = LoopRun(self.online, self.online, self.closer)
        gt = estimates_to_trajectory(self.truth) if len(self.truth) == len(self.odometry) else None
        out = loop_metrics(run, estimates_to_trajectory(self.odometry), gt)
        out["loop_closure_rows"] = [c.as_row() for c in self.closer.run_closures]
        return out
