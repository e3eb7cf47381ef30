"""The README's headset table: every head scenario, mono against stereo, over seeds (issue #12's benchmark).

Runs :func:`viotb.envs.run.headset.run_headset` for each head scenario, camera count and seed, and prints one
JSON object (``rows``: per scenario and camera count the mean over seeds of each metric, and per seed the
raw values) followed, with ``--markdown``, by the Markdown table the README carries. The mean position NEES
over ``S`` seeds comes with the two-sided 95 % band of a consistent filter, ``chi2(3 S) / S`` at each frame
(Bar-Shalom's average NEES test over Monte-Carlo runs).

Usage::

    python benchmarks/headset_table.py --frontend sim --seeds 0-2 --markdown
    python benchmarks/headset_table.py --frontend klt --scenarios headset-look-around --cameras 2 --seeds 0
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.stats import chi2
from viotb.envs.run.headset import HeadsetOptions, run_headset
from viotb.envs.run.headset_report import METRIC_KEYS, headset_result
from viotb.envs.scenarios.head_catalog import head_scenarios
from viotb.envs.tools.cli_common import seed_range
from viotb.envs.tools.jsonout import dumps_strict

COLUMNS = (*METRIC_KEYS, "nees_pos_mean", "ms_per_frame_median", "ms_per_frame_p99")


def nees_band(n_seeds: int, dof: int = 3, level: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the mean NEES of ``n_seeds`` consistent runs: ``chi2(dof n) / n`` quantiles."""
    a = (1.0 - level) / 2.0
    return (
        float(chi2.ppf(a, dof * n_seeds) / n_seeds),
        float(chi2.ppf(1.0 - a, dof * n_seeds) / n_seeds),
    )


def _mean(values: list) -> float | None:
    finite = [float(v) for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(finite)) if finite else None


def _fmt(v: float | None, digits: int) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def markdown(rows: list[dict]) -> str:
    """The README table: one line per scenario and camera count (means over seeds)."""
    out = [
        "| scenario | cameras | jitter pos / rot | world-lock ATE / max | pred p95 pos / rot | drift "
        "| NEES pos (band) | ms/frame median / p99 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        m = r["mean"]
        band = r["nees_band"]
        pred = (
            "n/a (no turn > 150 deg/s)"
            if m["pred_err_pos_mm_p95"] is None
            else f"{m['pred_err_pos_mm_p95']:.2f} mm / {m['pred_err_rot_deg_p95']:.3f} deg"
        )
        path_m = _mean([p["path_length_m"] for p in r["per_seed"]]) or 0.0
        drift = f"{_fmt(m['drift_pct'], 1)} %" if path_m >= 1.0 else f"({1e3 * path_m:.0f} mm path)"
        out.append(
            f"| `{r['scenario']}` | {r['cameras']} "
            f"| {_fmt(m['jitter_pos_mm'], 2)} mm / {_fmt(m['jitter_rot_deg'], 3)} deg "
            f"| {_fmt(m['world_lock_ate_mm'], 1)} / {_fmt(m['max_err_mm'], 1)} mm "
            f"| {pred} | {drift} "
            f"| {_fmt(m['nees_pos_mean'], 1)} ({band[0]:.1f}-{band[1]:.1f}) "
            f"| {_fmt(m['ms_per_frame_median'], 0)} / {_fmt(m['ms_per_frame_p99'], 0)} |"
        )
    return "\n".join(out)


def main() -> None:
    """Run the table and print it (JSON, then Markdown with ``--markdown``)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frontend", default="sim", choices=("sim", "klt"))
    ap.add_argument("--estimator", default="msckf")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--cameras", default="1,2", help="comma-separated camera counts")
    ap.add_argument("--scenarios", default="", help="comma-separated names (default: every headset-*)")
    ap.add_argument("--seconds", type=float, default=None, help="override every scenario's duration")
    ap.add_argument("--imu", default=None, help="IMU preset (default: the scenario's)")
    ap.add_argument("--gyro-noise-inflation", type=float, default=None)  # None: the headset runner's
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()

    names = [s for s in args.scenarios.split(",") if s] or [s.name for s in head_scenarios()]
    seeds = seed_range(args.seeds)
    rows = []
    for name in names:
        for cams in (int(c) for c in args.cameras.split(",")):
            per_seed = []
            for seed in seeds:
                opts = HeadsetOptions(
                    estimator=args.estimator,
                    cameras=cams,
                    frontend=args.frontend,
                    seed=seed,
                    seconds=args.seconds,
                    imu_preset=args.imu,
                    gyro_noise_inflation=args.gyro_noise_inflation,
                )
                res = headset_result(run_headset(name, opts))
                per_seed.append({k: res.get(k) for k in (*COLUMNS, "diverged", "path_length_m")})
            rows.append(
                {
                    "scenario": name,
                    "cameras": cams,
                    "seeds": seeds,
                    "mean": {k: _mean([p[k] for p in per_seed]) for k in COLUMNS},
                    "nees_band": nees_band(len(seeds)),
                    "per_seed": per_seed,
                }
            )
    print(
        dumps_strict({"frontend": args.frontend, "estimator": args.estimator, "imu": args.imu, "rows": rows})
    )
    if args.markdown:
        print(markdown(rows))


if __name__ == "__main__":
    main()
