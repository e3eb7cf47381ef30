"""Monte-Carlo sweeps on Ray (``viotb sweep``, ``viotb sweep-report``).

The public API: :func:`run_sweep` (a spec to a Parquet table, resumable), :func:`run_config` (one run, no
Ray), :func:`load_spec` / :func:`parse_spec`, :func:`sweep_report`. Heavy modules (ray, pyarrow, pandas,
matplotlib, the simulator) are imported only when a function needs them.
"""

from viotb.envs.tools.sweep.engine import SweepInterrupted, SweepProgress, SweepResult, run_sweep
from viotb.envs.tools.sweep.report import sweep_report
from viotb.envs.tools.sweep.runs import RunConfig, run_config
from viotb.envs.tools.sweep.spec import SpecError, SweepSpec, load_spec, parse_spec

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
