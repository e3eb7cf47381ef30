"""Consistency on rendered recordings (issue #13's benchmark): NEES and ATE per scenario and noise model.

Records (or reuses) KLT recordings of the scenarios, ``--seconds`` long at 320x240, one per seed, and
evaluates each with every requested model (``viotb eval``'s code path, :func:`evaluate_dataset`, monitor
on). Prints one JSON object: a row per run and, per model and scenario, the mean and range of the position
and orientation NEES (anchored at the first pose, :func:`viotb.vio.metrics.anchor_first_pose`) and of the
ATE. Models:

- ``msckf``, ``window``: the defaults (1 px white, 0.025 px^2/px walk for the MSCKF).
- ``msckf-render``: the KLT noise measured on the renders (:meth:`MsckfParams.with_render_klt_noise`).
- ``msckf-render-gyro``, ``msckf-render-gyro+accel``: and the IMU's scale/misalignment matrices estimated
  online (:attr:`MsckfParams.imu_intrinsics`), i.e. ``viotb eval --klt-noise render --imu-intrinsics ...``.
- ``msckf-sensor-render``: :meth:`MsckfParams.with_render_sensor_model` (``viotb eval --sensor-model
  render``): the above with both matrices and rotation-compensated clones.
- ``window-render``: :meth:`WindowParams.with_render_klt_noise`.
- ``window-sensor-render``: :meth:`WindowParams.with_render_sensor_model` (``viotb eval --estimator window
  --sensor-model render``): the render noise, both IMU matrices online, outliers at 5 sigmas.

Usage::

    python benchmarks/nees_rendered.py --recordings /tmp/nees --seeds 0-4
    python benchmarks/nees_rendered.py --recordings /tmp/nees --scenarios aggressive,hover \
        --models msckf,msckf-render-gyro+accel --seeds 0-2 --seconds 20
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from viotb.envs.data.eval_options import EvalOptions
from viotb.envs.data.evaluate import evaluate_dataset
from viotb.envs.data.record import record_scenario
from viotb.envs.tools.cli_common import seed_range
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.window_params import WindowParams

SCENARIOS = ("figure8", "circle", "aggressive", "hover", "head-fast-turns", "head-look-around", "head-walk")
"""Issue #13's set: the drone scenarios and the head motions."""

MODELS = (
    "msckf",
    "msckf-render",
    "msckf-render-gyro",
    "msckf-render-gyro+accel",
    "msckf-sensor-render",
    "window",
    "window-render",
    "window-sensor-render",
)


def options(model: str) -> EvalOptions:
    """The evaluation options of a model name (ValueError naming the allowed ones)."""
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; allowed: {', '.join(MODELS)}")
    if model.startswith("window"):
        window = {
            "window-render": WindowParams().with_render_klt_noise(),
            "window-sensor-render": WindowParams().with_render_sensor_model(),
        }.get(model)
        return EvalOptions("window", "klt", window=window)
    msckf = MsckfParams()
    if model == "msckf-sensor-render":
        return EvalOptions("msckf", "klt", msckf=msckf.with_render_sensor_model())
    if "render" in model:
        msckf = msckf.with_render_klt_noise()
    if "gyro" in model:
        msckf = replace(msckf, imu_intrinsics=model.split("render-")[1])
    return EvalOptions("msckf", "klt", msckf=msckf)


def summarize(rows: list[dict]) -> dict:
    """Per ``model/scenario``: runs, diverged, mean / min / max of ATE (cm) and of both NEES."""
    out: dict[str, dict] = {}
    for key in dict.fromkeys(f"{r['model']}/{r['scenario']}" for r in rows):
        rs = [r for r in rows if f"{r['model']}/{r['scenario']}" == key]
        entry: dict[str, float | int] = {"runs": len(rs), "diverged": sum(bool(r["diverged"]) for r in rs)}
        for name, scale in (("ate_posyaw_m", 100.0), ("nees_pos_mean", 1.0), ("nees_rot_mean", 1.0)):
            v = np.array([r[name] for r in rs], dtype=float) * scale
            label = "ate_cm" if name == "ate_posyaw_m" else name.removesuffix("_mean")
            entry[f"{label}_mean"] = float(np.mean(v))
            entry[f"{label}_min"] = float(np.min(v))
            entry[f"{label}_max"] = float(np.max(v))
        out[key] = entry
    return out


def main() -> None:
    """Parse the arguments, record what is missing, evaluate, print JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=Path, required=True, help="folder of SCENARIO-SEED recordings")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--models", default="msckf,msckf-sensor-render")
    ap.add_argument("--seeds", default="0-4", help="e.g. 0-4 or 0,3")
    ap.add_argument("--seconds", type=float, default=40.0)
    args = ap.parse_args()
    models = args.models.split(",")
    for model in models:
        options(model)
    keys = ("ate_posyaw_m", "nees_pos_mean", "nees_rot_mean", "ms_per_frame_median", "diverged")
    rows = []
    for scenario in args.scenarios.split(","):
        for seed in seed_range(args.seeds):
            rec = args.recordings / f"{scenario}-{seed}"
            if not (rec / "mav0").is_dir():
                record_scenario(scenario, rec, seed=seed, seconds=args.seconds)
            for model in models:
                with tempfile.TemporaryDirectory() as out:
                    m = evaluate_dataset(rec, Path(out), options(model))
                row = {"model": model, "scenario": scenario, "seed": seed}
                rows.append({**row, **{k: m.get(k) for k in keys}})
    print(json.dumps({"rows": rows, "summary": summarize(rows)}, indent=1))


if __name__ == "__main__":
    main()
