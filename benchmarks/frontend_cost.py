"""CPU cost of the KLT front end per camera frame on a recording, and a fingerprint of its tracks.

Runs the front end the MSCKF builds (:class:`viotb.vio.frontend.KltTracker`, wrapped in
:class:`viotb.vio.frontend_stereo.StereoTracker` when the recording has ``cam1`` and ``--cameras 2``) over
every frame of a EuRoC folder (``viotb record ...``), images decoded beforehand, and times each ``process``
call in process CPU time (``time.process_time``, all threads) and wall time. With ``--repeats R`` the whole
sequence is run R times with fresh trackers (the work per frame is the same in every repeat) and each
frame's minimum is taken, which removes most of the load of a shared machine. The JSON also gives the number
of observations and a digest of every frame's ids and pixels, so two versions of the code can be compared
for identical tracks (same digest) or not (then ``benchmarks/klt_track_error.py`` and the estimator's
accuracy say what moved).

Only the public front-end API is used, so the same script times any checkout: run it with the import path
of that checkout (``PYTHONPATH``).

Usage::

    python benchmarks/frontend_cost.py RECORDING_DIR [--cameras 1|2] [--repeats 3] [--max-frames N]
        [--klt FIELD=VALUE ...] [--stereo FIELD=VALUE ...] [--opencv-threads N] [--per-frame-out F.npy]
        [--profile] [--json]
"""

from __future__ import annotations

import argparse
import ast
import cProfile
import hashlib
import json
import pstats
import time
from pathlib import Path

import numpy as np


def load_frames(rec: Path, cameras: int, max_frames: int | None) -> tuple[object, list]:
    """The recording and its frames as ``CameraFrame`` with decoded images (cam1 where ``cameras`` is 2)."""
    from viotb.envs.data.euroc import load_image, read_euroc
    from viotb.vio.types import CameraFrame

    ds = read_euroc(rec)
    n = len(ds) if max_frames is None else min(len(ds), max_frames)
    frames = []
    for k in range(n):
        right = None
        if cameras == 2:
            j = ds.right_index(k)
            right = None if j is None else load_image(ds, j, camera=1)
        frames.append(CameraFrame(float(ds.cam_t_s[k]), image=load_image(ds, k), image_right=right))
    return ds, frames


def make_tracker(ds: object, cameras: int, klt: dict | None = None, stereo: dict | None = None) -> object:
    """The front end the MSCKF builds: ``MsckfParams().klt`` and ``.stereo``, with ``klt`` / ``stereo`` set.

    (Before session 10 the stereo settings were ``StereoMatchParams()``'s, a 21 px window on 3 levels,
    not the MSCKF's 15 px on 2.)
    """
    from dataclasses import replace

    from viotb.vio.frontend import KltTracker
    from viotb.vio.frontend_stereo import make_stereo_frontend
    from viotb.vio.msckf_params import MsckfParams

    defaults = MsckfParams()
    mono = KltTracker(ds.calib.camera, replace(defaults.klt, **(klt or {})))
    right = ds.calib_right if cameras == 2 else None
    return make_stereo_frontend(mono, ds.calib, right, replace(defaults.stereo, **(stereo or {})))


def _settings(items: list[str]) -> dict:
    """``["name=value", ...]`` -> ``{name: value}``, values read as Python literals."""
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        out[name] = ast.literal_eval(value)
    return out


def run_once(
    ds: object, frames: list, cameras: int, klt: dict | None = None, stereo: dict | None = None
) -> tuple[np.ndarray, list[str], np.ndarray, int, np.ndarray]:
    """One pass: per-frame CPU (s), digests, (cam0, cam1) observation counts, cam0 tracks, wall (s).

    CPU is the process's (``time.process_time``: every thread, OpenCV's and the tracker's worker
    (``KltParams.parallel_anchoring``) included; the front end is the only work of the process); the wall
    time is the latency of the frame.
    """
    tracker = make_tracker(ds, cameras, klt, stereo)
    cpu = np.zeros(len(frames))
    wall = np.zeros(len(frames))
    digests, counts = [], np.zeros((len(frames), 2), dtype=int)
    seen: set[int] = set()
    for k, frame in enumerate(frames):
        t0, w0 = time.process_time(), time.perf_counter()
        tr = tracker.process(frame, frame.t_s)
        cpu[k], wall[k] = time.process_time() - t0, time.perf_counter() - w0
        h = hashlib.sha1()
        for arr in (tr.ids, tr.uv_px, tr.ids_right, tr.uv_px_right):
            h.update(np.ascontiguousarray(arr).tobytes())
        digests.append(h.hexdigest())
        counts[k] = (len(tr.ids), len(tr.ids_right))
        seen.update(tr.ids.tolist())
    return cpu, digests, counts, len(seen), wall


def main() -> None:
    """Command line: print the per-frame CPU statistics (and the tracks' digest) of one checkout."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--cameras", type=int, default=2, choices=(1, 2))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--profile", action="store_true", help="cProfile one extra pass, print the top 25")
    ap.add_argument("--opencv-threads", type=int, default=None, help="cv2.setNumThreads (default: OpenCV's)")
    ap.add_argument("--klt", action="append", default=[], help="KltParams field=value (repeatable)")
    ap.add_argument("--stereo", action="append", default=[], help="StereoMatchParams field=value")
    ap.add_argument("--per-frame-out", type=Path, default=None, help="save the per-frame minima (ms), .npy")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.opencv_threads is not None:
        import cv2

        cv2.setNumThreads(args.opencv_threads)
    ds, frames = load_frames(args.recording, args.cameras, args.max_frames)
    klt, stereo = _settings(args.klt), _settings(args.stereo)
    cpus, walls, digest_sets = [], [], []
    for _ in range(args.repeats):
        cpu, digests, counts, starts, wall = run_once(ds, frames, args.cameras, klt, stereo)
        cpus.append(cpu)
        walls.append(wall)
        digest_sets.append(digests)
    per_frame_min_ms = 1e3 * np.min(np.stack(cpus), axis=0)
    if args.per_frame_out is not None:
        np.save(args.per_frame_out, per_frame_min_ms)
    whole = hashlib.sha1("".join(digest_sets[0]).encode()).hexdigest()
    import viotb.vio

    out = {
        "code": str(Path(viotb.vio.__file__).resolve().parent),
        "recording": str(args.recording),
        "cameras": args.cameras,
        "klt": klt,
        "stereo": stereo,
        "frames": len(frames),
        "repeats": args.repeats,
        "opencv_threads": args.opencv_threads,
        "ms_per_frame_median": float(np.median(per_frame_min_ms)),
        "ms_per_frame_mean": float(np.mean(per_frame_min_ms)),
        "ms_per_frame_p99": float(np.percentile(per_frame_min_ms, 99)),
        "wall_ms_per_frame_median": float(np.median(1e3 * np.min(np.stack(walls), axis=0))),
        "ms_per_frame_median_each_repeat": [float(np.median(1e3 * c)) for c in cpus],
        "obs_cam0_mean": float(counts[:, 0].mean()),
        "obs_cam1_mean": float(counts[:, 1].mean()),
        "track_starts_cam0": starts,
        "deterministic": all(d == digest_sets[0] for d in digest_sets),
        "tracks_digest": whole,
    }
    if args.profile:
        prof = cProfile.Profile(time.thread_time)
        prof.enable()
        run_once(ds, frames, args.cameras, klt, stereo)
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    print(json.dumps(out, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
