r"""Paired test of front-end options on the stereo headset look-around over many seeds (world lock, NEES).

Runs :func:`viotb.envs.run.headset.run_headset` (MSCKF, :data:`viotb.envs.run.headset.HEADSET_MSCKF` with
the given ``KltParams`` / ``StereoMatchParams`` fields replaced) for every option set and seed, the same
seeds for every set, so each seed pairs the sets on the same rendered images and IMU. Prints one JSON line
per run and, at the end, per option set the mean over seeds of the world lock, its max error and the
position NEES, and the paired differences against the first set (mean and how many seeds got worse).

Usage::

    python benchmarks/frontend_checks_seeds.py --seconds 10 --seeds 0-7 \\
        --set base --set zncc:klt.anchor_zncc_at_final_warp=False \\
        --set stereo:stereo.tracked_check_beyond_px=1.0
"""

from __future__ import annotations

import argparse
import ast
import json
from dataclasses import replace

import numpy as np

KEYS = ("world_lock_ate_mm", "max_err_mm", "nees_pos_mean", "ms_per_frame_median")


def parse_set(text: str) -> tuple[str, dict, dict]:
    """``NAME[:klt.F=V,stereo.F=V,...]`` -> ``(name, klt fields, stereo fields)``."""
    name, _, rest = text.partition(":")
    klt, stereo = {}, {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        group, _, fld = key.partition(".")
        {"klt": klt, "stereo": stereo}[group][fld] = ast.literal_eval(value)
    return name, klt, stereo


def run_one(seed: int, seconds: float, klt: dict, stereo: dict, scenario: str) -> dict:
    """One stereo MSCKF headset run with the options replaced; the metrics of ``KEYS``."""
    from viotb.envs.run.headset import HEADSET_MSCKF, HeadsetOptions, run_headset
    from viotb.envs.run.headset_report import headset_result

    msckf = replace(
        HEADSET_MSCKF, klt=replace(HEADSET_MSCKF.klt, **klt), stereo=replace(HEADSET_MSCKF.stereo, **stereo)
    )
    opts = HeadsetOptions(estimator="msckf", cameras=2, seconds=seconds, seed=seed, msckf=msckf)
    result = headset_result(run_headset(scenario, opts, None))
    return {k: result.get(k) for k in (*KEYS, "diverged")}


def main() -> None:
    """Command line: run every set on every seed, print the runs and the paired summary (JSON lines)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--seeds", default="0-7", help="A-B or a,b,c")
    ap.add_argument("--scenario", default="headset-look-around")
    ap.add_argument("--set", action="append", dest="sets", default=[], help="NAME[:klt.F=V,stereo.F=V]")
    args = ap.parse_args()
    if "-" in args.seeds:
        lo, hi = args.seeds.split("-")
        seeds = list(range(int(lo), int(hi) + 1))
    else:
        seeds = [int(s) for s in args.seeds.split(",")]
    sets = [parse_set(s) for s in (args.sets or ["base"])]
    table: dict[str, dict[int, dict]] = {name: {} for name, _, _ in sets}
    for seed in seeds:
        for name, klt, stereo in sets:
            row = run_one(seed, args.seconds, klt, stereo, args.scenario)
            table[name][seed] = row
            print(json.dumps({"set": name, "seed": seed, **row}), flush=True)
    base = sets[0][0]
    for name, _, _ in sets:
        summary: dict = {"summary": name, "seeds": len(seeds)}
        for key in KEYS[:3]:
            vals = np.array([np.nan if table[name][s][key] is None else table[name][s][key] for s in seeds])
            ref = np.array([np.nan if table[base][s][key] is None else table[base][s][key] for s in seeds])
            summary[f"{key}_mean"] = float(np.nanmean(vals))
            summary[f"{key}_max"] = float(np.nanmax(vals))
            summary[f"{key}_paired_diff_mean"] = float(np.nanmean(vals - ref))
            summary[f"{key}_worse_seeds"] = int(np.sum(vals > ref))
        print(json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
