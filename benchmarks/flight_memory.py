"""Peak RSS of a closed-loop flight against its length (issue #15: a 10-minute flight within 10 % of 1 min).

Each flight runs in a fresh interpreter (``fly-hover``, ground-truth estimator, simulated features by
default), which reports its peak resident set size (``getrusage``'s ``ru_maxrss``) after ``fly`` returns,
metrics included.

Usage::

    python benchmarks/flight_memory.py [--seconds 60 600] [--estimator ground-truth] [--frontend sim]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

_CHILD = """
import json, resource, sys
from viotb.envs.run.fly import fly
metrics, _ = fly("fly-hover", sys.argv[1], float(sys.argv[2]), 0, sys.argv[3])
print(json.dumps({"peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                  "ate_posyaw_m": metrics["ate_posyaw_m"]}))
"""


def peak_rss_mb(seconds: float, estimator: str = "ground-truth", frontend: str = "sim") -> dict:
    """Peak RSS (MB, Linux ``ru_maxrss`` in KiB / 1024) and ATE of one flight in a fresh interpreter."""
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, estimator, str(seconds), frontend],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    """Fly each length once and print one JSON object with the ratios to the first."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, nargs="+", default=[60.0, 600.0])
    parser.add_argument("--estimator", default="ground-truth")
    parser.add_argument("--frontend", default="sim")
    args = parser.parse_args()
    runs = {str(s): peak_rss_mb(s, args.estimator, args.frontend) for s in args.seconds}
    first = runs[str(args.seconds[0])]["peak_rss_mb"]
    for r in runs.values():
        r["over_first"] = r["peak_rss_mb"] / first
    print(json.dumps(runs))


if __name__ == "__main__":
    main()
