"""Command-line tool ``viotb`` (typer + rich).

Every command has ``--help``; ``--json`` prints one JSON object on stdout as the last line. Heavy modules
are imported inside each command so that ``viotb --help`` stays fast.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from viotb.envs.tools.sweep.cli import register as register_sweep

app = typer.Typer(add_completion=False, no_args_is_help=True, help="vio-testbed: VIO in the loop.")
_err = Console(stderr=True)

ProgressFn = Callable[[float, float], None]
"""Progress callback ``(done, total)`` passed to long-running library functions."""


@contextmanager
def _progress(description: str, enabled: bool = True) -> Iterator[ProgressFn]:
    """A rich progress bar on stderr, yielded as a ``(done, total)`` callback."""
    if not enabled:
        yield lambda done, total: None
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeRemainingColumn(),
        console=_err,
        transient=True,
    ) as bar:
        task = bar.add_task(description, total=1.0)

        def update(done: float, total: float) -> None:
            bar.update(task, completed=done, total=max(total, 1e-9))

        yield update


def _emit(result: dict, as_json: bool, title: str) -> None:
    """Print a result as a table (human) or one JSON line (``--json``)."""
    if as_json:
        sys.stdout.write(json.dumps(result, default=float) + "\n")
        return
    console = Console()
    console.print(f"[bold]{title}[/bold]")
    for key, value in result.items():
        console.print(f"  {key:<24} {value}")


def _fail(message: str) -> None:
    """Print a clear error and exit with status 2."""
    _err.print(f"[red]error:[/red] {message}")
    raise typer.Exit(code=2)


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
def record(
    scenario: str = typer.Argument(..., help="Scenario name (see `viotb scenarios`)."),
    out: Path = typer.Option(..., "--out", help="Output folder; a EuRoC ASL tree is written to OUT/mav0."),
    seed: int = typer.Option(0, "--seed", help="Random seed (IMU noise, pixel noise, drops)."),
    seconds: float | None = typer.Option(None, "--seconds", help="Duration (s); scenario default if unset."),
    severity: float | None = typer.Option(None, "--severity", help="Severity of a fail-* scenario."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Simulate a scenario open loop and write a EuRoC ASL dataset."""
    from viotb.envs.data.record import record_scenario

    if seconds is not None and seconds <= 0:
        _fail(f"--seconds must be positive, got {seconds}")
    try:
        with _progress(f"record {scenario}", not as_json) as progress:
            result = record_scenario(
                scenario, out, seed=seed, seconds=seconds, progress=progress, severity=severity
            )
    except (ValueError, FileNotFoundError) as exc:
        _fail(str(exc))
    _emit(result, as_json, f"recorded {scenario} -> {out}")


@app.command("eval")
def eval_(
    dataset: Path = typer.Argument(..., help="EuRoC-layout folder (containing mav0/, or mav0 itself)."),
    estimator: str = typer.Option("msckf", "--estimator", help="msckf | window | imu-only | ground-truth."),
    out: Path = typer.Option(Path("viotb_out/eval"), "--out", help="Output folder for the TUM files."),
    frontend: str = typer.Option("klt", "--frontend", help="klt (images) | sim (recorded landmarks, fast)."),
    max_frames: int | None = typer.Option(None, "--max-frames", help="Stop after this many frames."),
    loop_closure: bool = typer.Option(False, "--loop-closure", help="Loop closure (loop_closures.csv)."),
    map_in: Path | None = typer.Option(None, "--map-in", help="Start in this saved map's frame."),
    map_out: Path | None = typer.Option(None, "--map-out", help="Save the loop-closure map here (.npz)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Run an estimator on a EuRoC folder, write TUM trajectories and print ATE/RPE/NEES/timing."""
    from viotb.envs.data.evaluate import EvalOptions, evaluate_dataset
    from viotb.envs.run.loop_glue import loop_options

    try:
        loop = loop_options(loop_closure, map_in, map_out)
    except ValueError as exc:
        _fail(str(exc))
    opts = EvalOptions(estimator=estimator, frontend=frontend, max_frames=max_frames, loop=loop)
    try:
        with _progress(f"eval {estimator}", not as_json) as progress:
            result = evaluate_dataset(dataset, out, opts, progress)
    except (ValueError, FileNotFoundError) as exc:
        _fail(str(exc))
    _emit(result, as_json, f"{estimator} on {dataset} -> {out}")


@app.command()
def fly(
    scenario: str = typer.Argument(..., help="Closed-loop scenario (see `viotb scenarios`)."),
    estimator: str = typer.Option("msckf", "--estimator", help="msckf | window | imu-only | ground-truth."),
    seconds: float | None = typer.Option(None, "--seconds", help="Flight duration (s)."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    frontend: str = typer.Option("klt", "--frontend", help="klt (rendered images) | sim (fast mode)."),
    out: Path | None = typer.Option(None, "--out", help="Write plots (PNG) and metrics.json here."),
    calibrate: bool = typer.Option(
        False, "--calibrate", help="Estimate the camera-IMU time offset and extrinsics online (MSCKF)."
    ),
    severity: float | None = typer.Option(None, "--severity", help="Severity of a fly-fail-* scenario."),
    loop_closure: bool = typer.Option(
        False, "--loop-closure", help="Loop closure; the controller gets the corrected pose (needs klt)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Fly a closed-loop scenario with the estimator in the loop."""
    from viotb.envs.run.fly import fly as run_fly

    if seconds is not None and seconds <= 0:
        _fail(f"--seconds must be positive, got {seconds}")
    try:
        with _progress(f"fly {scenario}", not as_json) as progress:
            result, log = run_fly(
                scenario,
                estimator,
                seconds,
                seed,
                frontend,
                progress,
                online_calibration=calibrate or None,
                severity=severity,
                loop_closure=loop_closure,
            )
    except ValueError as exc:
        _fail(str(exc))
    if out is not None:
        from viotb.envs.tools.viz import save_plots

        out.mkdir(parents=True, exist_ok=True)
        result["plots"] = [str(p) for p in save_plots(log, out)]
        (out / "metrics.json").write_text(json.dumps(result, indent=2, default=float))
    _emit(result, as_json, f"flew {scenario} on {estimator}")


@app.command()
def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", help="Output folder for plots and demo.rrd."),
    scenario: str = typer.Option("fly-hover", "--scenario", help="Closed-loop scenario."),
    seconds: float | None = typer.Option(None, "--seconds", help="Flight duration (s)."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """The default closed-loop VIO flight, with PNG plots and a rerun recording."""
    from viotb.envs.run.fly import fly as run_fly
    from viotb.envs.tools.viz import RerunRecorder, save_plots

    out.mkdir(parents=True, exist_ok=True)
    recorder = RerunRecorder(out / "demo.rrd")
    try:
        with _progress(f"demo {scenario}", not as_json) as progress:
            result, log = run_fly(scenario, "msckf", seconds, seed, "klt", progress, on_tick=recorder)
    except ValueError as exc:
        _fail(str(exc))
    finally:
        recorder.close()
    plots = save_plots(log, out)
    result["recording"] = str(out / "demo.rrd")
    result["plots"] = [str(p) for p in plots]
    (out / "metrics.json").write_text(json.dumps(result, indent=2, default=float))
    if not as_json:
        _err.print(f"plots: {', '.join(str(p) for p in plots)}")
        _err.print(f"recording: {out / 'demo.rrd'}  (view with: rerun {out / 'demo.rrd'})")
    _emit(result, as_json, f"demo {scenario}")


@app.command()
def bench(
    section: list[str] = typer.Option(
        None, "--section", help="render | record | estimator | closed_loop (repeatable; all by default)."
    ),
    seconds: float = typer.Option(10.0, "--seconds", help="Simulated seconds of each timed run."),
    repeats: int = typer.Option(3, "--repeats", help="Repeats per timed figure (medians reported)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Speed benchmarks: render ms/frame, physics steps/s, record/closed-loop real-time factors."""
    from viotb.envs.tools.bench import SECTIONS, run_bench

    try:
        with _progress("bench", not as_json) as progress:
            result = run_bench(tuple(section) if section else SECTIONS, seconds, repeats, progress)
    except ValueError as exc:
        _fail(str(exc))
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
        _fail(str(exc))
    if as_json:
        sys.stdout.write(json.dumps({"passed": passed, "rows": rows, "result": result}, default=float) + "\n")
    else:
        table = Table(title=f"regress vs {path}" + (" (baseline updated)" if update else ""))
        for col in ("case", "metric", "value", "baseline", "limit", "ok"):
            table.add_column(col)
        for r in rows:
            vals = (r["value"], r["baseline"], r["limit"])
            fmt = [f"{x:.4g}" if isinstance(x, float) else str(x) for x in vals]
            table.add_row(r["case"], r["metric"], *fmt, "ok" if r["ok"] else "[red]REGRESSION[/red]")
        _err.print(table)
    if not passed:
        raise typer.Exit(1)


@app.command()
def failures(
    out: Path = typer.Option(Path("failures_out"), "--out", help="Folder for the plots and report.json."),
    name: list[str] = typer.Option(None, "--name", help="Failure scenario(s) (default: all fail-*)."),
    seed: int = typer.Option(0, help="Seed of every stream."),
    severity: float = typer.Option(1.0, help="Severity knob (0 nominal, 1 default, larger worse)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
) -> None:
    """Run each failure mode and its fix: error-vs-time plot, what the monitor said and when, the fix."""
    from rich.table import Table
    from viotb.envs.scenarios.failures import FAILURES
    from viotb.envs.tools.failure_report import failure_report

    names = list(name) if name else list(FAILURES)
    unknown = [n for n in names if n not in FAILURES]
    if unknown:
        _fail(f"unknown failure scenario(s) {unknown}; known: {sorted(FAILURES)}")
    try:
        reports = [failure_report(n, out, seed=seed, severity=severity) for n in names]
    except ValueError as exc:
        _fail(str(exc))
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(reports, indent=2, default=float) + "\n")
    if as_json:
        sys.stdout.write(json.dumps({"failures": reports}, default=float) + "\n")
        return
    table = Table(title=f"failure modes (seed {seed}, severity {severity}); plots in {out}")
    for col in ("scenario", "monitor said (first time)", "fix", "ATE failing", "ATE fixed", "fixed run said"):
        table.add_column(col)
    for r in reports:
        said = ", ".join(f"{c['name']} ({c['t_s_first']:.2f} s)" for c in r["conditions"]) or "nothing"
        ate = (f"{r['failing']['ate_m']:.3f} m", f"{r['fixed']['ate_m']:.3f} m")
        table.add_row(r["name"], said, r["fix"], *ate, ", ".join(r["fixed_conditions"]) or "nothing")
    Console().print(table)


register_sweep(app)  # viotb sweep, viotb sweep-report


def main() -> None:
    """Entry point of the ``viotb`` console script."""
    app()


if __name__ == "__main__":
    main()
