"""``viotb failures``: each failure of the catalog and its fix, error-vs-time plots, what the monitor said."""

from __future__ import annotations

from pathlib import Path

from viotb.envs.run.failure_runner import RunResult, run_stream
from viotb.envs.scenarios.failures import FAILURES
from viotb.envs.scenarios.streams import synthesize_stream


def _plot(path: Path, title: str, runs: dict[str, RunResult]) -> None:
    """Position error vs time of each run (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for label, r in runs.items():
        ax.plot(r.t_s, r.err_m, label=label)
        for c in r.run.monitor.report():
            ax.axvline(c.t_s_first, ls=":", lw=0.8, color="gray")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("position error (m, 4-DOF aligned)")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def failure_report(name: str, out_dir: Path | str, seed: int = 0, severity: float = 1.0) -> dict:
    """Run failure ``name`` and its fix, plot error vs time and report what the monitor said.

    Args:
        name: A key of :data:`FAILURES`.
        out_dir: Folder for ``<name>_error.png`` (created).
        seed: Seed of the stream.
        severity: Failure severity (0 = nominal).

    Returns:
        ``{"name", "severity", "seed", "expected_condition", "conditions": [{name, t_s_first, evidence}],
        "detected", "detection_time_s", "fix", "failing": metrics, "fixed": metrics, "fixed_conditions",
        "diagnosis", "diagnosis_time_s", "plot"}`` (``diagnosis``: the condition the fixed run should name).
    """
    if name not in FAILURES:
        raise ValueError(f"unknown failure {name!r}; known: {sorted(FAILURES)}")
    spec = FAILURES[name]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bad = run_stream(synthesize_stream(spec.config(severity), seed))
    cfg_fix, prm_fix = spec.fixed(severity)
    good = run_stream(synthesize_stream(cfg_fix, seed), prm_fix)
    plot = out / f"{name}_error.png"
    _plot(plot, f"{name} (severity {severity})", {"failing": bad, f"fix: {spec.fix}": good})
    conds = bad.run.monitor.report()
    return {
        "name": name,
        "severity": float(severity),
        "seed": int(seed),
        "expected_condition": spec.condition,
        "conditions": [{"name": c.name, "t_s_first": c.t_s_first, "evidence": c.evidence} for c in conds],
        "detected": spec.condition in {c.name for c in conds} if spec.condition else None,
        "detection_time_s": bad.run.monitor.first_time(spec.condition) if spec.condition else None,
        "fix": spec.fix,
        "failing": bad.metrics,
        "fixed": good.metrics,
        "fixed_conditions": [c.name for c in good.run.monitor.report()],
        "diagnosis": spec.diagnosis or None,
        "diagnosis_time_s": good.run.monitor.first_time(spec.diagnosis) if spec.diagnosis else None,
        "plot": str(plot),
    }
