"""How and when an estimator initializes on a stream, against the truth (issue #13's moving starts).

:func:`check_initialization` feeds a :class:`~viotb.envs.scenarios.streams.Stream` to an estimator in IMU
time order until its first estimate and compares that state with the ground truth at the same time:

* ``delay_s``: time of the first estimate minus the time of the first image (IMU clock);
* ``scale_error``: ``|v_est| / |v_true| - 1`` (with a monocular camera the metric scale lives in the speed);
* ``velocity_error_m_s``: ``|R_est^T v_est - R_true^T v_true|`` (in the body frame: free of the yaw gauge);
* ``tilt_error_deg``: angle between the estimated and the true "up" axis seen in the body frame.

:func:`moving_start_monte_carlo` runs it over seeds and motions (the benchmark and the slow test).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from viotb.envs.run.replay import imu_end_for_frame
from viotb.envs.scenarios.streams import Stream, StreamConfig, synthesize_stream
from viotb.vio.lie import quat_wxyz_to_rotmat
from viotb.vio.msckf import MsckfEstimator, MsckfParams
from viotb.vio.window import WindowEstimator, WindowParams


@dataclass(frozen=True)
class InitCheck:
    """The first estimate of a run against the truth (see the module docstring).

    Attributes:
        t_first_frame_s: Time of the first image (s, IMU clock).
        t_init_s: Time of the first estimate (s, IMU clock), None if it never came.
        delay_s: ``t_init_s - t_first_frame_s`` (inf if never).
        method: ``"static"`` / ``"dynamic"`` (the initializer's), ``""`` if never.
        scale_error: Relative speed error (NaN at rest or if never).
        velocity_error_m_s: Body-frame velocity error (m/s).
        tilt_error_deg: Gravity-direction error (deg).
        speed_m_s: True speed at ``t_init_s`` (m/s).
        scale_sigma: The initializer's own relative scale sigma (NaN for static).
        dynamic_tries: Dynamic solves the initializer ran (refused ones included).
        cpu_per_try_s: Their mean CPU time (s; NaN without a try).
    """

    t_first_frame_s: float
    t_init_s: float | None
    delay_s: float
    method: str
    scale_error: float
    velocity_error_m_s: float
    tilt_error_deg: float
    speed_m_s: float
    scale_sigma: float
    dynamic_tries: int = 0
    cpu_per_try_s: float = float("nan")

    def as_dict(self) -> dict:
        """JSON-able fields."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _make(stream: Stream, estimator: str) -> MsckfEstimator | WindowEstimator:
    if estimator == "msckf":
        return MsckfEstimator(
            stream.calib_given,
            stream.noise,
            MsckfParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px),
        )
    if estimator == "window":
        return WindowEstimator(
            stream.calib_given,
            stream.noise,
            WindowParams(frontend="sim", pixel_sigma_px=stream.pixel_sigma_px),
        )
    raise ValueError(f"check_initialization: estimator must be 'msckf' or 'window', got {estimator!r}")


def check_initialization(stream: Stream, estimator: str = "msckf", max_delay_s: float = 5.0) -> InitCheck:
    """Run ``estimator`` (sim front end) on ``stream`` until its first estimate; compare it with the truth.

    Args:
        stream: A :func:`~viotb.envs.scenarios.streams.synthesize_stream` output (without external init).
        estimator: ``"msckf"`` or ``"window"``.
        max_delay_s: Give up this long after the first image (s).
    """
    est = _make(stream, estimator)
    initializer = est.initializer

    def tries() -> dict:
        n = initializer.dynamic_tries
        return {"dynamic_tries": n, "cpu_per_try_s": initializer.dynamic_cpu_s / n if n else float("nan")}

    imu, off = stream.imu, stream.time_offset_s
    t_first = stream.frames[0].t_s + off
    i = 0
    for frame in stream.frames:
        t_frame = frame.t_s + off
        if t_frame - t_first > max_delay_s:
            break
        end = imu_end_for_frame(imu.t_s, i, t_frame)
        while i < end:
            est.feed_imu(imu.sample(i))
            i += 1
        est.feed_camera(frame)
        e = est.estimate()
        if e is None:
            continue
        gt = stream.truth
        k = int(np.argmin(np.abs(gt.t_s - e.t_s)))
        R_true = quat_wxyz_to_rotmat(gt.quat_wxyz_WB[k])
        v_true = gt.v_WB[k]
        speed = float(np.linalg.norm(v_true))
        up_est, up_true = e.R_WB.T @ [0.0, 0.0, 1.0], R_true.T @ [0.0, 0.0, 1.0]
        init = est.initializer.last_result
        return InitCheck(
            t_first_frame_s=float(t_first),
            t_init_s=float(e.t_s),
            delay_s=float(e.t_s - t_first),
            method=init.method if init is not None else "",
            scale_error=float(np.linalg.norm(e.v_WB) / speed - 1.0) if speed > 0.05 else float("nan"),
            velocity_error_m_s=float(np.linalg.norm(e.R_WB.T @ e.v_WB - R_true.T @ v_true)),
            tilt_error_deg=float(np.rad2deg(np.arccos(np.clip(up_est @ up_true, -1.0, 1.0)))),
            speed_m_s=speed,
            scale_sigma=float(init.scale_sigma) if init is not None else float("nan"),
            **tries(),
        )
    nan = float("nan")
    return InitCheck(float(t_first), None, float("inf"), "", nan, nan, nan, nan, nan, **tries())


MOVING_STARTS = (("circle", 3.0), ("figure8", 3.0), ("hover", 3.0), ("aggressive", 4.0), ("head-walk", 3.0))
"""``(motion, start_at_s)`` of the moving-start Monte Carlo: each stream is entered ``start_at_s`` into its
run (1.5 s still start included), in motion."""


def moving_start_monte_carlo(
    seeds: list[int],
    starts: tuple[tuple[str, float], ...] = MOVING_STARTS,
    estimator: str = "msckf",
    seconds: float = 8.0,
    landmark_count: int = 600,
    max_delay_s: float = 5.0,
) -> list[dict]:
    """:func:`check_initialization` per seed and moving start; rows ``{motion, start_at_s, seed, ...}``.

    Args:
        seeds: Seeds (each gives another IMU, landmark and pixel-noise draw).
        starts: ``(motion, start_at_s)`` pairs.
        estimator: ``"msckf"`` or ``"window"``.
        seconds: Motion duration of each stream (s; the motion is built for it, then entered).
        landmark_count: Scene landmarks.
        max_delay_s: Give up this long after the first image (s).
    """
    rows = []
    for motion, start_at_s in starts:
        base = StreamConfig(motion=motion, seconds=seconds, landmark_count=landmark_count)
        for seed in seeds:
            cfg = replace(base, start_at_s=start_at_s)
            check = check_initialization(synthesize_stream(cfg, seed), estimator, max_delay_s)
            rows.append({"motion": motion, "start_at_s": start_at_s, "seed": seed, **check.as_dict()})
    return rows
