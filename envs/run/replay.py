"""The one open-loop replay: IMU samples and camera frames fed to an estimator in timestamp order.

Used by ``viotb eval`` (:mod:`viotb.envs.data.evaluate`), by the failure runner
(:mod:`viotb.envs.run.failure_runner`) and by the tests that watch an estimator with the health monitor.
Frames are stamped on the camera clock; they are interleaved with the IMU on the IMU clock, ``t_imu = t_cam +
time_offset_s``: every IMU sample up to a frame's IMU time is fed before the frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
from viotb.vio.health import HealthMonitor
from viotb.vio.types import CameraFrame, Estimator, HealthStatus, ImuSeries, StateEstimate

ProgressFn = Callable[[float, float], None]


@dataclass
class MonitoredRun:
    """What a replay saw, one entry per frame fed.

    Attributes:
        estimates: Estimate after each frame (None before initialization).
        frame_t_imu_s: Frame times on the IMU clock (s), shape (F,).
        health: Estimator health after each frame.
        active: The monitor's active conditions after each frame (empty sets without a monitor).
        monitor: The monitor (``report()`` for the conditions), or None when the replay ran without one.
        ms_per_frame: Wall time (ms) of each ``feed_camera`` call.
        monitor_ms: Total wall time (ms) spent in the monitor's ``observe_imu`` / ``observe_frame`` calls.
    """

    estimates: list[StateEstimate | None]
    frame_t_imu_s: np.ndarray
    health: list[HealthStatus]
    active: list[set[str]]
    monitor: HealthMonitor | None
    ms_per_frame: list[float] = field(default_factory=list)
    monitor_ms: float = 0.0


def imu_end_for_frame(imu_t_s: np.ndarray, i: int, t_frame_imu_s: float) -> int:
    """End (exclusive) of the IMU samples to feed, from index ``i``, before a frame at ``t_frame_imu_s``.

    Through the first sample at or past the frame's time (IMU clock), so the estimator interpolates the
    readings at the frame instead of holding the last one over the rest of the interval (see
    :func:`replay`); a frame past the last sample gets every sample, one before the first gets none.

    Args:
        imu_t_s: IMU sample times (s), shape (N,), increasing.
        i: First sample not fed yet.
        t_frame_imu_s: The frame's time on the IMU clock (s).
    """
    j = int(np.searchsorted(imu_t_s, t_frame_imu_s, side="left"))  # the first sample at or past the frame
    if j == 0 and (len(imu_t_s) == 0 or imu_t_s[0] > t_frame_imu_s):
        return i
    return max(i, min(j + 1, len(imu_t_s)))


def replay(
    estimator: Estimator,
    imu: ImuSeries,
    frames: Iterable[CameraFrame],
    time_offset_s: float,
    monitor: HealthMonitor | None = None,
    stop_on_divergence: bool = True,
    imu_start_s: float | None = None,
    truth_at: Callable[[float], StateEstimate] | None = None,
    progress: ProgressFn | None = None,
    n_frames: int | None = None,
) -> MonitoredRun:
    """Replay ``imu`` and ``frames`` through ``estimator`` (and ``monitor``, when given) in IMU-clock order.

    A frame is fed once the IMU has reached its time: after the first sample at or past it (as open_vins
    and VINS-Mono wait for the IMU to pass an image), so the estimator interpolates the readings at the
    frame instead of holding the last one over the rest of the interval. Held, a 200 Hz IMU put the pose
    of each 30 Hz frame of ``head-fast-turns`` (350 deg/s) off by up to half the angular acceleration times
    the 5 ms squared: MSCKF ATE 4.01 -> 0.84 cm, position NEES 10.1 -> 0.37, and 159 -> 3.2 told the
    render noise model (README "Consistency per scenario"). Frames on the IMU's grid (the drones' 20 Hz on
    200 Hz) get the same readings as before.

    Args:
        estimator: Any estimator of the :class:`~viotb.vio.types.Estimator` protocol.
        imu: IMU series (N samples).
        frames: Camera frames in time order (camera clock); may be a lazy iterable (images load as they come).
        time_offset_s: ``t_imu = t_cam + time_offset_s`` used to interleave the streams.
        monitor: Health monitor fed every IMU sample and every frame (None: no monitor).
        stop_on_divergence: Stop after the first frame whose health reports divergence.
        imu_start_s: Skip IMU samples before this time (s, IMU clock); None = from the first sample.
        truth_at: For the ``ground-truth`` pass-through: the truth at an IMU time, fed with
            ``estimator.feed_truth`` before each frame.
        progress: Optional ``(frames_done, n_frames)`` callback.
        n_frames: Total frame count for ``progress``.

    Returns:
        One entry per frame fed (the frame that diverged included).
    """
    out = MonitoredRun([], np.zeros(0), [], [], monitor)
    times: list[float] = []
    i = 0 if imu_start_s is None else int(np.searchsorted(imu.t_s, imu_start_s))
    total = float(n_frames) if n_frames is not None else float("nan")
    for k, frame in enumerate(frames):
        t_imu = float(frame.t_s) + time_offset_s
        end = imu_end_for_frame(imu.t_s, i, t_imu)
        while i < end:
            s = imu.sample(i)
            estimator.feed_imu(s)
            if monitor is not None:
                t0 = time.perf_counter()
                monitor.observe_imu(s)
                out.monitor_ms += (time.perf_counter() - t0) * 1e3
            i += 1
        if truth_at is not None:
            estimator.feed_truth(truth_at(t_imu))
        t0 = time.perf_counter()
        estimator.feed_camera(frame)
        out.ms_per_frame.append((time.perf_counter() - t0) * 1e3)
        h = estimator.health()
        est = estimator.estimate()
        if monitor is not None:
            t0 = time.perf_counter()
            monitor.observe_frame(t_imu, h, est)
            out.active.append(monitor.active())
            out.monitor_ms += (time.perf_counter() - t0) * 1e3
        else:
            out.active.append(set())
        times.append(t_imu)
        out.estimates.append(est)
        out.health.append(h)
        if progress is not None:
            progress(k + 1, total)
        if h.diverged and stop_on_divergence:
            break
    out.frame_t_imu_s = np.array(times)
    return out


def monitor_run(
    estimator: Estimator,
    imu: ImuSeries,
    frames: Iterable[CameraFrame],
    time_offset_s: float,
    monitor: HealthMonitor | None = None,
    stop_on_divergence: bool = True,
) -> MonitoredRun:
    """:func:`replay` with a health monitor (a default :class:`~viotb.vio.health.HealthMonitor` when None)."""
    mon = monitor if monitor is not None else HealthMonitor()
    return replay(estimator, imu, frames, time_offset_s, monitor=mon, stop_on_divergence=stop_on_divergence)
