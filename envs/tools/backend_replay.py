"""The replay scaffold of the back-end benchmarks: a recording's frames with the front end timed or replayed.

``benchmarks/msckf_backend.py`` and ``benchmarks/window_backend.py`` time an estimator's work per frame
beyond its front end. Both run the front end once (timed in thread CPU time, its tracks captured) and then
replay the captured tracks into fresh estimators, so a change to the back end is timed on exactly the same
tracks. :class:`BackendReplay` is that scaffold; the scripts time ``feed_camera`` themselves.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
from viotb.envs.data.eval_frames import camera_frame, usable_frames
from viotb.envs.data.eval_options import EvalOptions
from viotb.envs.run.replay import imu_end_for_frame
from viotb.vio.frontend import Tracks
from viotb.vio.types import CameraFrame


class _ReplayedFrontEnd:
    """Returns captured tracks in order (the estimator's ``frontend`` in a replay)."""

    def __init__(self, tracks: list[Tracks]) -> None:
        self._tracks = tracks
        self._next = 0

    def process(self, frame: CameraFrame, t_imu_s: float) -> Tracks:
        tracks = self._tracks[self._next]
        self._next += 1
        return tracks

    def reset(self) -> None:
        """Nothing to reset (the captured tracks already contain the real front end's resets)."""


class BackendReplay:
    """Frames of a recording for ``estimator``: its own front end timed and captured, or replayed tracks.

    Args:
        estimator: An estimator made by :func:`viotb.vio.factory.make_estimator` (its ``frontend`` is
            wrapped, or replaced by the replay).
        dataset: The recording (:func:`viotb.envs.data.euroc.read_euroc`).
        opts: Evaluation options (which frames are usable, the cameras).
        tracks: Captured tracks to replay (one per usable frame), or None to run the real front end.

    Attributes:
        tracks: The captured (or replayed) tracks, one per frame so far.
    """

    def __init__(self, estimator, dataset, opts: EvalOptions, tracks: list[Tracks] | None = None) -> None:
        """Install the timed front end or the replay on ``estimator``."""
        self._est, self._ds = estimator, dataset
        self._first, self._stop = usable_frames(dataset, opts)
        self._front_ms = np.zeros(self._stop - self._first)
        self._replay = tracks is not None
        if tracks is None:
            self.tracks: list[Tracks] = []
            real = estimator.frontend.process
            rng = np.random.default_rng(0)
            self._frames = (camera_frame(dataset, k, opts, rng, dataset.calib) for k in range(*self.span))

            def timed(frame: CameraFrame, t_imu_s: float) -> Tracks:
                t0 = time.thread_time()
                out = real(frame, t_imu_s)
                self._front_ms[len(self.tracks)] = (time.thread_time() - t0) * 1e3
                self.tracks.append(out)
                return out

            estimator.frontend.process = timed
        else:
            self.tracks = tracks
            estimator.frontend = _ReplayedFrontEnd(tracks)
            self._frames = (CameraFrame(t_s=float(dataset.cam_t_s[k])) for k in range(*self.span))

    @property
    def span(self) -> tuple[int, int]:
        """``(first, stop)`` indices of the usable frames."""
        return self._first, self._stop

    def frames(self) -> Iterator[CameraFrame]:
        """Each frame, after the IMU samples through it are fed (from one second before the first frame).

        Interleaved as :func:`viotb.envs.run.replay.replay` does; the caller feeds (and times) the frame.
        """
        ds, est = self._ds, self._est
        off = ds.calib.time_offset_s
        imu = ds.imu
        first, stop = self.span
        i = int(np.searchsorted(imu.t_s, float(ds.cam_t_s[first]) + off - 1.0)) if stop > first else 0
        for frame in self._frames:
            t_imu = frame.t_s + off
            end = imu_end_for_frame(imu.t_s, i, t_imu)
            while i < end:
                est.feed_imu(imu.sample(i))
                i += 1
            yield frame

    def frontend_ms(self, n: int) -> np.ndarray:
        """CPU ms of the first ``n`` frames' front end (zeros in a replay), shape (n,)."""
        return np.zeros(n) if self._replay else self._front_ms[:n].copy()


def ms_summary(ms: np.ndarray) -> dict:
    """Frames, median, p99, max and mean of per-frame times (ms), shape (N,); ``{"frames": 0}`` when empty."""
    if ms.size == 0:
        return {"frames": 0}
    return {
        "frames": int(ms.size),
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(np.max(ms)),
        "mean_ms": float(np.mean(ms)),
    }
