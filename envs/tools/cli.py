"""Command-line tool ``viotb`` (typer + rich).

Every command has ``--help``; ``--json`` prints one JSON object on stdout as the last line. Heavy modules
are imported inside each command so that ``viotb --help`` stays fast.
"""

from __future__ import annotations

import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from viotb.envs.tools.cli_common import (
    check_out,
    err_console,
    fail,
    overwrite_option,
    progress,
    quiet_option,
    seed_option,
)
from viotb.envs.tools.cli_common import emit as _emit
from viotb.envs.tools.cli_data import register as register_data
from viotb.envs.tools.cli_fly import register as register_fly
from viotb.envs.tools.headset_cli import register as register_headset
from viotb.envs.tools.jsonout import dumps_strict
from viotb.envs.tools.sweep.cli import register as register_sweep

app = typer.Typer(add_completion=False, no_args_is_help=True, help="vio-testbed: VIO in the loop.")


@app.command()
def scenarios(as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout.")) -> None:
    """List the scenarios with one-line descriptions."""
    from viotb.envs.scenarios.registry import list_scenarios

    items = list_scenarios()
    if as_json:
        _emit({"scenarios": items}, True, "")
        return
    console = Console()
    for item in items:
        kind = escape(f"[{item['kind']}]")
        console.print(f"[bold]{item['name']:<28}[/bold] {kind:<9} {item['description']}")


@app.command()
def bench(
    section: list[str] = typer.Option(
        None, "--section", help="render | record | estimator | closed_loop | gym (repeatable; all by default)"
    ),
    seconds: float = typer.Option(10.0, "--seconds", help="Simulated seconds of each timed run."),
    repeats: int = typer.Option(3, "--repeats", min=1, help="Repeats per timed figure (medians reported)."),
    quiet: bool = quiet_option(),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Speed benchmarks: render ms/frame, physics steps/s, record/closed-loop/Gymnasium real-time factors."""
    from viotb.envs.tools.bench import SECTIONS, run_bench

    try:
        with progress("bench", not quiet) as report:
            result = run_bench(tuple(section) if section else SECTIONS, seconds, repeats, report)
    except ValueError as exc:
        fail(str(exc))
    _emit(result, as_json, "bench")


@app.command()
def regress(
    update: bool = typer.Option(False, "--update", help="Rewrite the baseline with this run (deliberate)."),
    full: bool = typer.Option(False, "--full", help="Run the full set (adds longer and faster cases)."),
    baseline: Path = typer.Option(None, "--baseline", help="Baseline JSON (default benchmarks/...)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Drift regression suite: seeded runs vs the committed baseline; exits 1 on a regression."""
    from rich.table import Table
    from viotb.envs.tools.regress import DEFAULT_BASELINE
    from viotb.envs.tools.regress import regress as run_regress

    path = baseline if baseline is not None else DEFAULT_BASELINE
    try:
        passed, rows, result = run_regress(path, update=update, full=full)
    except (ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    if as_json:
        sys.stdout.write(dumps_strict({"passed": passed, "rows": rows, "result": result}) + "\n")
    else:
        table = Table(title=f"regress vs {path}" + (" (baseline updated)" if update else ""))
        for col in ("case", "metric", "value", "baseline", "limit", "ok"):
            table.add_column(col)
        for r in rows:
            vals = (r["value"], r["baseline"], r["limit"])
            fmt = [f"{x:.4g}" if isinstance(x, float) else str(x) for x in vals]
            table.add_row(r["case"], r["metric"], *fmt, "ok" if r["ok"] else "[red]REGRESSION[/red]")
        err_console().print(table)
    if not passed:
        raise typer.Exit(1)


@app.command()
def failures(
    out: Path = typer.Option(Path("failures_out"), "--out", help="Folder for the plots and report.json."),
    name: list[str] = typer.Option(None, "--name", help="Failure scenario(s) (default: all fail-*)."),
    seed: int = seed_option(),
    severity: float = typer.Option(1.0, help="Severity knob (0 nominal, 1 default, larger worse)."),
    overwrite: bool = overwrite_option(),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Run each failure mode and its fix: error-vs-time plot, what the monitor said and when, the fix."""
    from rich.table import Table
    from viotb.envs.scenarios.failures import FAILURES
    from viotb.envs.tools.failure_report import failure_report
    from viotb.envs.tools.outdir import atomic_out_dir

    names = list(name) if name else list(FAILURES)
    unknown = [n for n in names if n not in FAILURES]
    if unknown:
        fail(f"unknown failure scenario(s) {unknown}; known: {sorted(FAILURES)}")
    check_out(out, overwrite)
    with atomic_out_dir(out, overwrite) as tmp:
        try:
            reports = [failure_report(n, tmp, seed=seed, severity=severity) for n in names]
        except ValueError as exc:
            fail(str(exc))
        for r in reports:
            r["plot"] = str(out / Path(r["plot"]).name)
        (tmp / "report.json").write_text(dumps_strict({"failures": reports}, indent=2) + "\n")
    if as_json:
        sys.stdout.write(dumps_strict({"failures": reports}) + "\n")
        return
    table = Table(title=f"failure modes (seed {seed}, severity {severity}); plots in {out}")
    for col in ("scenario", "monitor said (first time)", "fix", "ATE failing", "ATE fixed", "fixed run said"):
        table.add_column(col)
    for r in reports:
        said = ", ".join(f"{c['name']} ({c['t_s_first']:.2f} s)" for c in r["conditions"]) or "nothing"
        ate = (f"{r['failing']['ate_m']:.3f} m", f"{r['fixed']['ate_m']:.3f} m")
        table.add_row(r["name"], said, r["fix"], *ate, ", ".join(r["fixed_conditions"]) or "nothing")
    Console().print(table)


register_data(app)  # viotb record, viotb eval
register_fly(app)  # viotb fly, viotb demo
register_sweep(app)  # viotb sweep, viotb sweep-report
register_headset(app)  # viotb headset


def main() -> None:
    """Entry point of the ``viotb`` console script."""
    app()


if __name__ == "__main__":
    main()
