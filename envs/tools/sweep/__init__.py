"""Monte-Carlo sweeps on Ray (``viotb sweep``, ``viotb sweep-report``).

The public API: :func:`run_sweep` (a spec to a Parquet table, resumable), :func:`run_config` (one run, no
Ray), :func:`load_spec` / :func:`parse_spec`, :func:`sweep_report`. Heavy modules (ray, pyarrow, pandas,
matplotlib, the simulator) are imported only when a function needs them.

How ``viotb regress`` can run through this engine (not done here; regress is unchanged):

1. Each case becomes a :class:`RunConfig`. ``figure8-klt`` is ``RunConfig(mode="record-eval",
   scenario="figure8", seconds=12.0, estimator="msckf", frontend="klt", seed=seed)``: the same
   ``record_scenario`` + ``evaluate_dataset`` calls as ``regress._recording_case``, whose metrics come back
   under the same names (``ate_posyaw_m``, ``drift_pct``, ``scale_error_pct``, ``nees_pos_mean``,
   ``ms_per_frame_median``, ``diverged``). ``fly-hover-sim`` / ``fly-hover-klt`` are ``RunConfig(mode="fly",
   scenario="fly-hover", seconds=15.0 / 20.0, frontend="sim" / "klt", seed=seed)``, giving ``ate_posyaw_m``,
   ``max_err_m``, ``hover_rms_m`` and ``diverged``; ms per frame is ``wall_s * 1e3 / frames_delivered``.
   The degraded ``params`` of the regress tests become overrides: ``{f"msckf.{name}": value}`` for each
   field that differs from ``MsckfParams()``.
2. The open-loop stream cases (``hover-sim``, ``circle-sim``, ``line-sim``, ``circle-fast-sim``,
   ``long-loop-sim``, ``circle-sim-window``) need a third mode, ``stream``, in ``runs.py``:
   ``synthesize_stream(StreamConfig(motion, seconds, speed_scale, landmark_count), seed)`` and ``run_stream``,
   with the metrics of ``regress._stream_case``. Make that function public (``stream_metrics``) when the
   files move, and call it from ``runs.py``.
3. ``run_suite`` then runs the rows. For CI, run them in-process: ``engine.execute_run(cfg.as_dict(), {})``
   for each case. For a parallel run, use ``run_sweep({"fixed": ..., "grid": ..., "seeds": [seed]}, tmp,
   workers=N)`` and read the Parquet table. Either way it maps ``row[metric]`` into ``{"cases": {name:
   metrics}}`` (``scale_error_pct`` made absolute, ``timing_ratio = ms_per_frame_median / reference_ms()``),
   and ``compare`` / the baseline stay as they are. The slow Monte-Carlo tests call ``run_sweep`` on a
   spec dict in the same way, and assert on the DataFrame.
"""

from __future__ import annotations

import importlib

# The names load on first use (PEP 562): ``viotb --help`` imports ``sweep.cli``, which runs this file, and
# the engine pulls in the evaluation stack (scipy.stats, the estimators, MuJoCo): about 3 s at import.
_HOMES = {
    "SweepInterrupted": "engine",
    "SweepProgress": "engine",
    "SweepResult": "engine",
    "run_sweep": "engine",
    "sweep_report": "report",
    "RunConfig": "runs",
    "run_config": "runs",
    "SpecError": "spec",
    "SweepSpec": "spec",
    "load_spec": "spec",
    "parse_spec": "spec",
}


def __getattr__(name: str):
    """Import a public name from its module on first access."""
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{home}"), name)


__all__ = [
    "RunConfig",
    "SpecError",
    "SweepInterrupted",
    "SweepProgress",
    "SweepResult",
    "SweepSpec",
    "load_spec",
    "parse_spec",
    "run_config",
    "run_sweep",
    "sweep_report",
]
