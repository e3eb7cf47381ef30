"""Drift regression suite (``viotb regress``): fixed seeded runs compared with a committed baseline.

Short set (default): in-memory open-loop streams of :mod:`viotb.envs.scenarios.failures` (hover, circle, line;
no rendering) evaluated with the MSCKF and the simulated front end, plus one closed-loop ``fly-hover`` with
the simulated front end. ``full`` adds a fast circle, the 60 s long loop (simulated features), a moving start
(``moving-start-sim``: the stream entered mid-motion, so the MSCKF must initialize dynamically; its
``init_time_s`` is guarded too), and the
image path: a rendered 12 s ``figure8`` recording evaluated with the KLT front end (``figure8-klt``; and with
the sensor model measured on the renders, ``figure8-klt-render``, whose NEES guards its consistency, and the
window's, ``figure8-klt-window-render``) and a 20
s closed-loop ``fly-hover`` on rendered images (``fly-hover-klt``), and the circle with the sliding-window
optimizer (``circle-sim-window``).

The baseline holds the full set; a short run is compared on the short set's cases only. Every case is a
:class:`~viotb.envs.tools.sweep.runs.RunConfig` run by :func:`~viotb.envs.tools.sweep.runs.run_config`, the
engine of ``viotb sweep``, so a sweep over the same configuration gives the same numbers by construction.

Metrics per case: ``ate_m`` (4-DOF aligned RMS), ``final_err_m``, ``drift_pct`` (final error / path length),
``scale_error_pct`` (absolute), ``nees_pos`` (mean position NEES), and ``timing_ratio`` (ms per frame divided
by a reference workload -- a fixed NumPy matrix loop -- timed in the same process, so the machine's speed
cancels). Runs are deterministic for a seed, so accuracy tolerances are tight; timing is loose.

A metric regresses when ``value > baseline + abs_tol + rel_tol * |baseline|`` (all metrics are
"lower is better"); tolerances are stored per metric in the baseline JSON.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from viotb.envs.scenarios.streams import StreamConfig
from viotb.envs.tools.sweep.runs import RunConfig, run_config
from viotb.vio.msckf import MsckfParams
from viotb.vio.window_params import WindowParams

DEFAULT_BASELINE = Path(__file__).resolve().parents[2] / "benchmarks" / "regress_baseline.json"
"""The committed baseline."""

TOLERANCES = {
    "ate_m": {"rel": 0.05, "abs": 0.005},
    "final_err_m": {"rel": 0.10, "abs": 0.01},
    "drift_pct": {"rel": 0.10, "abs": 0.1},
    "scale_error_pct": {"rel": 0.10, "abs": 0.5},
    "nees_pos": {"rel": 0.25, "abs": 0.5},
    "timing_ratio": {"rel": 1.0, "abs": 0.5},
    "init_time_s": {"rel": 0.1, "abs": 0.2},
}
"""Default per-metric tolerances written into a new baseline."""

SHORT_CASES = {
    "hover-sim": StreamConfig(motion="hover", seconds=10.0, landmark_count=600),
    "circle-sim": StreamConfig(motion="circle", seconds=10.0, landmark_count=600),
    "line-sim": StreamConfig(motion="line", seconds=8.0, landmark_count=600),
}
FULL_CASES = {
    "circle-fast-sim": StreamConfig(motion="circle", seconds=10.0, speed_scale=1.5, landmark_count=600),
    "long-loop-sim": StreamConfig(motion="long-loop", seconds=60.0, landmark_count=600),
    "moving-start-sim": StreamConfig(motion="aggressive", seconds=12.0, landmark_count=600, start_at_s=4.0),
}
IMAGE_CASES = ("figure8-klt", "figure8-klt-render", "figure8-klt-window-render", "fly-hover-klt")
"""Full-set cases on rendered images."""
WINDOW_CASES = {"circle-sim-window": StreamConfig(motion="circle", seconds=10.0, landmark_count=600)}
"""Full-set cases run with the sliding-window optimizer instead of the MSCKF."""


def case_names(full: bool = False, fly_case: bool = True) -> tuple[str, ...]:
    """Names of the cases :func:`run_suite` runs for these options."""
    names = list(SHORT_CASES) + (list(FULL_CASES) if full else [])
    if fly_case:
        names.append("fly-hover-sim")
    if full:
        names += [*IMAGE_CASES, *WINDOW_CASES]
    return tuple(names)


def reference_ms() -> float:
    """Median wall time (ms) of a fixed NumPy workload (50 solves of a 60 x 60 system)."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(60, 60)) + 60.0 * np.eye(60)
    b = rng.normal(size=60)
    out = []
    for _ in range(15):
        t0 = time.perf_counter()
        for _ in range(50):
            np.linalg.solve(A, b)
        out.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(out))


def _overrides(params: MsckfParams, default: object, prefix: str = "msckf") -> tuple[tuple[str, object], ...]:
    """Dotted ``msckf.*`` overrides of the fields where ``params`` differs from the defaults (nested too)."""
    out: list[tuple[str, object]] = []
    for f in dataclasses.fields(params):
        value, base = getattr(params, f.name), getattr(default, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out.extend(_overrides(value, base, f"{prefix}.{f.name}"))
        elif value != base:
            out.append((f"{prefix}.{f.name}", value))
    return tuple(sorted(out, key=lambda kv: kv[0]))


def _stream_run(cfg: StreamConfig, seed: int, overrides: tuple, estimator: str = "msckf") -> RunConfig:
    """The sweep run of an open-loop stream case (mode ``stream``)."""
    stream = (("stream.landmark_count", cfg.landmark_count), ("stream.speed_scale", cfg.speed_scale))
    if cfg.start_at_s:
        stream += (("stream.start_at_s", cfg.start_at_s),)
    return RunConfig(
        scenario=cfg.motion,
        mode="stream",
        estimator=estimator,
        frontend="sim",
        seconds=cfg.seconds,
        seed=seed,
        params=tuple(sorted(stream + (overrides if estimator == "msckf" else ()), key=lambda kv: kv[0])),
    )


def _stream_case(run: RunConfig, ref_ms: float) -> dict:
    m = run_config(run)
    keys = ("ate_m", "final_err_m", "drift_pct", "scale_error_pct", "nees_pos")
    out = {**{k: m[k] for k in keys}, "timing_ratio": m["ms_per_frame"] / ref_ms, "diverged": m["diverged"]}
    if any(name == "stream.start_at_s" for name, _ in run.params):  # a moving start: when it initialized
        out["init_time_s"] = m["init_time_s"] if m["init_time_s"] is not None else float("inf")
    return out


def _recording_case(
    seed: int, ref_ms: float, params: MsckfParams | None = None, window: WindowParams | None = None
) -> dict:
    """``figure8`` rendered for 12 s, replayed with the KLT front end (mode ``record-eval``).

    ``params``: the MSCKF's settings (None: the defaults), as ``msckf.*`` overrides of the run; ``window``:
    replay with the window optimizer instead, its settings as ``window.*`` overrides.
    """
    overrides = _overrides(params, MsckfParams()) if params is not None else ()
    if window is not None:
        overrides = _overrides(window, WindowParams(), "window")
    m = run_config(
        RunConfig(
            scenario="figure8",
            mode="record-eval",
            estimator="msckf" if window is None else "window",
            frontend="klt",
            seconds=12.0,
            seed=seed,
            params=overrides,
        )
    )
    nan = float("nan")
    return {
        "ate_m": m.get("ate_posyaw_m", nan),
        "drift_pct": m.get("drift_pct", nan),
        "scale_error_pct": abs(m.get("scale_error_pct", nan)),
        "nees_pos": m.get("nees_pos_mean", nan),
        "timing_ratio": m["ms_per_frame_median"] / ref_ms,
        "diverged": bool(m["diverged"]),
    }


def _fly_case(seed: int, ref_ms: float, frontend: str = "sim", seconds: float = 15.0) -> dict:
    """``fly-hover`` (mode ``fly``): 15 s leave ~4 s of hover after ground init, takeoff and excitation."""
    m = run_config(
        RunConfig(
            scenario="fly-hover", mode="fly", estimator="msckf", frontend=frontend, seconds=seconds, seed=seed
        )
    )
    wall_s = m["seconds"] / m["realtime_factor"] if m["realtime_factor"] else float("nan")
    ms = wall_s * 1e3 / max(m["frames_delivered"], 1)
    nan = float("nan")
    return {
        "ate_m": m["ate_posyaw_m"] if m["ate_posyaw_m"] is not None else nan,
        "final_err_m": m["max_err_m"] if m["max_err_m"] is not None else nan,
        "hover_rms_m": m["hover_rms_m"] if m["hover_rms_m"] is not None else nan,
        "timing_ratio": ms / ref_ms,
        "diverged": bool(m["diverged"]),
    }


def run_suite(
    full: bool = False,
    seed: int = 0,
    params: MsckfParams | None = None,
    fly_case: bool = True,
    only: tuple[str, ...] | None = None,
) -> dict:
    """Run the fixed cases; returns ``{"reference_ms", "cases": {name: metrics}}``.

    Args:
        full: Add the full-set cases.
        seed: Seed of every case.
        params: MSCKF settings (a deliberately degraded one makes the suite fail; tests use this).
        fly_case: Include the closed-loop ``fly-hover`` case.
        only: Run only these open-loop cases (None = all of the set).
    """
    prm = params if params is not None else MsckfParams()
    overrides = _overrides(prm, MsckfParams())
    ref = reference_ms()
    cases = dict(SHORT_CASES)
    if full:
        cases.update(FULL_CASES)
    if only is not None:
        cases = {k: v for k, v in cases.items() if k in only}
    out = {name: _stream_case(_stream_run(cfg, seed, overrides), ref) for name, cfg in cases.items()}
    if fly_case:
        out["fly-hover-sim"] = _fly_case(seed, ref)
    if full and only is None:
        out["figure8-klt"] = _recording_case(seed, ref)
        out["figure8-klt-render"] = _recording_case(seed, ref, MsckfParams().with_render_sensor_model())
        window_render = WindowParams().with_render_sensor_model()
        out["figure8-klt-window-render"] = _recording_case(seed, ref, window=window_render)
        out["fly-hover-klt"] = _fly_case(seed, ref, frontend="klt", seconds=20.0)
        for name, cfg in WINDOW_CASES.items():
            out[name] = _stream_case(_stream_run(cfg, seed, (), estimator="window"), ref)
    return {"reference_ms": ref, "seed": seed, "cases": out}


def load_baseline(path: Path | str) -> dict:
    """Read a baseline JSON (FileNotFoundError / ValueError naming the file)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"regress baseline {p} not found (create it with `viotb regress --update`)")
    try:
        data = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"regress baseline {p}: invalid JSON ({exc})") from None
    for key in ("cases", "tolerances"):
        if key not in data:
            raise ValueError(f"regress baseline {p}: missing field {key!r}")
    return data


def compare(result: dict, baseline: dict, cases: tuple[str, ...] | None = None) -> list[dict]:
    """Rows ``{case, metric, value, baseline, limit, ok}`` for every metric present in both.

    Args:
        result: A :func:`run_suite` output.
        baseline: A :func:`load_baseline` output.
        cases: Compare only these baseline cases (None: all of them).

    A NaN value where the baseline is finite, a divergence the baseline did not have, and a missing case
    all fail.
    """
    rows = []
    tol = baseline["tolerances"]
    for case, base in baseline["cases"].items():
        if cases is not None and case not in cases:
            continue
        cur = result["cases"].get(case)
        if cur is None:
            rows.append(
                {
                    "case": case,
                    "metric": "(missing)",
                    "value": None,
                    "baseline": None,
                    "limit": None,
                    "ok": False,
                }
            )
            continue
        if cur.get("diverged") and not base.get("diverged"):
            rows.append(
                {
                    "case": case,
                    "metric": "diverged",
                    "value": True,
                    "baseline": False,
                    "limit": False,
                    "ok": False,
                }
            )
        for metric, b in base.items():
            if metric == "diverged" or metric not in tol or metric not in cur:
                continue
            v = cur[metric]
            if b is None or not np.isfinite(b):
                continue
            limit = b + tol[metric]["abs"] + tol[metric]["rel"] * abs(b)
            ok = v is not None and bool(np.isfinite(v)) and v <= limit
            rows.append({"case": case, "metric": metric, "value": v, "baseline": b, "limit": limit, "ok": ok})
    return rows


def write_baseline(path: Path | str, result: dict, tolerances: dict | None = None) -> None:
    """Write ``result`` as the new baseline (deliberate: ``viotb regress --update``)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    data = {
        "note": "viotb regress baseline; metrics are lower-is-better; limit = base + abs + rel * |base|",
        "seed": result["seed"],
        "reference_ms": result["reference_ms"],
        "tolerances": tolerances if tolerances is not None else TOLERANCES,
        "cases": result["cases"],
    }
    p.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")


def regress(
    baseline: Path | str = DEFAULT_BASELINE,
    update: bool = False,
    full: bool = False,
    params: MsckfParams | None = None,
) -> tuple[bool, list[dict], dict]:
    """Run the suite and compare (or rewrite the baseline when ``update``).

    Returns:
        ``(passed, rows, result)``.
    """
    if update and not full:
        raise ValueError("regress --update rewrites the whole baseline: run it with --full")
    result = run_suite(full=full, params=params)
    if update:
        write_baseline(baseline, result)
        return True, [], result
    rows = compare(result, load_baseline(baseline), case_names(full))
    return all(r["ok"] for r in rows), rows, result
