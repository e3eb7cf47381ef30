"""Moving-start initialization over many seeds (issue #13's benchmark): time to initialize and scale error.

Each moving start of :data:`viotb.envs.run.init_check.MOVING_STARTS` (a motion of the library entered
mid-flight, sim front end) is run with the estimator until its first estimate, for every seed, and compared
with the truth (:func:`viotb.envs.run.init_check.check_initialization`). Prints one JSON object: the rows
and, per motion, the initialized fraction, the delay after the first image (median, max) and the worst
absolute scale error.

Usage::

    python benchmarks/init_moving_start.py --seeds 0-19
    python benchmarks/init_moving_start.py --seeds 0-4 --estimator window
    python benchmarks/init_moving_start.py --seeds 0-19 --motions hover,circle --max-delay-s 2
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from viotb.envs.run.init_check import MOVING_STARTS, moving_start_monte_carlo
from viotb.envs.tools.cli_common import seed_range


def summarize(rows: list[dict]) -> dict:
    """Per motion: runs, initialized, delays (median, max), worst scale and tilt errors, CPU per try."""
    out = {}
    for motion in dict.fromkeys(r["motion"] for r in rows):
        rs = [r for r in rows if r["motion"] == motion]
        ok = [r for r in rs if r["t_init_s"] is not None]
        delays = [r["delay_s"] for r in ok]
        out[motion] = {
            "runs": len(rs),
            "initialized": len(ok),
            "delay_s_median": float(np.median(delays)) if delays else None,
            "delay_s_max": float(np.max(delays)) if delays else None,
            "worst_scale_error": float(max(abs(r["scale_error"]) for r in ok)) if ok else None,
            "worst_tilt_error_deg": float(max(r["tilt_error_deg"] for r in ok)) if ok else None,
            "over_2pct": sum(1 for r in ok if not abs(r["scale_error"]) <= 0.02),
            "worst_scale_error_over_sigma": (
                float(max(abs(r["scale_error"]) / r["scale_sigma"] for r in ok)) if ok else None
            ),
            "cpu_per_try_s_median": float(np.nanmedian([r["cpu_per_try_s"] for r in rs])),
            "tries_median": float(np.median([r["dynamic_tries"] for r in rs])),
        }
    return out


def main() -> None:
    """Parse the arguments, run, print JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-4", help="e.g. 0-19 or 0,3,5")
    ap.add_argument("--estimator", default="msckf", choices=("msckf", "window"))
    ap.add_argument("--motions", default="", help="comma-separated subset of MOVING_STARTS (default: all)")
    ap.add_argument("--max-delay-s", type=float, default=5.0, help="give up this long after the first image")
    args = ap.parse_args()
    starts = MOVING_STARTS
    if args.motions:
        wanted = args.motions.split(",")
        unknown = sorted(set(wanted) - {m for m, _ in MOVING_STARTS})
        if unknown:
            ap.error(f"--motions: unknown {unknown}; known: {[m for m, _ in MOVING_STARTS]}")
        starts = tuple(s for s in MOVING_STARTS if s[0] in wanted)
    rows = moving_start_monte_carlo(
        seed_range(args.seeds), starts, estimator=args.estimator, max_delay_s=args.max_delay_s
    )
    print(json.dumps({"summary": summarize(rows), "rows": rows}, indent=1, default=float))


if __name__ == "__main__":
    main()
