"""A second run in a saved map: does it agree with the first run's frame? (issue #14's map-reuse target).

Run 1 (``--map-seed``) closes its loops and saves its map; run 2 (``--run-seed``) starts in that map with its
odometry moved by ``--offset-yaw-deg`` / ``--offset-m`` (an arbitrary odometry frame) and localizes into it.
Both replay the odometry that an earlier ``loop_closure_truth.py --keep`` run wrote
(``estimate_odometry_tum.txt``), so only the loop closer runs (seconds).

Reference for a run-2 pose at true position ``p``: where run 1's map puts the same true place. For each of
run 1's keyframes within ``--radius-m`` of ``p`` (true positions), its map position plus the true offset
``p - p_true_k`` rotated by its map-vs-true yaw; averaged. Prints one JSON object: the relocalization time
and, from then on, the median / p95 / max distance and the fraction within 3 cm, for the final (written)
trajectory and the online one.

Usage::

    python benchmarks/loop_map_agreement.py /tmp/lcb/ll --scenario long-loop --map-seed 0 --run-seed 1
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc import read_euroc
from viotb.envs.data.tum import read_tum
from viotb.envs.run.loop_glue import LoopOptions, run_loop_closure
from viotb.vio.headset_metrics import interpolate_poses
from viotb.vio.lie import quat_wxyz_to_rotmat, rotz
from viotb.vio.loop.frames import heading_rad
from viotb.vio.types import StateEstimate


def _estimates(eval_dir: Path, yaw_rad: float = 0.0, offset_m: np.ndarray | None = None):
    odo = read_tum(eval_dir / "estimate_odometry_tum.txt")
    R_off, p_off = rotz(yaw_rad), np.zeros(3) if offset_m is None else offset_m
    return [
        StateEstimate(float(t), R_off @ quat_wxyz_to_rotmat(q), R_off @ p + p_off, np.zeros(3))
        for t, q, p in zip(odo.t_s, odo.quat_wxyz_WB, odo.p_WB, strict=True)
    ]


def _truth(ds, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gt = ds.groundtruth
    R_gt = np.array([quat_wxyz_to_rotmat(q) for q in gt.quat_wxyz_WB])
    return interpolate_poses(np.asarray(t_s, dtype=float), gt.t_s, R_gt, gt.p_WB)


def map_reference(ds1, closer1, p_true: np.ndarray, radius_m: float) -> np.ndarray:
    """Where run 1's map puts each true position ``p_true`` (M, 3); NaN rows where no keyframe is near."""
    kfs = [k for k in closer1.db.keyframes if k.p_WB_map is not None]
    R_t, p_t = _truth(ds1, np.array([k.t_s for k in kfs]))
    axis = closer1.heading_axis_B
    dyaw = np.array(
        [heading_rad(k.R_WB_map, axis) - heading_rad(R, axis) for k, R in zip(kfs, R_t, strict=True)]
    )
    p_map = np.array([k.p_WB_map for k in kfs])
    out = np.full((len(p_true), 3), np.nan)
    for i, p in enumerate(p_true):
        near = np.flatnonzero(np.linalg.norm(p_t - p, axis=1) < radius_m)
        if len(near):
            out[i] = np.mean([p_map[k] + rotz(dyaw[k]) @ (p - p_t[k]) for k in near], axis=0)
    return out


def _stats(err_m: np.ndarray) -> dict:
    err_m = err_m[np.isfinite(err_m)]
    return {
        "median_m": float(np.median(err_m)),
        "p95_m": float(np.percentile(err_m, 95)),
        "max_m": float(np.max(err_m)),
        "within_3cm": float(np.mean(err_m <= 0.03)),
        "frames": len(err_m),
    }


def main() -> None:
    """Run both and print the JSON summary."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="--out of a loop_closure_truth.py --keep run")
    ap.add_argument("--scenario", default="long-loop")
    ap.add_argument("--map-seed", type=int, default=0)
    ap.add_argument("--run-seed", type=int, default=1)
    ap.add_argument("--offset-yaw-deg", type=float, default=35.0)
    ap.add_argument("--offset-m", type=float, nargs=3, default=(1.2, -0.9, 0.0))
    ap.add_argument("--radius-m", type=float, default=0.4)
    args = ap.parse_args()
    d1, d2 = (args.root / f"{args.scenario}-{s}" for s in (args.map_seed, args.run_seed))
    ds1, ds2 = read_euroc(d1 / "data"), read_euroc(d2 / "data")
    map_path = args.root / f"map-{args.map_seed}.npz"
    run1 = run_loop_closure(ds1, _estimates(d1 / "eval"), [], LoopOptions(map_out=map_path))
    est2 = _estimates(d2 / "eval", np.deg2rad(args.offset_yaw_deg), np.array(args.offset_m))
    run2 = run_loop_closure(ds2, est2, [], replace(LoopOptions(), map_in=map_path))
    relocs = [c.t_query_s for c in run2.closer.run_closures if c.relocalization]
    out: dict = {"map_seed": args.map_seed, "run_seed": args.run_seed, "relocalized_at_s": None}
    if relocs:
        t0 = relocs[0]
        t = np.array([e.t_s for e in est2])
        keep = t >= t0
        _, p_true = _truth(ds2, t[keep])
        ref = map_reference(ds1, run1.closer, p_true, args.radius_m)
        out["relocalized_at_s"] = t0
        for name, ests in (("final", run2.final), ("online", run2.online)):
            p = np.array([e.p_WB for e in ests])[keep]
            out[name] = _stats(np.linalg.norm(p - ref, axis=1))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
