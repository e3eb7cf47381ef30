"""CPU time of the MSCKF back end per camera frame, the front end replayed from a capture.

The front end (KLT, stereo matching) is most of a frame and does not depend on the filter, so it runs once:
the recording is evaluated as ``viotb eval`` does (the real front end, the estimator online) while every
frame's tracks are kept. The back end (propagation, ZUPT, cloning, MSCKF update, marginalization, health) is
then replayed ``repeats`` times on those tracks; each frame's time is its minimum over the repeats (the work
per frame is the same in every repeat, so the minimum removes the other processes' load). Times are
``time.thread_time`` of ``feed_camera`` (BLAS runs on one thread, :mod:`viotb`). Every replay reproduces
the online run's estimates bit for bit (``tests/test_msckf_backend_bench.py``).

Usage::

    python benchmarks/msckf_backend.py DATASET [--cameras 1|2] [--frontend klt|sim] [--repeats 3]
        [--headset] [--kernels numba,numpy]

prints one JSON object: per-frame median / p99 / max (ms) of the back end, of keyframes (an update ran) and
of the other frames, the online run's front end per frame, and the frame counts. ``--headset`` builds the
estimator as ``envs/run/headset.py`` does (``HEADSET_MSCKF``: a clone every frame, gyro intrinsics, its
track random walk; the gyro noise times ``default_gyro_noise_inflation`` by ``estimator_imu_noise``).
``--kernels`` lists the ``MsckfParams.update_kernels`` to time: the online pass uses the first, and the
replays of all of them run interleaved (repeat 1 of each, then repeat 2, ...), each with its per-frame
minimum (``backend`` is the first's; ``backend_by_kernels`` has all, with the ratio of the summed minima).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc import read_euroc
from viotb.envs.data.eval_options import EvalOptions
from viotb.envs.run.headset import HEADSET_MSCKF, default_gyro_noise_inflation, estimator_imu_noise
from viotb.envs.tools.backend_replay import BackendReplay, ms_summary
from viotb.vio.factory import make_estimator
from viotb.vio.frontend import Tracks
from viotb.vio.msckf_params import MsckfParams


class BackendRun:
    """One pass over a recording (a plain class: the script is also loaded as a module by file path).

    Attributes:
        tracks: Front-end output of each frame (what the replays feed).
        frame_t_s: Frame times (s, camera clock), shape (N,).
        backend_ms: CPU ms of each ``feed_camera`` less its front end, shape (N,).
        frontend_ms: CPU ms of each frame's front end (0 in a replay), shape (N,).
        keyframe: Whether the frame ran an MSCKF update (a clone was added), shape (N,).
        estimates: ``(p_WB, R_WB, cov)`` after each frame with an estimate.
    """

    def __init__(self) -> None:
        """An empty run."""
        self.tracks: list[Tracks] = []
        self.frame_t_s = np.zeros(0)
        self.backend_ms = np.zeros(0)
        self.frontend_ms = np.zeros(0)
        self.keyframe = np.zeros(0, dtype=bool)
        self.estimates: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []


def run_backend(
    dataset: Path,
    cameras: int = 1,
    frontend: str = "klt",
    tracks: list[Tracks] | None = None,
    headset: bool = False,
    kernels: str = "numba",
):
    """Run the MSCKF over ``dataset`` (the real front end when ``tracks`` is None, else a replay of them).

    IMU samples and frames are interleaved as in :func:`viotb.envs.run.replay.replay` (the IMU from one
    second before the first usable frame). ``headset``: the headset runner's settings (module doc);
    ``kernels``: ``MsckfParams.update_kernels``.

    Returns:
        The :class:`BackendRun`.
    """
    ds = read_euroc(Path(dataset))
    opts = EvalOptions(cameras=cameras, frontend=frontend)
    stereo = {"calib_right": ds.calib_right} if cameras == 2 else {}
    params, noise = replace(MsckfParams(), update_kernels=kernels), ds.imu_noise
    if headset:
        params = replace(HEADSET_MSCKF, update_kernels=kernels)
        noise = estimator_imu_noise(noise, default_gyro_noise_inflation("msckf", params))
    est = make_estimator("msckf", ds.calib, noise, frontend=frontend, params=params, **stereo)
    replay = BackendReplay(est, ds, opts, tracks)
    run = BackendRun()
    total_ms, t_frames, keyframe = [], [], []
    for frame in replay.frames():
        n_clones = len(est.state.clones) if est.state is not None else 0
        last_clone = next(reversed(est.state.clones), None) if n_clones else None
        t0 = time.thread_time()
        est.feed_camera(frame)
        total_ms.append((time.thread_time() - t0) * 1e3)
        t_frames.append(frame.t_s)
        st = est.state
        keyframe.append(st is not None and bool(st.clones) and next(reversed(st.clones)) != last_clone)
        e = est.estimate()
        if e is not None:
            run.estimates.append((np.array(e.p_WB), np.array(e.R_WB), np.array(e.cov)))
    run.frame_t_s = np.array(t_frames)
    run.tracks = replay.tracks
    run.frontend_ms = replay.frontend_ms(len(total_ms))
    run.backend_ms = np.array(total_ms) - run.frontend_ms
    run.keyframe = np.array(keyframe, dtype=bool)
    return run


def measure(
    dataset: Path,
    cameras: int = 1,
    frontend: str = "klt",
    repeats: int = 3,
    headset: bool = False,
    kernels: tuple[str, ...] = ("numba",),
) -> dict:
    """Capture the front end once, replay the back end ``repeats`` times; per-frame minima (module doc)."""
    online = run_backend(dataset, cameras, frontend, headset=headset, kernels=kernels[0])
    replays: dict[str, list[BackendRun]] = {k: [] for k in kernels}
    for _ in range(repeats):
        for k in kernels:  # interleaved: every variant sees the same load
            replays[k].append(run_backend(dataset, cameras, frontend, online.tracks, headset, k))
    best = {k: np.min([r.backend_ms for r in runs], axis=0) for k, runs in replays.items()}
    reproduced = all(
        all(np.array_equal(a, b) for a, b in zip(x, y, strict=True))
        for r in replays[kernels[0]]
        for x, y in zip(online.estimates, r.estimates, strict=True)
    ) and all(len(r.estimates) == len(online.estimates) for r in replays[kernels[0]])
    kf = online.keyframe
    by_kernels = {
        k: {
            "backend": ms_summary(b),
            "backend_keyframes": ms_summary(b[kf]),
            "sum_ms": float(np.sum(b)),
            "sum_ratio_to_first": float(np.sum(b) / np.sum(best[kernels[0]])),
        }
        for k, b in best.items()
    }
    first = best[kernels[0]]
    return {
        "dataset": str(dataset),
        "cameras": cameras,
        "frontend": frontend,
        "headset": headset,
        "kernels": list(kernels),
        "repeats": repeats,
        "backend": ms_summary(first),
        "backend_keyframes": ms_summary(first[kf]),
        "backend_other_frames": ms_summary(first[~kf]),
        "backend_by_kernels": by_kernels,
        "frontend_online": ms_summary(online.frontend_ms),
        "replay_reproduces_online_estimates": bool(reproduced),
    }


def main() -> None:
    """Command line: print :func:`measure`'s JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--cameras", type=int, choices=(1, 2), default=1)
    ap.add_argument("--frontend", choices=("klt", "sim"), default="klt")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--headset", action="store_true", help="the headset runner's MSCKF settings and IMU noise"
    )
    ap.add_argument("--kernels", default="numba", help="comma-separated MsckfParams.update_kernels to time")
    a = ap.parse_args()
    kernels = tuple(k.strip() for k in a.kernels.split(",") if k.strip())
    print(json.dumps(measure(a.dataset, a.cameras, a.frontend, a.repeats, a.headset, kernels), indent=1))


if __name__ == "__main__":
    main()
