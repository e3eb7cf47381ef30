"""Consistency on data the estimators model exactly: their own inconsistency, apart from the sensors'.

Records each scenario with the ``adis16448-white`` IMU (the ADIS densities and bias random walk, nothing
else: no turn-on bias, scale, misalignment or quantization) and evaluates both estimators on the recording's
simulated features (white pixel noise of ``--pixel-sigma``, projected from the true poses), each told exactly
that noise. Whatever NEES is left is the estimator's: its linearization, its marginalization, its
parametrization, not a noise model that does not describe the data. Prints one JSON object: a row per run
(position / orientation NEES anchored at the first pose, ATE) and the per-scenario means.

Usage::

    python benchmarks/nees_clean_data.py --recordings /tmp/clean --scenarios head-look-around --seeds 0-2
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from viotb.envs.data.eval_options import EvalOptions
from viotb.envs.data.evaluate import evaluate_dataset
from viotb.envs.data.record import record_scenario
from viotb.envs.tools.cli_common import seed_range
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.window_params import WindowParams

IMU_PRESET = "adis16448-white"


def options(estimator: str, pixel_sigma_px: float) -> EvalOptions:
    """The ``sim`` front end at ``pixel_sigma_px``, the estimator told that noise."""
    if estimator == "window":
        window = replace(WindowParams(), frontend="sim", pixel_sigma_px=pixel_sigma_px)
        return EvalOptions("window", "sim", window=window, sim_pixel_sigma_px=pixel_sigma_px)
    if estimator == "msckf":
        msckf = replace(MsckfParams(), frontend="sim", pixel_sigma_px=pixel_sigma_px)
        return EvalOptions("msckf", "sim", msckf=msckf, sim_pixel_sigma_px=pixel_sigma_px)
    raise ValueError(f"unknown estimator {estimator!r}; allowed: msckf, window")


def main() -> None:
    """Parse the arguments, record what is missing, evaluate, print JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recordings", type=Path, required=True, help="folder of SCENARIO-SEED recordings")
    ap.add_argument("--scenarios", default="head-look-around,figure8,hover")
    ap.add_argument("--estimators", default="msckf,window")
    ap.add_argument("--seeds", default="0-2", help="e.g. 0-4 or 0,3")
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--pixel-sigma", type=float, default=0.5, help="simulated pixel noise (px), also told")
    args = ap.parse_args()
    rows = []
    for scenario in args.scenarios.split(","):
        for seed in seed_range(args.seeds):
            rec = args.recordings / f"{scenario}-{seed}"
            if not rec.exists():
                record_scenario(scenario, rec, seed=seed, seconds=args.seconds, imu_preset=IMU_PRESET)
            for est in args.estimators.split(","):
                out = args.recordings / "eval" / f"{scenario}-{seed}-{est}"
                m = evaluate_dataset(rec, out, options(est, args.pixel_sigma), overwrite=True)
                keys = ("ate_posyaw_m", "nees_pos_mean", "nees_rot_mean", "diverged")
                rows.append(
                    {"estimator": est, "scenario": scenario, "seed": seed, **{k: m.get(k) for k in keys}}
                )
    summary = {}
    for key in dict.fromkeys(f"{r['estimator']}/{r['scenario']}" for r in rows):
        rs = [r for r in rows if f"{r['estimator']}/{r['scenario']}" == key]
        summary[key] = {
            k: float(np.mean([r[k] for r in rs])) for k in ("ate_posyaw_m", "nees_pos_mean", "nees_rot_mean")
        }
    print(
        json.dumps(
            {"imu_preset": IMU_PRESET, "pixel_sigma_px": args.pixel_sigma, "rows": rows, "mean": summary},
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
