"""CPU time of the ``window`` optimizer's back end per camera frame, the front end replayed from a capture.

As :mod:`benchmarks.msckf_backend` for the MSCKF: the recording is evaluated as ``viotb eval --estimator
window`` does (the real KLT front end, the estimator online) while every frame's tracks are kept; the back end
(keyframe rule, stillness test, preintegration, NIS, triangulation, Levenberg-Marquardt steps, covariances,
marginalization) is then replayed ``repeats`` times on those tracks, and each frame's time is its minimum over
the repeats (the work per frame is the same in every repeat, so the minimum removes the other processes'
load). Times are ``time.thread_time`` of ``feed_camera`` (BLAS on one thread, :mod:`viotb`).

Two ways to use it:

- ``python benchmarks/window_backend.py DATASET [--repeats 3]``: capture and replay in one process, print a
  JSON summary (per-frame median / p99 / max of the back end; keyframe frames, the frames that continue a
  solve, the others; whether every replay reproduced the online estimates bit for bit).
- Before/after comparisons of two checkouts: ``--capture FILE`` writes the tracks (pickle) and exits;
  ``--tracks FILE --save RUN.npz`` replays them (run this with each checkout's ``PYTHONPATH``, alternating
  processes) and saves the per-frame minima, the keyframe flags and every estimate; ``--compare A.npz B.npz``
  prints both summaries, the ratios and the largest estimate difference.
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc import read_euroc
from viotb.envs.data.eval_options import EvalOptions
from viotb.envs.tools.backend_replay import BackendReplay, ms_summary
from viotb.vio.factory import make_estimator
from viotb.vio.frontend import Tracks
from viotb.vio.window_params import WindowParams


class BackendRun:
    """One pass over a recording (a plain class: the script is also loaded as a module by file path).

    Attributes:
        tracks: Front-end output of each frame (what the replays feed).
        backend_ms: CPU ms of each ``feed_camera`` less its front end, shape (N,).
        frontend_ms: CPU ms of each frame's front end (0 in a replay), shape (N,).
        keyframe: Whether the frame added a keyframe, shape (N,).
        solving: Whether the frame (not a keyframe) took steps of a keyframe's solve, shape (N,).
        estimates: ``(p_WB (3,), R_WB (3, 3), cov (15, 15))`` after each frame with an estimate.
    """

    def __init__(self) -> None:
        """An empty run."""
        self.tracks: list[Tracks] = []
        self.backend_ms = np.zeros(0)
        self.frontend_ms = np.zeros(0)
        self.keyframe = np.zeros(0, dtype=bool)
        self.solving = np.zeros(0, dtype=bool)
        self.estimates: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []


def run_backend(
    dataset: Path, tracks: list[Tracks] | None = None, params: WindowParams | None = None
) -> BackendRun:
    """Run the window over ``dataset`` (the real KLT front end when ``tracks`` is None, else a replay).

    IMU samples and frames are interleaved as in :func:`viotb.envs.run.replay.replay` (the IMU from one second
    before the first usable frame), the estimator built as ``viotb eval --estimator window`` builds it.
    """
    ds = read_euroc(Path(dataset))
    opts = EvalOptions(estimator="window")
    est = make_estimator("window", ds.calib, ds.imu_noise, frontend="klt", window_params=params)
    replay = BackendReplay(est, ds, opts, tracks)
    run = BackendRun()
    total_ms, keyframe, solving = [], [], []
    for frame in replay.frames():
        n_kf, n_solves = est.keyframes_added, len(est.solve_iterations)
        t0 = time.thread_time()
        est.feed_camera(frame)
        total_ms.append((time.thread_time() - t0) * 1e3)
        is_kf = est.keyframes_added != n_kf
        keyframe.append(is_kf)
        solving.append(not is_kf and len(est.solve_iterations) != n_solves)
        e = est.estimate()
        if e is not None:
            run.estimates.append((np.array(e.p_WB), np.array(e.R_WB), np.array(e.cov)))
    run.tracks = replay.tracks
    run.frontend_ms = replay.frontend_ms(len(total_ms))
    run.backend_ms = np.array(total_ms) - run.frontend_ms
    run.keyframe = np.array(keyframe, dtype=bool)
    run.solving = np.array(solving, dtype=bool)
    return run


def summarize(best_ms: np.ndarray, keyframe: np.ndarray, solving: np.ndarray) -> dict:
    """Summaries of the per-frame back-end minima: all frames, keyframes, solve continuations, the rest."""
    return {
        "backend": ms_summary(best_ms),
        "backend_keyframes": ms_summary(best_ms[keyframe]),
        "backend_continuations": ms_summary(best_ms[solving]),
        "backend_other_frames": ms_summary(best_ms[~keyframe & ~solving]),
        "sum_ms": float(np.sum(best_ms)),
    }


def _same(a: BackendRun, b: BackendRun) -> bool:
    return len(a.estimates) == len(b.estimates) and all(
        all(np.array_equal(x, y) for x, y in zip(ea, eb, strict=True))
        for ea, eb in zip(a.estimates, b.estimates, strict=True)
    )


def replay_min(
    dataset: Path, tracks: list[Tracks], repeats: int, params: WindowParams | None = None
) -> tuple[np.ndarray, list[BackendRun]]:
    """Replay ``repeats`` times; the per-frame minima (ms) and the runs."""
    runs = [run_backend(dataset, tracks, params) for _ in range(repeats)]
    return np.min([r.backend_ms for r in runs], axis=0), runs


def measure(dataset: Path, repeats: int = 3, params: WindowParams | None = None) -> dict:
    """Capture the front end once, replay the back end ``repeats`` times; per-frame minima (module doc)."""
    online = run_backend(dataset, params=params)
    best, runs = replay_min(dataset, online.tracks, repeats, params)
    out = {"dataset": str(dataset), "repeats": repeats, **summarize(best, online.keyframe, online.solving)}
    out["frontend_online"] = ms_summary(online.frontend_ms)
    out["replay_reproduces_online_estimates"] = all(_same(online, r) for r in runs)
    return out


def _stack(run: BackendRun) -> dict[str, np.ndarray]:
    est = run.estimates
    return {
        "p_WB": np.array([e[0] for e in est]).reshape(-1, 3),
        "R_WB": np.array([e[1] for e in est]).reshape(-1, 3, 3),
        "cov": np.array([e[2] for e in est]).reshape(len(est), *((est[0][2].shape) if est else (0, 0))),
    }


def compare(a_path: Path, b_path: Path) -> dict:
    """Summaries of two saved replays, their ratios (b / a) and the largest estimate differences."""
    a, b = np.load(a_path), np.load(b_path)
    out = {}
    for name, r in (("a", a), ("b", b)):
        out[name] = summarize(r["best_ms"], r["keyframe"], r["solving"])
    out["ratio_b_over_a"] = {
        k: out["b"]["backend"][k] / out["a"]["backend"][k] for k in ("median_ms", "p99_ms", "mean_ms")
    }
    same_len = a["p_WB"].shape == b["p_WB"].shape
    out["estimates_bit_identical"] = bool(
        same_len and all(np.array_equal(a[k], b[k]) for k in ("p_WB", "R_WB", "cov"))
    )
    if same_len:
        out["max_abs_diff"] = {k: float(np.max(np.abs(a[k] - b[k]), initial=0.0)) for k in ("p_WB", "R_WB")}
        scale = np.maximum(np.abs(a["cov"]), 1e-300)
        out["max_rel_diff_cov"] = float(np.max(np.abs(a["cov"] - b["cov"]) / scale, initial=0.0))
    return out


def _params(settings: list[str]) -> WindowParams | None:
    """``WindowParams`` with ``field=value`` settings (the type of each field's default), or None."""
    if not settings:
        return None
    base, changes = WindowParams(), {}
    for item in settings:
        name, value = item.split("=", 1)
        kind = type(getattr(base, name))
        changes[name] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return replace(base, **changes)


def main() -> None:
    """Command line (module doc)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, nargs="?")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--capture", type=Path, help="write the front end's tracks here and exit")
    ap.add_argument("--tracks", type=Path, help="replay these captured tracks")
    ap.add_argument("--save", type=Path, help="with --tracks: the per-frame minima and estimates (.npz)")
    ap.add_argument("--compare", type=Path, nargs=2, help="two saved replays")
    ap.add_argument("--set", action="append", default=[], help="WindowParams field=value (int, float, bool)")
    a = ap.parse_args()
    params = _params(a.set)
    if a.compare:
        print(json.dumps(compare(*a.compare), indent=1))
        return
    if a.capture:
        online = run_backend(a.dataset)
        a.capture.write_bytes(pickle.dumps(online.tracks))
        print(json.dumps({"frames": len(online.tracks), "frontend_online": ms_summary(online.frontend_ms)}))
        return
    if a.tracks:
        tracks = pickle.loads(a.tracks.read_bytes())
        best, runs = replay_min(a.dataset, tracks, a.repeats, params)
        r0 = runs[0]
        if a.save:
            np.savez(a.save, best_ms=best, keyframe=r0.keyframe, solving=r0.solving, **_stack(r0))
        out = summarize(best, r0.keyframe, r0.solving)
        out["replays_agree"] = all(_same(r0, r) for r in runs[1:])
        print(json.dumps(out, indent=1))
        return
    print(json.dumps(measure(a.dataset, a.repeats, params), indent=1))


if __name__ == "__main__":
    main()
