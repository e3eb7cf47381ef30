"""Loop closures against the truth over many seeds: is any accepted closure wrong? (issue #14's benchmark).

For each seed: record ``SCENARIO`` (rendered, open loop; ``--scene`` swaps the room, e.g. the repetitive
``pillars``), evaluate it with the MSCKF on KLT with loop closure, and compare every accepted closure's
relative pose (``loop_closures.csv``: the query body in the match body frame) with the truth's
``T_WB(t_match)^-1 T_WB(t_query)`` from the recording's ground truth. Prints one JSON object: per seed the
closure count, the worst translation (m) and rotation (deg) error, ATE odometry / loop-closed / online, and
the totals (``false_closures``: closures outside ``--max-err-m`` / ``--max-err-deg``).

Usage::

    python benchmarks/loop_closure_truth.py long-loop --seeds 0-19 --seconds 60 --out /tmp/lc_bench
    python benchmarks/loop_closure_truth.py long-loop --scene pillars --seeds 0-4 --out /tmp/lc_pillars
    python benchmarks/loop_closure_truth.py line --seeds 0-4 --seconds 8 --out /tmp/lc_line   # no revisit
    python benchmarks/loop_closure_truth.py long-loop --seeds 0-19 --seconds 40 --frontend sim --out /tmp/lc

``--reclose`` (with recordings kept by an earlier ``--keep`` run) records nothing and runs no estimator: it
feeds the earlier run's odometry (``estimate_odometry_tum.txt``) to the current loop closer again, to check a
change of the closer on the same seeds in seconds instead of minutes (no blackout handling: health records
are not kept).

``--set SECTION.FIELD=VALUE`` (repeatable) overrides one loop-closure parameter for an A/B check, e.g.
``--set verification.weight_by_octave=false`` or ``--set verification.max_yaw_sigma_deg=1.0``.

``--sensor-model render`` gives the MSCKF the sensor model measured on the renders
(:meth:`MsckfParams.with_render_sensor_model`; KLT only).

``--frontend sim`` runs the estimator on the recording's simulated feature tracks (fast); the loop closer
still works on the rendered images, so the closures are the same kind as on KLT, only the odometry differs.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc import read_euroc
from viotb.envs.data.eval_options import EvalOptions
from viotb.envs.data.evaluate import evaluate_dataset
from viotb.envs.data.record import record_scenario
from viotb.envs.data.tum import read_tum
from viotb.envs.run.loop_glue import LoopOptions, apply_loop_closure, estimates_to_trajectory
from viotb.envs.scenarios.registry import get_scenario, register
from viotb.envs.tools.cli_common import seed_range
from viotb.vio.headset_metrics import interpolate_poses
from viotb.vio.lie import log_so3, quat_wxyz_to_rotmat
from viotb.vio.loop import LoopClosureParams
from viotb.vio.metrics import evaluate_trajectory
from viotb.vio.msckf_params import SENSOR_MODELS, MsckfParams
from viotb.vio.types import StateEstimate


def loop_params(settings: list[str]) -> LoopClosureParams:
    """Default loop-closure parameters with ``SECTION.FIELD=VALUE`` overrides (JSON values).

    Raises:
        ValueError: A setting that is not ``SECTION.FIELD=VALUE``, or names no parameter.
    """
    params = LoopClosureParams()
    for item in settings:
        key, sep, text = item.partition("=")
        section, dot, name = key.partition(".")
        if not (sep and dot) or not hasattr(params, section):
            raise ValueError(f"--set {item!r}: expected SECTION.FIELD=VALUE with a LoopClosureParams section")
        sub = getattr(params, section)
        if name not in {f.name for f in dataclasses.fields(sub)}:
            raise ValueError(f"--set {item!r}: {type(sub).__name__} has no field {name!r}")
        value = json.loads(text)
        params = dataclasses.replace(params, **{section: dataclasses.replace(sub, **{name: value})})
    return params


def closure_errors(dataset_dir: Path, csv_path: Path) -> list[tuple[float, float]]:
    """``(translation error m, rotation error deg)`` of every closure in ``csv_path`` against the truth."""
    gt = read_euroc(dataset_dir).groundtruth
    if gt is None:
        raise ValueError(f"{dataset_dir}: no ground truth to check closures against")
    R_gt = np.array([quat_wxyz_to_rotmat(q) for q in gt.quat_wxyz_WB])
    out = []
    with Path(csv_path).open() as f:
        for row in csv.DictReader(f):
            t = np.array([float(row["t_query_s"]), float(row["t_match_s"])])
            R, p = interpolate_poses(t, gt.t_s, R_gt, gt.p_WB)
            R_mq_true = R[1].T @ R[0]
            p_mq_true = R[1].T @ (p[0] - p[1])
            q_xyzw = [float(row[k]) for k in ("qx", "qy", "qz", "qw")]
            R_mq = quat_wxyz_to_rotmat(np.array([q_xyzw[3], *q_xyzw[:3]]))
            p_mq = np.array([float(row[k]) for k in "xyz"])
            rot_deg = float(np.degrees(np.linalg.norm(log_so3(R_mq_true.T @ R_mq))))
            out.append((float(np.linalg.norm(p_mq - p_mq_true)), rot_deg))
    return out


def reclose(dataset_dir: Path, eval_dir: Path, params: LoopClosureParams | None = None) -> dict:
    """Run the loop closer again on a kept recording with the odometry of an earlier evaluation.

    Rewrites ``eval_dir/loop_closures.csv``; returns the loop keys and ``ate_posyaw_m`` of the new final
    trajectory.
    """
    ds = read_euroc(dataset_dir)
    odo = read_tum(Path(eval_dir) / "estimate_odometry_tum.txt")
    estimates = [
        StateEstimate(float(t), quat_wxyz_to_rotmat(q), p.copy(), np.zeros(3))
        for t, q, p in zip(odo.t_s, odo.quat_wxyz_WB, odo.p_WB, strict=True)
    ]
    opts = LoopOptions(params or LoopClosureParams())
    final, res = apply_loop_closure(ds, estimates, [], opts, Path(eval_dir))
    res["ate_posyaw_m"] = evaluate_trajectory(estimates_to_trajectory(final), ds.groundtruth)["ate_posyaw_m"]
    return res


def main() -> None:
    """Run the seeds and print the JSON summary."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("--seeds", default="0-19")
    ap.add_argument("--seconds", type=float, default=None)
    ap.add_argument("--scene", default=None, help="Swap the scenario's scene (e.g. pillars).")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--max-err-m", type=float, default=0.05)
    ap.add_argument("--max-err-deg", type=float, default=1.0)
    ap.add_argument("--frontend", choices=("klt", "sim"), default="klt", help="The estimator's front end.")
    ap.add_argument("--keep", action="store_true", help="Keep the recordings.")
    ap.add_argument("--reclose", action="store_true", help="Rerun only the closer on kept recordings.")
    ap.add_argument("--set", action="append", default=[], help="SECTION.FIELD=VALUE parameter override.")
    ap.add_argument(
        "--sensor-model",
        default="default",
        choices=SENSOR_MODELS,
        help="The MSCKF's sensor model (MsckfParams.with_sensor_model; render: KLT only).",
    )
    args = ap.parse_args()
    params = loop_params(args.set)
    name = args.scenario
    if args.scene is not None:
        base = get_scenario(name)
        name = f"{name}-{args.scene}"
        register(dataclasses.replace(base, name=name, scene=args.scene), replace=True)
    rows = []
    for seed in seed_range(args.seeds):
        data, ev = args.out / f"{name}-{seed}" / "data", args.out / f"{name}-{seed}" / "eval"
        if args.reclose:
            res = reclose(data, ev, params)
        else:
            record_scenario(name, data, seed=seed, seconds=args.seconds, overwrite=True)
            msckf = MsckfParams().with_sensor_model(args.sensor_model)
            opts = EvalOptions(frontend=args.frontend, loop=LoopOptions(params), msckf=msckf)
            res = evaluate_dataset(data, ev, opts, overwrite=True)
        errs = closure_errors(data, ev / "loop_closures.csv")
        worst_m = max((e[0] for e in errs), default=0.0)
        worst_deg = max((e[1] for e in errs), default=0.0)
        bad = sum(e[0] > args.max_err_m or e[1] > args.max_err_deg for e in errs)
        rows.append(
            {
                "seed": seed,
                "closures": len(errs),
                "false_closures": bad,
                "worst_m": worst_m,
                "worst_deg": worst_deg,
                "ate_posyaw_odometry_m": res.get("ate_posyaw_odometry_m"),
                "ate_posyaw_m": res.get("ate_posyaw_m"),
                "ate_posyaw_online_m": res.get("ate_posyaw_online_m"),
                "return_to_start_err_m": res.get("return_to_start_err_m"),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
        if not (args.keep or args.reclose):
            shutil.rmtree(data)
    ratios = [r["ate_posyaw_m"] / r["ate_posyaw_odometry_m"] for r in rows if r["ate_posyaw_odometry_m"]]
    summary = {
        "scenario": name,
        "frontend": "as kept (--reclose)" if args.reclose else args.frontend,
        "set": args.set,
        "sensor_model": args.sensor_model,
        "seeds": len(rows),
        "closures": sum(r["closures"] for r in rows),
        "false_closures": sum(r["false_closures"] for r in rows),
        "worst_m": max(r["worst_m"] for r in rows),
        "worst_deg": max(r["worst_deg"] for r in rows),
        "ate_ratio_median": float(np.median(ratios)) if ratios else None,
        "ate_ratio_max": float(np.max(ratios)) if ratios else None,
        "runs": rows,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
